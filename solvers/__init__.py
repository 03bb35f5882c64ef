"""Calibrated minimal solvers and RANSAC (OpenGV, in C++) in COLMAP's conventions, for
single cameras and camera rigs (generalized solvers), and
the mapper's one compiled search kernel (`largest_per_row`).

Conventions, once:
- Inputs are undistorted bearing vectors: (N, 3) rays or (N, 2) normalized image
  coordinates (x/z, y/z). `pycolmap.Camera.cam_from_img` gives the latter.
- Thresholds (`max_error`) are in normalized image units: pixels / focal length.
- Poses are `pycolmap.Rigid3d`: x_to = R x_from + t (cam2_from_cam1, cam_from_world;
  rig2_from_rig1, rig_from_world, cams_from_rig for rigs).
- E is COLMAP's: x2^T E x1 = 0 for homogeneous normalized points.
"""

from solvers.api import (
    AbsolutePoseResult,
    EstimationError,
    GeneralizedAbsolutePoseResult,
    GeneralizedRelativePoseResult,
    RelativePoseResult,
    absolute_pose,
    five_point,
    generalized_absolute_pose,
    generalized_relative_pose,
    largest_per_row,
    p3p,
    relative_pose,
    triangulate,
    triangulate_tracks,
)

__all__ = [
    "AbsolutePoseResult",
    "EstimationError",
    "GeneralizedAbsolutePoseResult",
    "GeneralizedRelativePoseResult",
    "RelativePoseResult",
    "absolute_pose",
    "five_point",
    "generalized_absolute_pose",
    "generalized_relative_pose",
    "largest_per_row",
    "p3p",
    "relative_pose",
    "triangulate",
    "triangulate_tracks",
]
