"""colmap-ext: camera poses from images taken by a camera with known intrinsics.

A drop-in for `colmap mapper` when the intrinsics are calibrated: OpenGV minimal
solvers (5-point relative pose, P3P) in RANSAC, guided matching, and pycolmap
bundle adjustment, writing ordinary COLMAP models.
"""

# pycolmap 4.2.1's wheel breaks zlib (PNG writing) in a process that loads it before
# NumPy: load NumPy first whatever our modules import (README, "Known problem").
import numpy  # noqa: F401

__version__ = "0.1.0"


def __getattr__(name: str):
    """`colmap_ext.incremental_mapping` (api.py), imported on first use: it loads pycolmap,
    which `import colmap_ext` (and so every command) should not pay for."""
    if name == "incremental_mapping":
        from colmap_ext.api import incremental_mapping

        return incremental_mapping
    raise AttributeError(f"module 'colmap_ext' has no attribute {name!r}")
