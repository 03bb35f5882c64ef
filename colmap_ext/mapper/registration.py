"""Registration of the next image (paper, steps 4a-4b): 2D-3D correspondences with
the model's points, then P3P RANSAC (OpenGV) refined on the inliers."""

from __future__ import annotations

import numpy as np
import pycolmap

import solvers
from colmap_ext.mapper.guided_matching import nearest_descriptors
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
    kps, point_ids = [], []
    queries = model.descriptors[image_id]
    for other_id in neighbours:
        other_kps, other_points = model.observations(other_id)
        if len(other_kps) < 2 or len(queries) == 0:
            continue
        index, angles = nearest_descriptors(queries, model.descriptors[other_id][other_kps], 2)
        ok = (angles[:, 0] <= options.max_descriptor_distance) & \
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
    if len(pairs) < max(4, options.abs_pose_min_num_inliers):
        return False
    kps, point_ids = pairs[:, 0], pairs[:, 1]
    try:
        result = solvers.absolute_pose(
            model.rays[image_id][kps], model.xyz[point_ids],
            max_error=options.abs_pose_max_error_px / model.focal(image_id),
            min_num_inliers=options.abs_pose_min_num_inliers, seed=options.seed)
    except solvers.EstimationError:
        return False
    if result.num_inliers < options.abs_pose_min_inlier_ratio * len(np.unique(kps)):
        return False
    kps, point_ids = kps[result.inlier_mask], point_ids[result.inlier_mask]
    if rotation_uncertainty(result.cam_from_world, model.xyz[point_ids]) > \
            options.abs_pose_max_rotation_uncertainty:
        return False
    model.register(image_id, result.cam_from_world)
    errors = model.reprojection_errors(image_id, kps, model.xyz[point_ids])
    for i in np.argsort(errors, kind="stable"):
        kp, point_id = int(kps[i]), int(point_ids[i])
        if model.point_of[image_id][kp] < 0 and image_id not in model.tracks[point_id] \
                and errors[i] <= options.abs_pose_max_error_px:
            model.add_observation(point_id, image_id, kp)
    return True


def rotation_uncertainty(cam_from_world: pycolmap.Rigid3d, xyz: np.ndarray) -> float:
    """How poorly the inliers `xyz` fix the pose's rotation: the standard deviation of
    the rotation (radians, about its least determined axis, marginal over the
    translation) per radian of keypoint noise, the points taken as exact.

    Gauss-Newton on the reprojection errors in normalized image units, with the
    Jacobian of absolute_pose's refinement: covariance (J^T J)^-1. Few inliers in a
    narrow field of view, or on a shallow scene, let a rotation trade off against a
    translation (bas-relief): the uncertainty grows, and so does any bias of the points."""
    pose = cam_from_world.matrix()
    rotated = xyz @ pose[:, :3].T
    x = rotated + pose[:, 3]
    inv_z = 1.0 / x[:, 2]
    zeros = np.zeros(len(x))
    dproject = np.stack([np.stack([inv_z, zeros, -x[:, 0] * inv_z ** 2], axis=1),
                         np.stack([zeros, inv_z, -x[:, 1] * inv_z ** 2], axis=1)], axis=1)
    skew = np.zeros((len(x), 3, 3))
    skew[:, 0, 1], skew[:, 0, 2], skew[:, 1, 2] = -rotated[:, 2], rotated[:, 1], -rotated[:, 0]
    skew -= skew.transpose(0, 2, 1)
    jacobian = np.concatenate([-dproject @ skew, dproject], axis=2)  # d(residual)/d(w, u)
    normal = np.einsum("nki,nkj->ij", jacobian, jacobian)
    try:
        covariance = np.linalg.inv(normal)[:3, :3]
    except np.linalg.LinAlgError:
        return float("inf")
    return float(np.sqrt(max(np.linalg.eigvalsh(covariance)[-1], 0.0)))
