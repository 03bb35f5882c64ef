"""colmap-ext: camera poses from images taken by a camera with known intrinsics.

A drop-in for `colmap mapper` when the intrinsics are calibrated: OpenGV minimal
solvers (5-point relative pose, P3P) in RANSAC, guided matching, and pycolmap
bundle adjustment, writing ordinary COLMAP models.
"""

# pycolmap 4.2.1's wheel breaks zlib (PNG writing) in a process that loads it before
# NumPy: load NumPy first whatever our modules import (README, "Known problem").
import numpy  # noqa: F401

__version__ = "0.1.0"
