"""Registration of the next frame (paper, steps 4a-4b): 2D-3D correspondences of its
images with the model's points, then P3P RANSAC (GP3P for a rig's frame; OpenGV) refined
on the inliers; the pose must keep the images' verified matches on their epipolar lines."""

from __future__ import annotations

import enum

import numpy as np
import pycolmap

import solvers
from colmap_ext.mapper.guided_matching import epipolar_inliers
from colmap_ext.mapper.model import Model
from colmap_ext.mapper.options import GuidedMatchingOptions, RegistrationOptions


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
        if model.is_registered(other_id):
            points = model.point_of[other_id][matches[:, 1]]
            has_point = points >= 0
            kps.append(matches[has_point, 0])
            point_ids.append(points[has_point])
    if not kps:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    return np.concatenate(kps), np.concatenate(point_ids)


def descriptor_correspondences(model: Model, image_id: int, neighbours: list[int],
                               guided: GuidedMatchingOptions) -> tuple[np.ndarray, np.ndarray]:
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
        ok = (angles[:, 0] <= guided.max_descriptor_distance) & \
             (angles[:, 0] < MAX_RATIO * angles[:, 1])
        kps.append(np.flatnonzero(ok))
        point_ids.append(other_points[index[ok, 0]])
    if not kps:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    return np.concatenate(kps), np.concatenate(point_ids)


def searches_descriptors(model: Model, image_id: int, verified_kps: np.ndarray,
                         guided: GuidedMatchingOptions) -> bool:
    """Whether the image's descriptors are matched to model points too: unless verified
    matches give skip_search_verified_share of its keypoints a point."""
    return len(np.unique(verified_kps)) < \
        guided.skip_search_verified_share * len(model.keypoints[image_id])


Correspondences = dict[int, tuple[np.ndarray, np.ndarray]]  # image id -> (keypoints, point ids)


def register_frame(model: Model, correspondences: Correspondences,
                   graph: dict[int, dict[int, np.ndarray]], registration: RegistrationOptions,
                   seed: int | None) -> Outcome:
    """Estimate the pose of a frame from the 2D-3D correspondences of its images (P3P for
    an image alone in its frame, GP3P for a rig's images, both OpenGV's, refined on the
    inliers within pose_max_error_px), then add the inliers within abs_pose_max_error_px
    to the points' tracks (per image, one keypoint per point, the one reprojecting
    closest).

    The pose must also keep the images' verified matches (`graph`) to registered images
    on their epipolar lines (epipolar_support): on repeated texture, wrong
    correspondences can agree on a wrong pose with more inliers than the right one.
    `seed`: the RANSAC's (None: unseeded)."""
    pairs_of = {}
    for image_id, (kps, point_ids) in correspondences.items():
        pairs = _distinct_pairs(kps, point_ids)
        pairs_of[image_id] = pairs[model.has_rays(image_id, pairs[:, 0])]
    image_ids = list(pairs_of)
    pairs = np.concatenate(list(pairs_of.values()))
    if len(pairs) < max(4, registration.abs_pose_min_num_inliers):
        return Outcome.TOO_FEW_INLIERS
    camera_index = np.repeat(np.arange(len(image_ids)), [len(p) for p in pairs_of.values()])
    rays = np.concatenate([model.rays[i][p[:, 0]] for i, p in pairs_of.items()])
    pixel_angles = np.concatenate([model.pixel_angles[i][p[:, 0]] for i, p in pairs_of.items()])
    xyz = model.xyz[pairs[:, 1]]
    cams_from_rig = [model.cam_from_rig(image_id) for image_id in image_ids]
    try:
        result, cams_from_world = _estimate_pose(
            rays, camera_index, xyz, cams_from_rig, registration.abs_pose_max_error_px *
            pixel_angles, registration.abs_pose_min_num_inliers, seed)
        num_keypoints = sum(len(np.unique(p[:, 0])) for p in pairs_of.values())
        if result.num_inliers < registration.abs_pose_min_inlier_ratio * num_keypoints:
            return Outcome.TOO_FEW_INLIERS
        if registration.pose_max_error_px < registration.abs_pose_max_error_px:
            # The pose again from those inliers within pose_max_error_px.
            inliers = result.inlier_mask
            _, cams_from_world = _estimate_pose(
                rays[inliers], camera_index[inliers], xyz[inliers], cams_from_rig,
                registration.pose_max_error_px * pixel_angles[inliers], 4, seed)
    except solvers.EstimationError:
        return Outcome.TOO_FEW_INLIERS
    if epipolar_support(model, dict(zip(image_ids, cams_from_world)), graph, registration) < \
            registration.min_epipolar_support:
        return Outcome.INCONSISTENT
    model.register(image_ids[0], cams_from_world[0])
    for k, image_id in enumerate(image_ids):
        inliers = pairs[result.inlier_mask & (camera_index == k)]
        model.add_observations_within(image_id, inliers[:, 0], inliers[:, 1],
                                      registration.abs_pose_max_error_px)
    return Outcome.REGISTERED


