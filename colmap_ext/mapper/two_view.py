"""Verified two-view matches: the database's, or our own 5-point RANSAC on raw matches.

Verification happens in memory; the user's database is never written.
"""

from __future__ import annotations

import numpy as np
from tqdm import tqdm

import solvers
from colmap_ext.mapper.guided_matching import pair_pixel_angles
from colmap_ext.mapper.model import Model
from colmap_ext.mapper.options import TwoViewOptions

Pair = tuple[int, int]


def verified_matches(model: Model, two_view: TwoViewOptions, seed: int | None,
                     progress: bool = True) -> dict[Pair, np.ndarray]:
    """(id1, id2) -> (m, 2) inlier keypoint indices, for the model's images; matches
    of keypoints that their camera model gives no ray are left out. `seed`: the
    RANSAC's of pairs the database left unverified (None: unseeded)."""
    db = model.db
    wanted = set(model.image_ids)
    if db.verified_matches:
        with_rays = {pair: with_rays_only(model, pair, m)
                     for pair, m in db.verified_matches.items()
                     if pair[0] in wanted and pair[1] in wanted}
        return {pair: m for pair, m in with_rays.items()
                if len(m) >= two_view.min_num_inliers}
    pairs = {pair: m for pair, m in db.raw_matches.items()
             if pair[0] in wanted and pair[1] in wanted}
    verified: dict[Pair, np.ndarray] = {}
    for (id1, id2), matches in tqdm(pairs.items(), desc="verifying pairs", unit="pair",
                                    disable=not progress, leave=False):
        inliers = verify_pair(model, id1, id2, with_rays_only(model, (id1, id2), matches),
                              two_view, seed)
        if inliers is not None:
            verified[(id1, id2)] = inliers
    return verified


def verify_pair(model: Model, id1: int, id2: int, matches: np.ndarray,
                two_view: TwoViewOptions, seed: int | None) -> np.ndarray | None:
    """The matches consistent with one calibrated relative pose, or None."""
    if len(matches) < max(5, two_view.min_num_inliers):
        return None
    result = relative_pose(model, (id1, id2), matches, two_view.max_error_px,
                           two_view.min_num_inliers, seed)
    return None if result is None else matches[result.inlier_mask]


def relative_pose(model: Model, pair: Pair, matches: np.ndarray, max_error_px: float,
                  min_num_inliers: int, seed: int | None) -> solvers.RelativePoseResult | None:
    """The 5-point RANSAC's relative pose of a pair from its matches' rays, the pixel
    threshold turned into each match's angle (pair_pixel_angles); None where it fails."""
    id1, id2 = pair
    try:
        return solvers.relative_pose(
            model.rays[id1][matches[:, 0]], model.rays[id2][matches[:, 1]],
            max_error=max_error_px * pair_pixel_angles(model, id1, matches[:, 0], id2,
                                                       matches[:, 1]),
            min_num_inliers=min_num_inliers, seed=seed)
    except solvers.EstimationError:
        return None


def with_rays_only(model: Model, pair: Pair, matches: np.ndarray) -> np.ndarray:
    """The matches both of whose keypoints have rays (Model.has_rays): `matches` itself
    where they all do, as they do within most camera models' images (a copy would double
    the verified matches held: 68 MiB at 150 generator images)."""
    keep = model.has_rays(pair[0], matches[:, 0]) & model.has_rays(pair[1], matches[:, 1])
    return matches if keep.all() else matches[keep]


def pair_graph(matches: dict[Pair, np.ndarray]) -> dict[int, dict[int, np.ndarray]]:
    """image -> other image -> (m, 2) matches oriented from the image to the other."""
    graph: dict[int, dict[int, np.ndarray]] = {}
    for (id1, id2), m in matches.items():
        graph.setdefault(id1, {})[id2] = m
        graph.setdefault(id2, {})[id1] = m[:, ::-1]
    return graph
