"""The calibrated incremental mapper: a drop-in for `colmap mapper` with known intrinsics.

One module per step of the method (SPEC.md, steps 4 to 7):
- `model`: the growing model, a pycolmap.Reconstruction (cameras, rigs, frames, poses,
  points, tracks), and the rays and indexes the steps derive from it
- `two_view`: verified matches, from the database or our 5-point RANSAC
- `initial_pair`: choosing and reconstructing the first two images
- `registration`: 2D-3D correspondences and P3P (a rig's frame: GP3P) RANSAC for the next frame
- `guided_matching`: visually and geometrically compatible features in registered images
- `triangulation`: new points and longer tracks from those features
- `bundle_adjustment`: local and global refinement: our calibrated adjuster
  (solvers.bundle_adjust), pycolmap's Ceres for the finished model
- `filtering`: dropping incompatible observations, weakly supported points and ill-posed images
- `merging`: joining models that fell apart, by a similarity two images agree on
- `refinement`: what the loop and the refinement of finished models share (neighbours,
  triangulation of images, adjustment with filtering); refinement after a merge, and
  retriangulation
- `pipeline`: the loop that runs them, and `run()`

Each step takes the option components it uses (options.py), as COLMAP's steps do; the
run's settings, the RANSAC seed and the thread count, are passed to the steps that need
them.
"""

from colmap_ext.mapper.options import MapperOptions
from colmap_ext.mapper.pipeline import run

__all__ = ["MapperOptions", "run"]
