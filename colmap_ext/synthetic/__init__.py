"""Synthetic data with known ground truth: scenes, rendered images, and COLMAP databases.

- `ring_scene`, `trajectory_scene`, `driving_scene`: a calibrated camera, known poses, textured quads;
  `rig_scene`: a rig's cameras (`side_by_side_rig`) at a scene's poses.
- `render_images`: PNG views of a scene, ray-cast through the distorted camera model.
- `write_par_file`, `write_ground_truth`: the true poses as Middlebury `*_par.txt` / COLMAP model;
  `write_placeholder_images`: black files under the images' names, for a database without images.
- `scene_points`, `points_for_keypoints`, `write_synthetic_database`: a COLMAP database of
  projected points (keypoints, descriptors, matches with outliers), without images;
  `sequential_pairs` restricts its matches to a sequence's neighbours; `write_rig_config`: COLMAP's
  rig configuration of a rig scene, to apply to its database; `true_tracks_reconstruction`: the
  truth's poses and points with every true observation (a maximum-likelihood reference's start).
"""

from colmap_ext.synthetic.database import (
    SyntheticDatabase,
    points_for_keypoints,
    scene_points,
    sequential_pairs,
    true_tracks_reconstruction,
    write_rig_config,
    write_synthetic_database,
)
from colmap_ext.synthetic.render import (
    ground_truth_reconstruction,
    render_images,
    write_ground_truth,
    write_par_file,
    write_placeholder_images,
)
from colmap_ext.synthetic.scene import (Quad, Scene, default_camera, driving_scene, rig_scene, ring_scene,
                                       side_by_side_rig, trajectory_scene)

__all__ = [
    "Quad",
    "Scene",
    "SyntheticDatabase",
    "default_camera",
    "driving_scene",
    "ground_truth_reconstruction",
    "points_for_keypoints",
    "render_images",
    "rig_scene",
    "ring_scene",
    "scene_points",
    "sequential_pairs",
    "side_by_side_rig",
    "trajectory_scene",
    "true_tracks_reconstruction",
    "write_ground_truth",
    "write_par_file",
    "write_placeholder_images",
    "write_rig_config",
    "write_synthetic_database",
]
