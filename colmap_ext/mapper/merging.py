"""Joining models that incremental mapping left apart.

Images fall apart into models where neighbouring images share too few points for a
registration (`abs_pose_min_num_inliers`): on a ring of narrow-field views of a weakly
textured object, for instance, two arcs grow into models of their own. An image next
to such a gap still sees a few points of the other model, too few to trust one P3P
pose: through a narrow field of view, poses from few points are often far off. Each
such cross-registration, though, implies a similarity between the two models, and two
images that imply the same one (the same rotation, and the same direction between
their centres) do not agree by chance; together they have the support a registration
needs. The models are then joined by that similarity, and the inliers of the two
cross-registrations become shared observations; the caller adjusts the joined model.
"""

from __future__ import annotations

import itertools
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import pycolmap

import solvers
from colmap_ext.geometry import (fit_similarity, mean_rotation, rotation_angles_deg,
                                 vector_angles_deg)
from colmap_ext.mapper.descriptors import nearest_descriptors
from colmap_ext.mapper.model import Model
from colmap_ext.mapper.options import GuidedMatchingOptions, MergingOptions, RegistrationOptions
from colmap_ext.mapper.registration import MAX_RATIO

# Nearest observations searched per keypoint for the ratio test, which compares the
# nearest with the nearest observation of another point (a point has many observations).
NUM_NEAREST_OBSERVATIONS = 20
# A cross-registration counts with this many P3P inliers, twice the minimal sample:
# alone far too few to trust, which is what the agreement of two is for.
MIN_CROSS_INLIERS = 6


@dataclass(frozen=True)
class CrossRegistration:
    """An image of one model posed among the other model's points, and what that
    implies for target_from_source: its rotation and the image's centre in both frames."""

    image_id: int
    rotation: np.ndarray
    centre_target: np.ndarray
    centre_source: np.ndarray
    kps: np.ndarray  # the image's inlier keypoints
    point_ids: np.ndarray  # the other model's points they observe

    @property
    def num_inliers(self) -> int:
        return len(self.kps)


def find_similarity(target: Model, source: Model, raw_graph: dict[int, dict[int, np.ndarray]],
                    merging: MergingOptions, registration: RegistrationOptions,
                    guided: GuidedMatchingOptions, seed: int | None
                    ) -> tuple[pycolmap.Sim3d, tuple[CrossRegistration, CrossRegistration]] | None:
    """target_from_source from the two consistent cross-registrations with most inliers
    together, if they have at least `abs_pose_min_num_inliers`; else None. `seed`: the
    RANSAC's (None: unseeded)."""
    registrations = [r for image_model, points_model in ((source, target), (target, source))
                     for image_id in image_model.registered
                     if (r := cross_register(image_model, image_id, points_model, raw_graph,
                                             registration, guided, seed,
                                             into_target=points_model is target))]
    pairs = sorted(itertools.combinations(registrations, 2),
                   key=lambda pair: -(pair[0].num_inliers + pair[1].num_inliers))
    for a, b in pairs:
        if a.num_inliers + b.num_inliers < registration.abs_pose_min_num_inliers:
            break
        similarity = similarity_from(a, b, merging.max_angle_deg)
        if similarity is not None:
            return similarity, (a, b)
    return None


def cross_register(image_model: Model, image_id: int, points_model: Model,
                   raw_graph: dict[int, dict[int, np.ndarray]],
                   registration: RegistrationOptions, guided: GuidedMatchingOptions,
                   seed: int | None, into_target: bool) -> CrossRegistration | None:
    """P3P of an image of `image_model` on descriptor matches to the points that
    `points_model` has in the images it shares raw matches with; None if none or no pose.
    `into_target` says whether `points_model` is the target of the similarity."""
    neighbours = [i for i in raw_graph.get(image_id, {}) if points_model.is_registered(i)]
    kps, point_ids = _descriptor_correspondences(image_model, image_id, points_model, neighbours,
                                                 guided.max_descriptor_distance)
    if len(kps) < MIN_CROSS_INLIERS:
        return None
    try:
        result = solvers.absolute_pose(
            image_model.rays[image_id][kps], points_model.xyz[point_ids],
            max_error=registration.abs_pose_max_error_px *
            image_model.pixel_angles[image_id][kps],
            min_num_inliers=MIN_CROSS_INLIERS, seed=seed)
    except solvers.EstimationError:
        return None
    own_pose, other_pose = image_model.pose(image_id), result.cam_from_world
    target_pose, source_pose = (other_pose, own_pose) if into_target else (own_pose, other_pose)
    return CrossRegistration(
        image_id, target_pose.rotation.matrix().T @ source_pose.rotation.matrix(),
        target_pose.inverse().translation, source_pose.inverse().translation,
        kps[result.inlier_mask], point_ids[result.inlier_mask])


