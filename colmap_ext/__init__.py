"""colmap-ext: camera poses from images taken by a camera with known intrinsics.

A drop-in for `colmap mapper` when the intrinsics are calibrated: OpenGV minimal
solvers (5-point relative pose, P3P) in RANSAC, guided matching, and pycolmap
bundle adjustment, writing ordinary COLMAP models.
"""

__version__ = "0.1.0"
