"""Checked, typed wrappers over the compiled module `solvers._opengv`."""

from __future__ import annotations

import secrets
from dataclasses import dataclass

import numpy as np
import pycolmap

from solvers import _opengv
from solvers.checks import (as_camera_index, as_points3D, as_pose_rows, as_rays, as_thresholds,
                            check_choice, check_rig_has_baseline, check_same_length)

RELATIVE_METHODS = ("stewenius", "nister")
ABSOLUTE_METHODS = ("kneip", "gao")
GENERALIZED_RELATIVE_METHODS = ("sixpt", "fivept_plus_one", "seventeenpt")


class EstimationError(RuntimeError):
    """RANSAC found no model that enough correspondences agree with (degenerate data)."""


@dataclass(frozen=True, kw_only=True)
class RansacStatistics:
    """What every estimate reports besides its model: the correspondences it fits."""

    inlier_mask: np.ndarray  # (N,) bool
    num_inliers: int
    num_iterations: int

    @classmethod
    def fields_from(cls, out: dict) -> dict:
        """These fields from the compiled module's output."""
        return {"inlier_mask": out["inlier_mask"], "num_inliers": out["num_inliers"],
                "num_iterations": out["num_iterations"]}


@dataclass(frozen=True)
class RelativePoseResult(RansacStatistics):
    cam2_from_cam1: pycolmap.Rigid3d  # unit translation
    E: np.ndarray  # (3, 3), x2^T E x1 = 0


@dataclass(frozen=True)
class AbsolutePoseResult(RansacStatistics):
    cam_from_world: pycolmap.Rigid3d


@dataclass(frozen=True)
class GeneralizedRelativePoseResult(RansacStatistics):
    rig2_from_rig1: pycolmap.Rigid3d  # metric: the rig's baseline fixes the scale


@dataclass(frozen=True)
class GeneralizedAbsolutePoseResult(RansacStatistics):
    rig_from_world: pycolmap.Rigid3d


def rigid3d(R: np.ndarray, t: np.ndarray) -> pycolmap.Rigid3d:
    return pycolmap.Rigid3d(pycolmap.Rotation3d(np.asarray(R)), np.asarray(t, dtype=np.float64))


def _ransac_kwargs(max_error, num_data: int, max_iterations: int, min_iterations: int,
                   confidence: float, seed: int | None) -> dict:
    max_errors = as_thresholds(max_error, num_data)
    if int(max_iterations) < 1 or int(min_iterations) < 0 or min_iterations > max_iterations:
        raise ValueError("need 0 <= min_iterations <= max_iterations and max_iterations >= 1")
    if not 0.0 < confidence < 1.0:
        raise ValueError(f"confidence must be in (0, 1), got {confidence}")
    if seed is None:
        seed = secrets.randbits(64)
    elif not 0 <= int(seed) < 2**64:
        raise ValueError(f"seed must be a non-negative 64-bit integer, got {seed}")
    return dict(max_errors=max_errors, max_iterations=int(max_iterations),
                min_iterations=int(min_iterations), confidence=float(confidence), seed=int(seed))


def relative_pose(rays1, rays2, *, max_error: float | np.ndarray, method: str = "stewenius",
                  max_iterations: int = 10000, min_iterations: int = 10,
                  confidence: float = 0.9999, min_num_inliers: int = 15,
                  seed: int | None = None) -> RelativePoseResult:
    """cam2_from_cam1 and E by 5-point LO-MSAC on rays in any direction; `max_error`
    bounds each pair's angular Sampson error (radians: the angle by which the two rays
    must turn to meet, to first order), one for all pairs or one per pair.

    `method` "stewenius" (default) or "nister": the same model, but OpenGV's Nister solver
    is slower and misses the true solution of a sample in a few percent of cases.

    The pose is refined on the inliers, and the cheirality check picks the one of E's
    four decompositions that puts the inliers in front of both cameras. Raises
    EstimationError when fewer than `min_num_inliers` correspondences agree.
    """
    check_choice("method", method, RELATIVE_METHODS)
    f1, f2 = as_rays(rays1, "rays1"), as_rays(rays2, "rays2")
    check_same_length(f1, f2, "rays1", "rays2", minimum=5)
    out = _opengv.relative_pose(f1, f2, method, **_ransac_kwargs(
        max_error, len(f1), max_iterations, min_iterations, confidence, seed))
    if not out["success"] or out["num_inliers"] < max(5, min_num_inliers):
        raise EstimationError(f"no relative pose: {out['num_inliers']} of {len(f1)} "
                              f"correspondences agree (need {max(5, min_num_inliers)})")
    return RelativePoseResult(rigid3d(out["R"], out["t"]), out["E"],
                              **RansacStatistics.fields_from(out))