def _descriptor_correspondences(image_model: Model, image_id: int, points_model: Model,
                                neighbours: list[int],
                                max_distance: float) -> tuple[np.ndarray, np.ndarray]:
    """(keypoints, point ids): each keypoint's nearest observation in `neighbours`,
    kept by the ratio test against the nearest observation of another point."""
    observed = [points_model.observations(i) for i in neighbours]
    if not observed or sum(len(kps) for kps, _ in observed) < 2:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    descriptors = np.concatenate([points_model.descriptors[i][kps]
                                  for i, (kps, _) in zip(neighbours, observed)])
    points = np.concatenate([point_ids for _, point_ids in observed])
    index, angles, _ = nearest_descriptors(image_model.descriptors[image_id], descriptors,
                                           NUM_NEAREST_OBSERVATIONS)
    nearest = points[index]
    other = nearest != nearest[:, :1]
    rows = np.arange(len(index))
    second = np.where(other.any(axis=1), angles[rows, np.argmax(other, axis=1)], np.pi)
    ok = (angles[:, 0] <= max_distance) & \
        (angles[:, 0] < MAX_RATIO * second) & image_model.has_rays(image_id, rows)
    return np.flatnonzero(ok), nearest[ok, 0]


def similarity_from(a: CrossRegistration, b: CrossRegistration,
                    max_angle_deg: float) -> pycolmap.Sim3d | None:
    """The similarity (target_from_source) two cross-registrations imply, or None when they disagree: their
    rotations, or the direction between their centres, differ by more than
    `max_angle_deg`. Rotation: the mean of both; scale and translation: the least-squares
    fit of the two centres under it."""
    if rotation_angles_deg((a.rotation.T @ b.rotation)[None])[0] > max_angle_deg:
        return None
    rotation = mean_rotation(np.stack([a.rotation, b.rotation]))
    baseline_target = b.centre_target - a.centre_target
    baseline_source = rotation @ (b.centre_source - a.centre_source)
    lengths = np.linalg.norm(baseline_target), np.linalg.norm(baseline_source)
    if min(lengths) <= 0 or vector_angles_deg(baseline_target[None],
                                              baseline_source[None])[0] > max_angle_deg:
        return None
    return fit_similarity(np.stack([a.centre_source, b.centre_source]),
                          np.stack([a.centre_target, b.centre_target]), rotation)


def join(target: Model, source: Model, similarity: pycolmap.Sim3d,
         links: tuple[CrossRegistration, ...]) -> Model:
    """One model of both, in the target's frame: the source's poses and points moved by
    `similarity`, and each cross-registration's inliers observing the same point."""
    model = Model(target.db, target.nearest,
                  sorted(set(target.image_ids) | set(source.image_ids)))
    model.fixed_frame_ids = target.fixed_frame_ids | source.fixed_frame_ids
    for image_id in target.registration_order:
        if not model.is_registered(image_id):
            model.register(image_id, target.pose(image_id))
    for image_id in source.registration_order:
        if not model.is_registered(image_id):
            model.register(image_id, similarity.transform_camera_world(source.pose(image_id)))
    target_ids = _copy_points(model, target, lambda xyz: xyz)
    source_ids = _copy_points(model, source, lambda xyz: similarity * xyz)
    for link in links:
        new_ids = source_ids if target.is_registered(link.image_id) else target_ids
        for kp, point_id in zip(link.kps.tolist(), link.point_ids.tolist()):
            _observe(model, link.image_id, kp, new_ids[point_id])
    return model


def _copy_points(model: Model, other: Model,
                 move: Callable[[np.ndarray], np.ndarray]) -> dict[int, int]:
    """Add `other`'s points (positions through `move`) to `model`; old id -> new id."""
    return {point_id: model.add_point(move(other.xyz[point_id]), other.track(point_id))
            for point_id in other.point_ids}


def _observe(model: Model, image_id: int, kp: int, point_id: int) -> None:
    """Keypoint `kp` of the image observes `point_id`: a free keypoint joins its track; a
    keypoint observing another point merges that point into it, unless their tracks
    share an image. A point merged away before is skipped."""
    if not model.has_point(point_id) or image_id in model.track(point_id):
        return
    other = int(model.point_of[image_id][kp])
    if other < 0:
        model.add_observation(point_id, image_id, kp)
    elif not set(model.track(other)) & set(model.track(point_id)):
        track = model.track(other)
        model.delete_point(other)
        for i, k in track.items():
            model.add_observation(point_id, i, k)
