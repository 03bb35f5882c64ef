"""Triangulation (paper, step 4c): a new image's compatible features either extend
an existing point's track or, seen in enough images, become a new point."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pycolmap

import solvers
from colmap_ext.mapper.guided_matching import compatible_features, verified_partners
from colmap_ext.mapper.model import Model
from colmap_ext.mapper.options import GuidedMatchingOptions, TriangulationOptions


def triangulate_image(model: Model, image_id: int, neighbours: list[int],
                      guided: GuidedMatchingOptions, triangulation: TriangulationOptions,
                      min_views: int, verified: dict[int, np.ndarray] | None = None
                      ) -> tuple[int, int]:
    """Guided matching of `image_id`'s free keypoints against `neighbours`, then track
    extension and new points with at least `min_views` observations. `verified`, the
    image's verified matches by other image, stand in for a neighbour's descriptor
    search where they match most free keypoints (verified_partners). Returns
    (observations added to existing points, new points)."""
    free = np.flatnonzero(model.point_of[image_id] < 0)
    verified = verified or {}
    partners = {other_id: verified_partners(model, image_id, free, verified[other_id], guided)
                for other_id in neighbours if other_id in verified}
    model.nearest.prefetch(image_id, [other_id for other_id in neighbours
                                      if partners.get(other_id) is None], free)
    found = [(other_id, *compatible_features(model, image_id, other_id, free, guided,
                                             partners.get(other_id))[:2])
             for other_id in neighbours]
    candidates = Candidates.of(found)
    num_extended = _extend_tracks(model, image_id, candidates, triangulation)
    num_new = _create_points(model, image_id, candidates, triangulation, min_views)
    return num_extended, num_new


@dataclass
class Candidates:
    """A new image's compatible features in its neighbours, keypoint by keypoint (in the
    order the keypoints first come, neighbour after neighbour), each keypoint's in its
    neighbours' order: the keypoint, the other image and its keypoint."""

    kp: np.ndarray
    other_image: np.ndarray
    other_kp: np.ndarray

    @classmethod
    def of(cls, found: list[tuple[int, np.ndarray, np.ndarray]]) -> Candidates:
        """From (neighbour, keypoints, its compatible keypoints) in the neighbours' order."""
        if not found:
            return cls(*(np.zeros(0, np.int64) for _ in range(3)))
        kp = np.concatenate([kps for _, kps, _ in found]).astype(np.int64)
        other_image = np.concatenate([np.full(len(kps), other_id, np.int64)
                                      for other_id, kps, _ in found])
        other_kp = np.concatenate([other_kps for _, _, other_kps in found]).astype(np.int64)
        _, first, inverse = np.unique(kp, return_index=True, return_inverse=True)
        order = np.argsort(first[inverse], kind="stable")
        return cls(kp[order], other_image[order], other_kp[order])


def _extend_tracks(model: Model, image_id: int, candidates: Candidates,
                   triangulation: TriangulationOptions) -> int:
    """Keypoints compatible with an observation of an existing point join its track
    when the point reprojects onto them (one keypoint per point, the closest)."""
    other = model.flat_index(candidates.other_image, candidates.other_kp)
    return model.add_observations_within(image_id, candidates.kp, model.point_of_flat[other],
                                         triangulation.max_reproj_error_px)


def complete_tracks(model: Model, verified: dict[int, dict[int, np.ndarray]],
                    triangulation: TriangulationOptions) -> int:
    """Free keypoints of registered images whose verified match observes a point join
    its track where the point reprojects onto them, as COLMAP completes tracks after an
    adjustment: an image registered on points still moving (the first images, on the
    initial pair's) leaves out the observations then beyond max_reproj_error_px, and
    triangulation only looks at free keypoints. Returns the observations added."""
    registered = model.registered
    is_registered = np.zeros(max(model.image_ids) + 1, bool)
    is_registered[registered] = True
    added = 0
    for image_id in registered:
        pairs = [(other_id, matches) for other_id, matches in verified.get(image_id, {}).items()
                 if is_registered[other_id]]
        if not pairs:
            continue
        matches = np.concatenate([m for _, m in pairs])
        flat = np.concatenate([m[:, 1] + model.flat_offset[other_id] for other_id, m in pairs])
        point_ids = model.point_of_flat[flat]
        missing = (point_ids >= 0) & (model.point_of[image_id][matches[:, 0]] < 0)
        if missing.any():
            added += model.add_observations_within(image_id, matches[missing, 0],
                                                   point_ids[missing],
                                                   triangulation.max_reproj_error_px)
    return added