def _estimate_pose(rays: np.ndarray, camera_index: np.ndarray, xyz: np.ndarray,
                   cams_from_rig: list[pycolmap.Rigid3d], max_error: np.ndarray,
                   min_num_inliers: int, seed: int | None
                   ) -> tuple[solvers.AbsolutePoseResult | solvers.GeneralizedAbsolutePoseResult,
                              list[pycolmap.Rigid3d]]:
    """P3P (one camera) or GP3P (a rig's cameras, `camera_index`) RANSAC: the estimate and
    each camera's cam_from_world. Raises solvers.EstimationError."""
    if len(cams_from_rig) == 1:
        result = solvers.absolute_pose(rays, xyz, max_error=max_error,
                                       min_num_inliers=min_num_inliers, seed=seed)
        return result, [result.cam_from_world]
    result = solvers.generalized_absolute_pose(rays, camera_index, xyz, cams_from_rig,
                                               max_error=max_error,
                                               min_num_inliers=min_num_inliers, seed=seed)
    return result, [cam_from_rig * result.rig_from_world for cam_from_rig in cams_from_rig]


def _distinct_pairs(kps: np.ndarray, point_ids: np.ndarray) -> np.ndarray:
    """The distinct (keypoint, point id) rows, sorted by keypoint then point id, as
    np.unique(axis=0) gives them; through one integer key a row, whose sort is many
    times faster than unique's over rows."""
    if not len(kps):
        return np.zeros((0, 2), np.int64)
    num_point_ids = int(point_ids.max()) + 1
    keys = np.unique(kps.astype(np.int64) * num_point_ids + point_ids)
    return np.stack([keys // num_point_ids, keys % num_point_ids], axis=1)


def epipolar_support(model: Model, cams_from_world: dict[int, pycolmap.Rigid3d],
                     graph: dict[int, dict[int, np.ndarray]],
                     registration: RegistrationOptions) -> float:
    """The fraction of the images' verified matches to registered images that the poses
    `cams_from_world` (image id -> pose) keep within pose_max_error_px (or
    abs_pose_max_error_px, if lower) of their epipolar lines (1 without such matches).

    Verified matches are true far more often than the pair's own relative pose is right
    (near-planar pairs), so they check a pose where 2D-3D inliers alone cannot."""
    max_error_px = min(registration.pose_max_error_px, registration.abs_pose_max_error_px)
    consistent = total = 0
    for image_id, cam_from_world in cams_from_world.items():
        for other_id, matches in graph.get(image_id, {}).items():
            if not model.is_registered(other_id):
                continue
            consistent += int(np.count_nonzero(epipolar_inliers(
                model, (image_id, other_id), matches,
                model.pose(other_id) * cam_from_world.inverse(), max_error_px)))
            total += len(matches)
    return consistent / total if total else 1.0
