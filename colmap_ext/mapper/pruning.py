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
    candidates = [p for p in touched if p in model.tracks]
    angles = max_triangulation_angles_deg(model, candidates)
    removed_points = 0
    for point_id, angle in zip(candidates, angles):
        if not _supported(model, point_id, angle, options, final):
            model.delete_point(point_id)
            removed_points += 1
    return removed_observations, removed_points


def _supported(model: Model, point_id: int, angle_deg: float, options: MapperOptions,
               final: bool) -> bool:
    track = model.tracks[point_id]
    if len(track) < 2:
        return False
    age = model.num_registered - model.born[point_id]
    if len(track) < options.min_track_length and (final or age >= options.track_grace_registrations):
        return False
    return angle_deg >= options.min_tri_angle_deg


def max_triangulation_angles_deg(model: Model, point_ids: list[int]) -> np.ndarray:
    """The widest angle between two rays of each point's track (0 for single rays)."""
    if not point_ids:
        return np.zeros(0)
    image_index = {image_id: k for k, image_id in enumerate(model.poses)}
    centres = np.array([model.centre(image_id) for image_id in model.poses])
    lengths = np.array([len(model.tracks[p]) for p in point_ids])
    observed = np.array([image_index[i] for p in point_ids for i in model.tracks[p]], np.int64)
    rows = np.repeat(np.arange(len(point_ids)), lengths)
    columns = np.arange(len(rows)) - np.repeat(np.cumsum(lengths) - lengths, lengths)
    rays = np.full((len(point_ids), lengths.max(), 3), np.nan)
    rays[rows, columns] = model.xyz[np.repeat(point_ids, lengths)] - centres[observed]
    rays /= np.linalg.norm(rays, axis=2, keepdims=True)
    cosines = np.nan_to_num(np.einsum("pid,pjd->pij", rays, rays), nan=1.0)
    return np.degrees(np.arccos(np.clip(cosines.min(axis=(1, 2)), -1.0, 1.0)))