def absolute_pose(rays, points3D, *, max_error: float | np.ndarray, method: str = "kneip",
                  max_iterations: int = 10000, min_iterations: int = 10,
                  confidence: float = 0.9999, min_num_inliers: int = 6,
                  seed: int | None = None) -> AbsolutePoseResult:
    """cam_from_world by P3P LO-MSAC, refined on the inliers (non-linear, OpenGV).

    `max_error` bounds each reprojection error (radians, one for all or one per ray):
    the angle between a ray and its point, as the point's offset on the plane tangent
    to the unit sphere at the ray (tan of the angle); a point 90 degrees or more from
    its ray never fits, so rays may point anywhere, behind the image plane too. Raises
    EstimationError when fewer than `min_num_inliers` correspondences agree.
    """
    check_choice("method", method, ABSOLUTE_METHODS)
    f, X = as_rays(rays, "rays"), as_points3D(points3D, "points3D")
    check_same_length(f, X, "rays", "points3D", minimum=3)
    out = _opengv.absolute_pose(f, X, method, **_ransac_kwargs(
        max_error, len(f), max_iterations, min_iterations, confidence, seed))
    if not out["success"] or out["num_inliers"] < max(4, min_num_inliers):
        raise EstimationError(f"no absolute pose: {out['num_inliers']} of {len(f)} "
                              f"correspondences agree (need {max(4, min_num_inliers)})")
    return AbsolutePoseResult(rigid3d(out["R"], out["t"]),
                              **RansacStatistics.fields_from(out))


def generalized_relative_pose(rays1, camera_index1, rays2, camera_index2,
                              cams_from_rig: list[pycolmap.Rigid3d], *,
                              max_error: float | np.ndarray, method: str = "fivept_plus_one",
                              max_iterations: int = 10000,
                              min_iterations: int = 10, confidence: float = 0.9999,
                              min_num_inliers: int = 15,
                              seed: int | None = None) -> GeneralizedRelativePoseResult:
    """rig2_from_rig1 between two frames of one camera rig, by LO-MSAC over OpenGV's
    generalized relative pose solvers.

    Correspondence i is ray `rays1[i]` of camera `camera_index1[i]` in frame 1 and
    `rays2[i]` of camera `camera_index2[i]` in frame 2; `cams_from_rig[c]` is camera c's
    pose in the rig. The translation is metric: the rig needs cameras at different
    centres. `max_error` bounds each pair's angular Sampson error in its camera pair
    (radians, one for all pairs or one per pair, as `relative_pose`'s). `method`:
    - "fivept_plus_one" (default): the 5-point solver on five correspondences of one
      camera pair, the scale from a sixth of another pair; needs a camera pair with five
      correspondences and another with one (a rig moving, its cameras seeing the scene
      again), and is the fastest by far (docs/experiments/benchmarks-history.md,
      "Solvers").
    - "sixpt": Stewenius' generalized 6-point solver, for any correspondences; each
      sample takes milliseconds.
    - "seventeenpt": Li's linear 17 points, whose sample needs far more iterations with
      outliers.
    Samples of a single camera pair are skipped: they leave the scale open. The pose is
    refined on the inliers (angular Sampson errors, Levenberg-Marquardt). Raises EstimationError
    when fewer than `min_num_inliers` correspondences agree.
    """
    check_choice("method", method, GENERALIZED_RELATIVE_METHODS)
    f1, f2 = as_rays(rays1, "rays1"), as_rays(rays2, "rays2")
    rig = as_pose_rows(cams_from_rig, "cams_from_rig")
    check_rig_has_baseline(rig, "cams_from_rig")
    c1 = as_camera_index(camera_index1, "camera_index1", len(rig))
    c2 = as_camera_index(camera_index2, "camera_index2", len(rig))
    sample_size = 17 if method == "seventeenpt" else 6
    check_same_length(f1, f2, "rays1", "rays2", minimum=sample_size)
    check_same_length(f1, c1, "rays1", "camera_index1")
    check_same_length(f2, c2, "rays2", "camera_index2")
    out = _opengv.generalized_relative_pose(f1, c1, f2, c2, rig, method, **_ransac_kwargs(
        max_error, len(f1), max_iterations, min_iterations, confidence, seed))
    need = max(sample_size, min_num_inliers)
    if not out["success"] or out["num_inliers"] < need:
        raise EstimationError(f"no generalized relative pose: {out['num_inliers']} of "
                              f"{len(f1)} correspondences agree (need {need})")
    return GeneralizedRelativePoseResult(rigid3d(out["R"], out["t"]),
                                         **RansacStatistics.fields_from(out))


