"""Triangulation (paper, step 4c): a new image's compatible features either extend
an existing point's track or, seen in enough images, become a new point."""

from __future__ import annotations

import numpy as np

import solvers
from colmap_ext.mapper.guided_matching import compatible_features
from colmap_ext.mapper.model import Model
from colmap_ext.mapper.options import GuidedMatchingOptions, TriangulationOptions


def triangulate_image(model: Model, image_id: int, neighbours: list[int],
                      guided: GuidedMatchingOptions, triangulation: TriangulationOptions,
                      min_views: int) -> tuple[int, int]:
    """Guided matching of `image_id`'s free keypoints against `neighbours`, then track
    extension and new points with at least `min_views` observations. Returns
    (observations added to existing points, new points)."""
    free = np.flatnonzero(model.point_of[image_id] < 0)
    candidates: dict[int, list[tuple[int, int]]] = {}  # kp -> [(other image, other kp)]
    model.nearest.prefetch(image_id, neighbours)
    for other_id in neighbours:
        kps, other_kps, _ = compatible_features(model, image_id, other_id, free, guided)
        for kp, other_kp in zip(kps.tolist(), other_kps.tolist()):
            candidates.setdefault(kp, []).append((other_id, other_kp))
    num_extended = _extend_tracks(model, image_id, candidates, triangulation)
    num_new = _create_points(model, image_id, candidates, triangulation, min_views)
    return num_extended, num_new


def _extend_tracks(model: Model, image_id: int, candidates: dict[int, list[tuple[int, int]]],
                   triangulation: TriangulationOptions) -> int:
    """Keypoints compatible with an observation of an existing point join its track
    when the point reprojects onto them (one keypoint per point, the closest)."""
    observed = set(model.observations(image_id)[1].tolist())
    kps, point_ids = [], []
    for kp, matches in candidates.items():
        for other_id, other_kp in matches:
            point_id = model.point_of[other_id][other_kp]
            if point_id >= 0 and point_id not in observed:
                kps.append(kp)
                point_ids.append(point_id)
    if not kps:
        return 0
    kps, point_ids = np.array(kps), np.array(point_ids)
    errors = model.reprojection_errors(image_id, kps, model.xyz[point_ids])
    ok = errors <= triangulation.max_reproj_error_px
    kps, point_ids, errors = kps[ok], point_ids[ok], errors[ok]
    added = 0
    for i in np.argsort(errors, kind="stable"):
        kp, point_id = int(kps[i]), int(point_ids[i])
        if model.point_of[image_id][kp] < 0 and point_id not in observed:
            model.add_observation(point_id, image_id, kp)
            observed.add(point_id)
            added += 1
    return added


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
    xyz, valid = triangulate_tracks(model, tracks, triangulation.min_tri_angle_deg)
    ok = valid & _reprojection_ok(model, tracks, xyz, triangulation.max_reproj_error_px)
    created = 0
    for track, point, keep in zip(tracks, xyz, ok):
        if keep and all(model.point_of[i][kp] < 0 for i, kp in track.items()):
            model.add_point(point, track)
            created += 1
    return created


def triangulate_tracks(model: Model, tracks: list[dict[int, int]],
                       min_angle_deg: float) -> tuple[np.ndarray, np.ndarray]:
    """Linear multi-view triangulation of tracks over registered images; valid where
    some two rays meet at `min_angle_deg` or more."""
    image_ids = sorted({i for track in tracks for i in track})
    view_of = {image_id: v for v, image_id in enumerate(image_ids)}
    views, points, rays = [], [], []
    for p, track in enumerate(tracks):
        for image_id, kp in track.items():
            views.append(view_of[image_id])
            points.append(p)
            rays.append(model.rays[image_id][kp])
    return solvers.triangulate_tracks([model.pose(i) for i in image_ids], np.array(views),
                                      np.array(points), np.array(rays), num_points=len(tracks),
                                      min_angle_deg=min_angle_deg)


def _reprojection_ok(model: Model, tracks: list[dict[int, int]], xyz: np.ndarray,
                     max_error_px: float) -> np.ndarray:
    """Whether every observation of each track reprojects within `max_error_px`."""
    ok = np.isfinite(xyz).all(axis=1)
    by_image: dict[int, tuple[list[int], list[int]]] = {}
    for p, track in enumerate(tracks):
        for image_id, kp in track.items():
            by_image.setdefault(image_id, ([], []))
            by_image[image_id][0].append(p)
            by_image[image_id][1].append(kp)
    for image_id, (ps, kps) in by_image.items():
        ps = np.array(ps)
        errors = model.reprojection_errors(image_id, np.array(kps), np.nan_to_num(xyz[ps]))
        bad = ps[errors > max_error_px]
        ok[bad] = False
    return ok
