"""Registration of the next image (paper, steps 4a-4b): 2D-3D correspondences with
the model's points, then P3P RANSAC (OpenGV) refined on the inliers; the pose must keep
the image's verified matches on their epipolar lines."""

from __future__ import annotations

import enum

import numpy as np
import pycolmap

import solvers
from colmap_ext.geometry import sampson_angles
from colmap_ext.mapper.guided_matching import pair_pixel_angles
from colmap_ext.mapper.model import Model
from colmap_ext.mapper.options import MapperOptions


class Outcome(enum.Enum):
    """What register_image did."""

    REGISTERED = "registered"
    TOO_FEW_INLIERS = "too few P3P inliers"
    INCONSISTENT = "pose off the verified matches' epipolar lines"


# Lowe's ratio test for descriptor matches against model points (the paper's 1.25, inverted).
MAX_RATIO = 0.8


def track_correspondences(model: Model, image_id: int,
                          graph: dict[int, dict[int, np.ndarray]]) -> tuple[np.ndarray, np.ndarray]:
    """(keypoints, point ids) through verified matches to registered images' points."""
    kps, point_ids = [], []
    for other_id, matches in graph.get(image_id, {}).items():
        if other_id in model.poses:
            points = model.point_of[other_id][matches[:, 1]]
            has_point = points >= 0
            kps.append(matches[has_point, 0])
            point_ids.append(points[has_point])
    if not kps:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    return np.concatenate(kps), np.concatenate(point_ids)


def descriptor_correspondences(model: Model, image_id: int, neighbours: list[int],
                               options: MapperOptions) -> tuple[np.ndarray, np.ndarray]:
    """(keypoints, point ids) by matching descriptors against the observations of
    points in nearby registered images, with the ratio test."""
    if len(model.keypoints[image_id]) == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    observed = [(other_id, *model.observations(other_id)) for other_id in neighbours]
    observed = [o for o in observed if len(o[1]) >= 2]
    found = model.nearest.search_subsets(image_id, [(other_id, other_kps)
                                                    for other_id, other_kps, _ in observed], 2)
    kps, point_ids = [], []
    for (_, _, other_points), (index, angles) in zip(observed, found):
        ok = (angles[:, 0] <= options.guided_matching.max_descriptor_distance) & \
             (angles[:, 0] < MAX_RATIO * angles[:, 1])
        kps.append(np.flatnonzero(ok))
        point_ids.append(other_points[index[ok, 0]])
    if not kps:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    return np.concatenate(kps), np.concatenate(point_ids)


def register_image(model: Model, image_id: int, kps: np.ndarray, point_ids: np.ndarray,
                   graph: dict[int, dict[int, np.ndarray]], options: MapperOptions) -> Outcome:
    """Estimate the image's pose from 2D-3D correspondences and add its inliers to the
    points' tracks (one keypoint per point, the one reprojecting closest).

    The pose must also keep the image's verified matches (`graph`) to registered images
    on their epipolar lines (epipolar_support): on repeated texture, wrong
    correspondences can agree on a wrong pose with more inliers than the right one."""
    registration = options.registration
    pairs = np.unique(np.stack([kps, point_ids], axis=1), axis=0) if len(kps) else \
        np.zeros((0, 2), np.int64)
    pairs = pairs[model.has_rays(image_id, pairs[:, 0])]
    if len(pairs) < max(4, registration.abs_pose_min_num_inliers):
        return Outcome.TOO_FEW_INLIERS
    try:
        result = solvers.absolute_pose(
            model.rays[image_id][pairs[:, 0]], model.xyz[pairs[:, 1]],
            max_error=registration.abs_pose_max_error_px *
            model.pixel_angles[image_id][pairs[:, 0]],
            min_num_inliers=registration.abs_pose_min_num_inliers, seed=options.seed)
    except solvers.EstimationError:
        return Outcome.TOO_FEW_INLIERS
    if result.num_inliers < registration.abs_pose_min_inlier_ratio * len(np.unique(pairs[:, 0])):
        return Outcome.TOO_FEW_INLIERS
    if epipolar_support(model, image_id, result.cam_from_world, graph, options) < \
            registration.min_epipolar_support:
        return Outcome.INCONSISTENT
    _add_inliers(model, image_id, result.cam_from_world, pairs[result.inlier_mask], options)
    return Outcome.REGISTERED


def _add_inliers(model: Model, image_id: int, cam_from_world: pycolmap.Rigid3d,
                 inliers: np.ndarray, options: MapperOptions) -> None:
    """Register the image and add its (keypoint, point id) inliers to the tracks."""
    model.register(image_id, cam_from_world)
    kps, point_ids = inliers[:, 0], inliers[:, 1]
    errors = model.reprojection_errors(image_id, kps, model.xyz[point_ids])
    for i in np.argsort(errors, kind="stable"):
        kp, point_id = int(kps[i]), int(point_ids[i])
        if model.point_of[image_id][kp] < 0 and image_id not in model.tracks[point_id] \
                and errors[i] <= options.registration.abs_pose_max_error_px:
            model.add_observation(point_id, image_id, kp)


def epipolar_support(model: Model, image_id: int, cam_from_world: pycolmap.Rigid3d,
                     graph: dict[int, dict[int, np.ndarray]], options: MapperOptions) -> float:
    """The fraction of the image's verified matches to registered images that the pose
    keeps within abs_pose_max_error_px of their epipolar lines (1 without such matches).

    Verified matches are true far more often than the pair's own relative pose is right
    (near-planar pairs), so they check a pose where 2D-3D inliers alone cannot."""
    max_error_px = options.registration.abs_pose_max_error_px
    consistent = total = 0
    for other_id, matches in graph.get(image_id, {}).items():
        if other_id not in model.poses:
            continue
        E = pycolmap.essential_matrix_from_pose(model.poses[other_id] * cam_from_world.inverse())
        errors = sampson_angles(E, model.rays[image_id][matches[:, 0]],
                                model.rays[other_id][matches[:, 1]])
        max_errors = max_error_px * pair_pixel_angles(model, image_id, matches[:, 0], other_id,
                                                      matches[:, 1])
        consistent += int(np.count_nonzero(errors <= max_errors))
        total += len(matches)
    return consistent / total if total else 1.0