def generalized_absolute_pose(rays, camera_index, points3D, cams_from_rig: list[pycolmap.Rigid3d],
                              *, max_error: float | np.ndarray, max_iterations: int = 10000,
                              min_iterations: int = 10, confidence: float = 0.9999,
                              min_num_inliers: int = 6,
                              seed: int | None = None) -> GeneralizedAbsolutePoseResult:
    """rig_from_world of a camera rig by GP3P (OpenGV) LO-MSAC, refined on the inliers.

    Ray `rays[i]` of camera `camera_index[i]` sees world point `points3D[i]`;
    `cams_from_rig[c]` is camera c's pose in the rig. `max_error` bounds the reprojection
    error on the plane tangent to each ray, through the observing camera (radians, one for
    all or one per ray, as `absolute_pose`'s). Raises EstimationError when fewer than
    `min_num_inliers` correspondences agree.
    """
    f, X = as_rays(rays, "rays"), as_points3D(points3D, "points3D")
    rig = as_pose_rows(cams_from_rig, "cams_from_rig")
    cameras = as_camera_index(camera_index, "camera_index", len(rig))
    check_same_length(f, X, "rays", "points3D", minimum=3)
    check_same_length(f, cameras, "rays", "camera_index")
    out = _opengv.generalized_absolute_pose(f, cameras, X, rig, **_ransac_kwargs(
        max_error, len(f), max_iterations, min_iterations, confidence, seed))
    need = max(4, min_num_inliers)
    if not out["success"] or out["num_inliers"] < need:
        raise EstimationError(f"no generalized absolute pose: {out['num_inliers']} of "
                              f"{len(f)} correspondences agree (need {need})")
    return GeneralizedAbsolutePoseResult(rigid3d(out["R"], out["t"]),
                                         **RansacStatistics.fields_from(out))


def five_point(rays1, rays2, *, method: str = "stewenius") -> list[np.ndarray]:
    """Every essential matrix (x2^T E x1 = 0, unit Frobenius norm) fitting five ray pairs."""
    check_choice("method", method, RELATIVE_METHODS)
    f1, f2 = as_rays(rays1, "rays1"), as_rays(rays2, "rays2")
    if len(f1) != 5 or len(f2) != 5:
        raise ValueError(f"five_point takes exactly 5 ray pairs, got {len(f1)} and {len(f2)}")
    return list(_opengv.five_point(f1, f2, method))


def p3p(rays, points3D, *, method: str = "kneip") -> list[pycolmap.Rigid3d]:
    """Every cam_from_world fitting three ray/point pairs (up to four)."""
    check_choice("method", method, ABSOLUTE_METHODS)
    f, X = as_rays(rays, "rays"), as_points3D(points3D, "points3D")
    if len(f) != 3 or len(X) != 3:
        raise ValueError(f"p3p takes exactly 3 ray/point pairs, got {len(f)} and {len(X)}")
    return [rigid3d(T[:, :3], T[:, 3]) for T in _opengv.p3p(f, X, method)]


