"""Calibrated minimal solvers and RANSAC (OpenGV, in C++) in COLMAP's conventions, for
single cameras and camera rigs (generalized solvers), the mapper's bundle adjuster for
calibrated cameras (`bundle_adjust`), and its compiled search kernels
(`largest_per_row`, `largest_per_column`).

Conventions, once:
- Inputs are undistorted bearing vectors in any direction (behind the image plane too):
  (N, 3) rays, as `pycolmap.Camera.cam_ray_from_img` gives them for every camera model,
  or (N, 2) normalized image coordinates (x/z, y/z); a rig's rays are each in the frame
  of the camera that made them.
- Thresholds (`max_error`) are angles in radians, one for all correspondences or one
  each (a pixel threshold times the camera's angular resolution at the keypoint), for
  single cameras and rigs alike: absolute poses bound the reprojection error on the plane
  tangent to each ray (through its rig camera), relative poses the angular Sampson error
  (of each pair's camera pair).
- Poses are `pycolmap.Rigid3d`: x_to = R x_from + t (cam2_from_cam1, cam_from_world;
  rig2_from_rig1, rig_from_world, cams_from_rig for rigs).
- E is COLMAP's: x2^T E x1 = 0 for rays (or homogeneous normalized points).
"""

from solvers.api import (
    AbsolutePoseResult,
    BundleAdjustmentResult,
    EstimationError,
    GeneralizedAbsolutePoseResult,
    GeneralizedRelativePoseResult,
    RelativePoseResult,
    absolute_pose,
    bundle_adjust,
    five_point,
    generalized_absolute_pose,
    generalized_relative_pose,
    largest_per_column,
    largest_per_row,
    p3p,
    relative_pose,
    triangulate,
    triangulate_tracks,
)

__all__ = [
    "AbsolutePoseResult",
    "BundleAdjustmentResult",
    "EstimationError",
    "GeneralizedAbsolutePoseResult",
    "GeneralizedRelativePoseResult",
    "RelativePoseResult",
    "absolute_pose",
    "bundle_adjust",
    "five_point",
    "generalized_absolute_pose",
    "generalized_relative_pose",
    "largest_per_column",
    "largest_per_row",
    "p3p",
    "relative_pose",
    "triangulate",
    "triangulate_tracks",
]