@dataclass
class TrackLinks:
    """Verified matches between registered images whose two keypoints are not
    observations of one point: each side's image and keypoint, its point (-1 where the
    keypoint is free), and whether that point reprojects within the limit onto the other
    side's keypoint (False where free). A true match across a split track has a point
    near on one side at least; a wrong match that got through verification links points
    apart."""

    first_image: np.ndarray
    first_kp: np.ndarray
    first: np.ndarray
    first_near: np.ndarray
    second_image: np.ndarray
    second_kp: np.ndarray
    second: np.ndarray
    second_near: np.ndarray


def track_links(model: Model, verified: dict[int, dict[int, np.ndarray]],
                max_error_px: float) -> TrackLinks:
    """The TrackLinks of the verified matches between the model's registered images, with
    one reprojection per image."""
    columns: list[list[np.ndarray]] = [[] for _ in range(6)]
    # Per image, (its keypoints, the linked points to reproject onto them, and where the
    # answers go: 2 x the link's index, + 1 for second_near).
    queries: dict[int, list[tuple[np.ndarray, np.ndarray, np.ndarray]]] = {}
    num_links = 0
    for image_id in model.registered:
        pairs = [(other_id, matches) for other_id, matches in verified.get(image_id, {}).items()
                 if other_id > image_id and model.is_registered(other_id)]
        if not pairs:
            continue
        # All the image's pairs at once; the few links then pair by pair.
        first = model.point_of[image_id][np.concatenate([m[:, 0] for _, m in pairs])]
        second = model.point_of_flat[np.concatenate([m[:, 1] + model.flat_offset[other_id]
                                                     for other_id, m in pairs])]
        linked = first != second
        start = 0
        for other_id, matches in pairs:
            end = start + len(matches)
            in_pair = np.flatnonzero(linked[start:end])
            if len(in_pair):
                index = np.arange(num_links, num_links + len(in_pair))
                num_links += len(in_pair)
                pair_first, pair_second = first[start:end][in_pair], second[start:end][in_pair]
                for column, values in zip(columns, (
                        np.full(len(in_pair), image_id), matches[in_pair, 0], pair_first,
                        np.full(len(in_pair), other_id), matches[in_pair, 1], pair_second)):
                    column.append(values)
                for kps, point_ids, query_id, target in (
                        (matches[in_pair, 1], pair_first, other_id, 2 * index),
                        (matches[in_pair, 0], pair_second, image_id, 2 * index + 1)):
                    has = point_ids >= 0
                    queries.setdefault(query_id, []).append(
                        (kps[has], point_ids[has], target[has]))
            start = end
    near = np.zeros(2 * num_links, bool)
    for image_id, parts in queries.items():
        kps, point_ids, target = (np.concatenate(part) for part in zip(*parts))
        errors = model.reprojection_errors(image_id, kps, model.xyz[point_ids])
        near[target[errors <= max_error_px]] = True
    (first_image, first_kp, first, second_image, second_kp, second) = (
        np.concatenate(column) if column else np.zeros(0, np.int64) for column in columns)
    return TrackLinks(first_image, first_kp, first, near[0::2],
                      second_image, second_kp, second, near[1::2])


