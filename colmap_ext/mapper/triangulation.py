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
    candidates: dict[int, list[tuple[int, int]]] = {}  # kp -> [(other image, other kp)]
    verified = verified or {}
    partners = {other_id: verified_partners(model, image_id, free, verified[other_id], guided)
                for other_id in neighbours if other_id in verified}
    model.nearest.prefetch(image_id, [other_id for other_id in neighbours
                                      if partners.get(other_id) is None], free)
    for other_id in neighbours:
        kps, other_kps, _ = compatible_features(model, image_id, other_id, free, guided,
                                                partners.get(other_id))
        for kp, other_kp in zip(kps.tolist(), other_kps.tolist()):
            candidates.setdefault(kp, []).append((other_id, other_kp))
    num_extended = _extend_tracks(model, image_id, candidates, triangulation)
    num_new = _create_points(model, image_id, candidates, triangulation, min_views)
    return num_extended, num_new


def _extend_tracks(model: Model, image_id: int, candidates: dict[int, list[tuple[int, int]]],
                   triangulation: TriangulationOptions) -> int:
    """Keypoints compatible with an observation of an existing point join its track
    when the point reprojects onto them (one keypoint per point, the closest)."""
    # Every (keypoint, other image's keypoint) pair in the candidates' order, looked up
    # at once as flat indices into model.point_of_flat.
    kps = np.array([kp for kp, matches in candidates.items() for _ in matches], np.int64)
    flat = np.array([model.flat_offset[other_id] + other_kp
                     for matches in candidates.values() for other_id, other_kp in matches],
                    np.int64)
    return model.add_observations_within(image_id, kps, model.point_of_flat[flat],
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
    xyz, ok = triangulate_points(model, tracks, triangulation)
    merged: set[int] = set()
    for (first, second), track, point, keep in zip(pairs, tracks, xyz, ok):
        if keep and first not in merged and second not in merged:
            model.delete_point(first)
            model.delete_point(second)
            model.add_point(point, track)
            merged.update((first, second))
    return len(merged) // 2


def _create_points(model: Model, image_id: int, candidates: dict[int, list[tuple[int, int]]],
                   triangulation: TriangulationOptions, min_views: int) -> int:
    """Free keypoints with free compatible features in enough images become points,
    kept when every observation reprojects within the threshold."""
    tracks = []
    for kp, matches in candidates.items():
        if model.point_of[image_id][kp] >= 0:
            continue
        track = {image_id: kp}
        for other_id, other_kp in matches:
            if model.point_of[other_id][other_kp] < 0:
                track[other_id] = other_kp
        if len(track) >= min_views:
            tracks.append(track)
    if not tracks:
        return 0
    xyz, ok = triangulate_points(model, tracks, triangulation)
    created = 0
    for track, point, keep in zip(tracks, xyz, ok):
        if keep and all(model.point_of[i][kp] < 0 for i, kp in track.items()):
            model.add_point(point, track)
            created += 1
    return created


def triangulate_points(model: Model, tracks: list[dict[int, int]],
                       triangulation: TriangulationOptions,
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


def triangulate_tracks(model: Model, tracks: list[dict[int, int]], min_angle_deg: float,
                       cams_from_world: dict[int, pycolmap.Rigid3d] | None = None
                       ) -> tuple[np.ndarray, np.ndarray]:
    """Linear multi-view triangulation of tracks over registered images (or over the
    poses `cams_from_world`); valid where some two rays meet at `min_angle_deg` or more."""
    image_ids = sorted({i for track in tracks for i in track})
    view_of = {image_id: v for v, image_id in enumerate(image_ids)}
    views, points, rays = [], [], []
    for p, track in enumerate(tracks):
        for image_id, kp in track.items():
            views.append(view_of[image_id])
            points.append(p)
            rays.append(model.rays[image_id][kp])
    poses = [model.pose(i) if cams_from_world is None else cams_from_world[i] for i in image_ids]
    return solvers.triangulate_tracks(poses, np.array(views),
                                      np.array(points), np.array(rays), num_points=len(tracks),
                                      min_angle_deg=min_angle_deg)


def _reprojection_ok(model: Model, tracks: list[dict[int, int]], xyz: np.ndarray,
                     max_error_px: float,
                     cams_from_world: dict[int, pycolmap.Rigid3d] | None) -> np.ndarray:
    """Whether every observation of each track reprojects within `max_error_px` (poses:
    `cams_from_world`, or the registered ones)."""
    ok = np.isfinite(xyz).all(axis=1)
    by_image: dict[int, tuple[list[int], list[int]]] = {}
    for p, track in enumerate(tracks):
        for image_id, kp in track.items():
            by_image.setdefault(image_id, ([], []))
            by_image[image_id][0].append(p)
            by_image[image_id][1].append(kp)
    for image_id, (ps, kps) in by_image.items():
        ps = np.array(ps)
        pose = None if cams_from_world is None else cams_from_world[image_id]
        errors = model.reprojection_errors(image_id, np.array(kps), np.nan_to_num(xyz[ps]), pose)
        bad = ps[errors > max_error_px]
        ok[bad] = False
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
