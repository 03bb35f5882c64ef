"""Pruning (paper, step 4e): observations no longer geometrically compatible with
their point go, then points without enough support or triangulation angle."""

from __future__ import annotations

import numpy as np

from colmap_ext.mapper.model import Model
from colmap_ext.mapper.options import MapperOptions


def prune(model: Model, image_ids: list[int], options: MapperOptions,
          final: bool = False) -> tuple[int, int]:
    """Prune the observations in `image_ids` and the points they see. Before the end
    (`final` False), points younger than the grace period may keep two-view tracks.
    Returns (observations removed, points removed)."""
    removed_observations = 0
    touched: set[int] = set()
    for image_id in image_ids:
        kps, point_ids = model.observations(image_id)
        touched.update(point_ids.tolist())
        errors = model.reprojection_errors(image_id, kps, model.xyz[point_ids])
        for point_id in point_ids[errors > options.max_reproj_error_px].tolist():
            model.delete_observation(point_id, image_id)
            removed_observations += 1
    removed_points = 0
    for point_id in touched:
        if point_id in model.tracks and not _supported(model, point_id, options, final):
            model.delete_point(point_id)
            removed_points += 1
    return removed_observations, removed_points


def _supported(model: Model, point_id: int, options: MapperOptions, final: bool) -> bool:
    track = model.tracks[point_id]
    if len(track) < 2:
        return False
    age = model.num_registered - model.born[point_id]
    if len(track) < options.min_track_length and (final or age >= options.track_grace_registrations):
        return False
    return max_triangulation_angle_deg(model, point_id) >= options.min_tri_angle_deg


def max_triangulation_angle_deg(model: Model, point_id: int) -> float:
    """The widest angle between two rays of a point's track."""
    centres = np.array([model.centre(image_id) for image_id in model.tracks[point_id]])
    directions = model.xyz[point_id] - centres
    directions /= np.maximum(np.linalg.norm(directions, axis=1, keepdims=True), 1e-30)
    cosines = directions @ directions.T
    return float(np.degrees(np.arccos(np.clip(cosines.min(), -1.0, 1.0))))