def merge_tracks(model: Model, verified: dict[int, dict[int, np.ndarray]],
                 triangulation: TriangulationOptions) -> int:
    """Points that a verified match links (a keypoint of one matched to a keypoint of the
    other) become one point where their joined track, triangulated again, reprojects
    within max_reproj_error_px in every image, as COLMAP merges tracks after an
    adjustment: the first observations of a point still off by more than the threshold
    leave the next image's keypoint free, and it starts a second point of the same track.
    Only links where one of the two points reprojects within the threshold onto the other's
    keypoint are tried (track_links); tracks that share an image are not joined; a point
    joins one other point per call. Returns the points merged into others."""
    links = track_links(model, verified, triangulation.max_reproj_error_px)
    tried = ((links.first >= 0) & (links.second >= 0)
             & (links.first_near | links.second_near))
    first, second = links.first[tried], links.second[tried]
    linked_points = set(zip(np.minimum(first, second).tolist(),
                            np.maximum(first, second).tolist()))
    pairs, tracks = [], []
    for first, second in sorted(linked_points):
        track, other_track = model.track(first), model.track(second)
        if not track.keys() & other_track.keys():
            pairs.append((first, second))
            tracks.append({**track, **other_track})
    if not tracks:
        return 0
    xyz, ok = triangulate_points(model, Tracks.of(tracks), triangulation)
    merged: set[int] = set()
    for (first, second), track, point, keep in zip(pairs, tracks, xyz, ok):
        if keep and first not in merged and second not in merged:
            model.delete_point(first)
            model.delete_point(second)
            model.add_point(point, track)
            merged.update((first, second))
    return len(merged) // 2


def _create_points(model: Model, image_id: int, candidates: Candidates,
                   triangulation: TriangulationOptions, min_views: int) -> int:
    """Free keypoints with free compatible features in enough images become points,
    kept when every observation reprojects within the threshold (in the candidates'
    order, a keypoint taken by an earlier new point is not taken again)."""
    free = (model.point_of[image_id][candidates.kp] < 0) & \
        (model.point_of_flat[model.flat_index(candidates.other_image, candidates.other_kp)] < 0)
    kp, other_image, other_kp = (candidates.kp[free], candidates.other_image[free],
                                 candidates.other_kp[free])
    # Each keypoint's features are contiguous, the keypoints in the candidates' order.
    heads, start, count = np.unique(kp, return_index=True, return_counts=True)
    order = np.argsort(start)
    heads, count = heads[order], count[order]
    enough = count + 1 >= min_views
    if not enough.any():
        return 0
    # Each track: the image's keypoint, then its compatible features.
    entries = np.repeat(enough, count)
    entry_track = np.repeat(np.cumsum(enough) - 1, count)[entries]
    heads = heads[enough]
    track = np.concatenate([np.arange(len(heads)), entry_track])
    order = np.argsort(track, kind="stable")
    tracks = Tracks(track[order],
                    np.concatenate([np.full(len(heads), image_id), other_image[entries]])[order],
                    np.concatenate([heads, other_kp[entries]])[order], len(heads))
    xyz, ok = triangulate_points(model, tracks, triangulation)
    flat = model.flat_index(tracks.image, tracks.kp)
    # Only a keypoint in several tracks can be taken by an earlier one.
    _, inverse, uses = np.unique(flat, return_inverse=True, return_counts=True)
    shared = np.zeros(tracks.num_tracks, bool)
    shared[tracks.track[uses[inverse] > 1]] = True
    bounds = np.searchsorted(tracks.track, np.arange(tracks.num_tracks + 1)).tolist()
    created = 0
    for t in np.flatnonzero(ok).tolist():
        begin, end = bounds[t], bounds[t + 1]
        if shared[t] and (model.point_of_flat[flat[begin:end]] >= 0).any():
            continue
        model.add_point(xyz[t], dict(zip(tracks.image[begin:end].tolist(),
                                         tracks.kp[begin:end].tolist())))
        created += 1
    return created