def triangulate_tracks(cams_from_world: list[pycolmap.Rigid3d], view_index, point_index, rays,
                       *, num_points: int | None = None,
                       min_angle_deg: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """Linear multi-view triangulation of many points at once.

    Observation k sees point `point_index[k]` along `rays[k]` from camera
    `cams_from_world[view_index[k]]`. Returns (P, 3) world points and a bool mask of
    points in front of every observing camera whose widest pair of rays spans at
    least `min_angle_deg`. Points with fewer than two observations are invalid.
    """
    f = as_rays(rays, "rays")
    views = np.ascontiguousarray(view_index, dtype=np.int32).reshape(-1)
    points = np.ascontiguousarray(point_index, dtype=np.int32).reshape(-1)
    check_same_length(f, views, "rays", "view_index")
    check_same_length(f, points, "rays", "point_index")
    if num_points is None:
        num_points = int(points.max()) + 1 if len(points) else 0
    if len(views) and (views.min() < 0 or views.max() >= len(cams_from_world)):
        raise ValueError("view_index out of range of cams_from_world")
    if len(points) and (points.min() < 0 or points.max() >= num_points):
        raise ValueError("point_index out of range of num_points")
    if not np.isfinite(min_angle_deg) or min_angle_deg < 0:
        raise ValueError(f"min_angle_deg must be finite and >= 0, got {min_angle_deg}")
    poses = as_pose_rows(cams_from_world, "cams_from_world")
    return _opengv.triangulate_tracks(poses, views, points, f, int(num_points),
                                      float(min_angle_deg))


def triangulate(cam1_from_world: pycolmap.Rigid3d, cam2_from_world: pycolmap.Rigid3d,
                rays1, rays2, *, min_angle_deg: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """(N, 3) world points from ray pairs, and a mask of those in front of both cameras
    with a triangulation angle of at least `min_angle_deg`."""
    f1, f2 = as_rays(rays1, "rays1"), as_rays(rays2, "rays2")
    check_same_length(f1, f2, "rays1", "rays2")
    n = len(f1)
    index = np.arange(n, dtype=np.int32)
    return triangulate_tracks(
        [cam1_from_world, cam2_from_world],
        np.concatenate([np.zeros(n, np.int32), np.ones(n, np.int32)]),
        np.concatenate([index, index]), np.concatenate([f1, f2]),
        num_points=n, min_angle_deg=min_angle_deg)


def largest_per_row(values: np.ndarray, k: int, *, subset: np.ndarray | None = None,
                    k_subset: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Per row of `values` (n, m): the columns of its k largest values, largest first
    (the earlier column on ties, as numpy's argmax), and those values; with `subset`
    (column indices), the k_subset largest among those columns too (positions in
    `subset`, and values). Places beyond the columns there are hold -inf at column 0.
    One pass over each row, in C++ without the GIL: the mapper's nearest-descriptor
    search runs it on blocks of cosines."""
    values = np.ascontiguousarray(values, dtype=np.float32)
    if values.ndim != 2:
        raise ValueError(f"values must be 2-D, got shape {values.shape}")
    columns = np.ascontiguousarray(np.zeros(0) if subset is None else subset, dtype=np.int64)
    if k < 0 or k_subset < 0:
        raise ValueError(f"k and k_subset must be >= 0, got {k} and {k_subset}")
    return _opengv.largest_per_row(values, int(k), columns, int(k_subset))


def largest_per_column(values: np.ndarray, k: int, first_row: int, index: np.ndarray,
                       best: np.ndarray) -> None:
    """Merges the k largest values of each column of `values` (n, m), whose rows are rows
    `first_row`.. of a matrix taken block by block, into `index` (m, k) int64 and `best`
    (m, k) float32, largest first, in place: those of the blocks before, -inf at row 0
    where none yet. The earlier row wins ties, so the result is largest_per_row's on the
    whole matrix transposed, without transposing it."""
    values = np.ascontiguousarray(values, dtype=np.float32)
    if values.ndim != 2:
        raise ValueError(f"values must be 2-D, got shape {values.shape}")
    for name, array, dtype in (("index", index, np.int64), ("best", best, np.float32)):
        if array.dtype != dtype or not array.flags.c_contiguous or \
                array.shape != (values.shape[1], k):
            raise ValueError(f"{name} must be a C-contiguous ({values.shape[1]}, {k}) "
                             f"{np.dtype(dtype).name} array")
    _opengv.largest_per_column(values, int(k), int(first_row), index, best)


@dataclass
class BundleAdjustmentResult:
    """The adjusted rig_from_world of every frame and position of every point, and Ceres's
    figures: iterations (successful and unsuccessful steps), the cost
    (1/2 sum of the loss of the squared pixel residuals) before and after."""

    rigs_from_world: list[pycolmap.Rigid3d]
    points3D: np.ndarray
    iterations: int
    initial_cost: float
    final_cost: float


BUNDLE_LOSSES = ("trivial", "cauchy", "huber", "soft_l1")


def bundle_adjust(rigs_from_world: list[pycolmap.Rigid3d], free_parameters,
                  sensors_from_rig: list[pycolmap.Rigid3d], image_frame, points3D,
                  point_variable, observation_image, observation_point, rays,
                  pixels_from_tangent, *, loss: str = "trivial", loss_scale: float = 1.0,
                  max_iterations: int = 50, gradient_tolerance: float = 1.0,
                  function_tolerance: float = 0.0, max_step_scale: float = 16.0,
                  initial_trust_region_radius: float = 1e4,
                  num_threads: int = 1) -> BundleAdjustmentResult:
    """Bundle adjustment of frame poses and points with calibrated cameras (C++).

    Image i is camera `sensors_from_rig[i]` (held constant) of frame `image_frame[i]`;
    a frame's parameters (rotation x3, then translation x3, (F, 6) bools) change where
    `free_parameters` says, a point where `point_variable`. Observation k is point
    `observation_point[k]` seen by image `observation_image[k]` along the unit ray
    `rays[k]`; its residual is `pixels_from_tangent[k]` (2x3, the camera model's pixels
    per unit of the plane tangent to the ray at unit distance) times the point's offset
    from the ray on that plane: the reprojection error in pixels to first order, for any
    camera model. Levenberg-Marquardt on the Schur complement of the points, with Ceres's
    losses (scale in pixels), step control and stopping rules; each accepted step is tried
    at 2, 4, ... up to `max_step_scale` times its length while the cost falls (under a
    robust loss a reweighted step falls short); the first step damped by the inverse of
    `initial_trust_region_radius` (Ceres's). `num_threads` share the residuals and the
    Schur complement. Raises EstimationError if no finite cost comes out.
    """
    check_choice("loss", loss, BUNDLE_LOSSES)
    if not max_step_scale >= 1 or not max_iterations >= 0 or not loss_scale > 0 \
            or not num_threads >= 1 or not initial_trust_region_radius > 0:
        raise ValueError("bundle_adjust needs max_step_scale >= 1, max_iterations >= 0, "
                         "loss_scale > 0, initial_trust_region_radius > 0 and "
                         "num_threads >= 1")
    f = as_rays(rays, "rays")
    observed = np.ascontiguousarray(observation_point, dtype=np.int32).reshape(-1)
    images = np.ascontiguousarray(observation_image, dtype=np.int32).reshape(-1)
    jacobians = np.ascontiguousarray(pixels_from_tangent, dtype=np.float64).reshape(-1, 6)
    points = as_points3D(points3D, "points3D")
    frames, adjusted, info = _opengv.bundle_adjust(
        as_pose_rows(rigs_from_world, "rigs_from_world"),
        np.ascontiguousarray(free_parameters, dtype=bool).reshape(-1, 6),
        as_pose_rows(sensors_from_rig, "sensors_from_rig"),
        np.ascontiguousarray(image_frame, dtype=np.int32).reshape(-1), points,
        np.ascontiguousarray(point_variable, dtype=bool).reshape(-1), images, observed, f,
        jacobians, loss, float(loss_scale), int(max_iterations), float(gradient_tolerance),
        float(function_tolerance), float(max_step_scale), float(initial_trust_region_radius),
        int(num_threads))
    if not info["usable"]:
        raise EstimationError("bundle adjustment gave no finite cost")
    poses = frames.reshape(-1, 3, 4)
    return BundleAdjustmentResult([rigid3d(T[:, :3], T[:, 3]) for T in poses], adjusted,
                                  info["iterations"], info["initial_cost"], info["final_cost"])
