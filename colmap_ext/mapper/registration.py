"""Registration of the next image (paper, steps 4a-4b): 2D-3D correspondences with
the model's points, then P3P RANSAC (OpenGV) refined on the inliers."""

from __future__ import annotations

import numpy as np

import solvers
from colmap_ext.mapper.model import Model
from colmap_ext.mapper.options import MapperOptions

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
                   options: MapperOptions) -> bool:
    """Estimate the image's pose from 2D-3D correspondences and add its inliers to the
    points' tracks (one keypoint per point, the one reprojecting closest)."""
    pairs = np.unique(np.stack([kps, point_ids], axis=1), axis=0) if len(kps) else \
        np.zeros((0, 2), np.int64)
    if len(pairs) < max(4, options.registration.abs_pose_min_num_inliers):
        return False
    kps, point_ids = pairs[:, 0], pairs[:, 1]
    try:
        result = solvers.absolute_pose(
            model.rays[image_id][kps], model.xyz[point_ids],
            max_error=options.registration.abs_pose_max_error_px / model.focal(image_id),
            min_num_inliers=options.registration.abs_pose_min_num_inliers, seed=options.seed)
    except solvers.EstimationError:
        return False
    if result.num_inliers < options.registration.abs_pose_min_inlier_ratio * len(np.unique(kps)):
        return False
    model.register(image_id, result.cam_from_world)
    kps, point_ids = kps[result.inlier_mask], point_ids[result.inlier_mask]
    errors = model.reprojection_errors(image_id, kps, model.xyz[point_ids])
    for i in np.argsort(errors, kind="stable"):
        kp, point_id = int(kps[i]), int(point_ids[i])
        if model.point_of[image_id][kp] < 0 and image_id not in model.tracks[point_id] \
                and errors[i] <= options.registration.abs_pose_max_error_px:
            model.add_observation(point_id, image_id, kp)
    return True