@dataclass
class Tracks:
    """Many tracks at once, observation by observation, each track's together and in its
    order: the track it belongs to (0 .. num_tracks - 1, ascending), its image and keypoint."""

    track: np.ndarray
    image: np.ndarray
    kp: np.ndarray
    num_tracks: int

    @classmethod
    def of(cls, tracks: list[dict[int, int]]) -> Tracks:
        """From tracks as image id -> keypoint."""
        lengths = [len(track) for track in tracks]
        return cls(np.repeat(np.arange(len(tracks)), lengths),
                   np.array([i for track in tracks for i in track], np.int64),
                   np.array([kp for track in tracks for kp in track.values()], np.int64),
                   len(tracks))


def triangulate_points(model: Model, tracks: Tracks, triangulation: TriangulationOptions,
                       cams_from_world: dict[int, pycolmap.Rigid3d] | None = None
                       ) -> tuple[np.ndarray, np.ndarray]:
    """The points of tracks (triangulate_tracks), and whether each is kept: some two of
    its rays meet at triangulation.min_tri_angle_deg or more, and every observation
    reprojects within triangulation.max_reproj_error_px. `cams_from_world`: the images'
    poses (default: their registered ones)."""
    xyz, valid = triangulate_tracks(model, tracks, triangulation.min_tri_angle_deg,
                                    cams_from_world)
    return xyz, valid & _reprojection_ok(model, tracks, xyz, triangulation.max_reproj_error_px,
                                         cams_from_world)


def triangulate_tracks(model: Model, tracks: Tracks, min_angle_deg: float,
                       cams_from_world: dict[int, pycolmap.Rigid3d] | None = None
                       ) -> tuple[np.ndarray, np.ndarray]:
    """Linear multi-view triangulation of tracks over registered images (or over the
    poses `cams_from_world`); valid where some two rays meet at `min_angle_deg` or more."""
    image_ids, views = np.unique(tracks.image, return_inverse=True)
    poses = [model.pose(i) if cams_from_world is None else cams_from_world[i]
             for i in image_ids.tolist()]
    return solvers.triangulate_tracks(poses, views, tracks.track,
                                      model.rays_flat[model.flat_index(tracks.image, tracks.kp)],
                                      num_points=tracks.num_tracks, min_angle_deg=min_angle_deg)


def _reprojection_ok(model: Model, tracks: Tracks, xyz: np.ndarray, max_error_px: float,
                     cams_from_world: dict[int, pycolmap.Rigid3d] | None) -> np.ndarray:
    """Whether every observation of each track reprojects within `max_error_px` (poses:
    `cams_from_world`, or the registered ones)."""
    ok = np.isfinite(xyz).all(axis=1)
    by_image = np.argsort(tracks.image, kind="stable")
    image_ids, starts = np.unique(tracks.image[by_image], return_index=True)
    for image_id, observations in zip(image_ids.tolist(), np.split(by_image, starts[1:])):
        ps = tracks.track[observations]
        pose = None if cams_from_world is None else cams_from_world[image_id]
        errors = model.reprojection_errors(image_id, tracks.kp[observations],
                                           np.nan_to_num(xyz[ps]), pose)
        ok[ps[errors > max_error_px]] = False
    return ok


def shared_observation_groups(point: np.ndarray, image: np.ndarray, keypoint: np.ndarray,
                              num_points: int) -> np.ndarray:
    """Per point id, the smallest id of its group: points that share an observation
    (image, keypoint), directly or through other points. Observation k is keypoint
    `keypoint[k]` of image `image[k]` seeing point `point[k]`. Minimum labels spread
    along the links, with pointer jumping, until nothing changes."""
    key = image.astype(np.int64) * (int(keypoint.max(initial=0)) + 1) + keypoint
    _, first, inverse = np.unique(key, return_index=True, return_inverse=True)
    other = point[first][inverse]
    linked = point != other
    a, b = point[linked], other[linked]
    label = np.arange(num_points)
    while True:
        previous = label.copy()
        low = np.minimum(label[a], label[b])
        np.minimum.at(label, a, low)
        np.minimum.at(label, b, low)
        while True:
            jumped = label[label]
            if (jumped == label).all():
                break
            label = jumped
        if (label == previous).all():
            return label
