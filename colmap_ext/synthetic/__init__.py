"""Synthetic data with known ground truth: scenes, rendered images, and COLMAP databases.

- `ring_scene`, `trajectory_scene`: a calibrated camera, known poses, textured quads.
- `render_images`: PNG views of a scene, ray-cast through the distorted camera model.
- `write_par_file`, `write_ground_truth`: the true poses as Middlebury `*_par.txt` / COLMAP model.
- `scene_points`, `write_synthetic_database`: a COLMAP database of projected points
  (keypoints, descriptors, matches with outliers), without images.
"""

from colmap_ext.synthetic.database import SyntheticDatabase, scene_points, write_synthetic_database
from colmap_ext.synthetic.render import (
    ground_truth_reconstruction,
    render_images,
    write_ground_truth,
    write_par_file,
)
from colmap_ext.synthetic.scene import Quad, Scene, default_camera, ring_scene, trajectory_scene

__all__ = [
    "Quad",
    "Scene",
    "SyntheticDatabase",
    "default_camera",
    "ground_truth_reconstruction",
    "render_images",
    "ring_scene",
    "scene_points",
    "trajectory_scene",
    "write_ground_truth",
    "write_par_file",
    "write_synthetic_database",
]
