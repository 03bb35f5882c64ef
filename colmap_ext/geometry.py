"""Geometry shared by the mapper, the hierarchical mapper and the evaluation: angles of
rotations and between vectors, rotations nearest to a matrix, similarity fits and
Sampson errors."""

from __future__ import annotations

import numpy as np
import pycolmap

# A quaternion written by hand to four digits ([0.7071, 0, 0.7071, 0]) is one; it is normalized.
QUATERNION_NORM_TOLERANCE = 1e-3


def rotation_angles_deg(R: np.ndarray) -> np.ndarray:
    """Angles of rotations (n,3,3) in degrees, as atan2(sin, cos): exact near 0 where arccos is not."""
    cos = (np.trace(R, axis1=1, axis2=2) - 1) / 2
    skew = np.stack([R[:, 2, 1] - R[:, 1, 2], R[:, 0, 2] - R[:, 2, 0], R[:, 1, 0] - R[:, 0, 1]], axis=1)
    sin = np.linalg.norm(skew, axis=1) / 2
    return np.degrees(np.arctan2(sin, cos))


def vector_angles_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Angles between rows of a and b (n,3) in degrees, as atan2(|a x b|, a.b)."""
    return np.degrees(np.arctan2(np.linalg.norm(np.cross(a, b), axis=1), np.sum(a * b, axis=1)))


def nearest_rotation(matrix: np.ndarray) -> np.ndarray:
    """The rotation nearest to a 3x3 `matrix` in the Frobenius norm (its SVD, the smallest
    singular direction flipped where the determinant would be -1)."""
    u, _, vt = np.linalg.svd(matrix)
    return u @ np.diag([1.0, 1.0, np.sign(np.linalg.det(u @ vt))]) @ vt


def mean_rotation(rotations: np.ndarray) -> np.ndarray:
    """The chordal mean of `rotations` (n,3,3): the rotation nearest to their sum."""
    return nearest_rotation(np.sum(rotations, axis=0))


def fit_similarity(source: np.ndarray, target: np.ndarray,
                   rotation: np.ndarray | None = None, with_scale: bool = True) -> pycolmap.Sim3d:
    """The least-squares similarity taking `source` points (n,3) onto `target` (Umeyama
    1991); with `rotation` given, its scale and translation alone; without `with_scale`,
    scale 1: the rigid transform, which keeps a metric model's errors in metres.

    Not pycolmap.estimate_sim3d: it refuses 2 points (pycolmap 4.2.1: "Check failed:
    src.size() >= kMinNumSamples (2 vs. 3)"), which a 2-view model under evaluation and
    two cross-registrations (merging.py) have, and it cannot keep a given rotation."""
    mean_source, mean_target = source.mean(axis=0), target.mean(axis=0)
    offsets_source, offsets_target = source - mean_source, target - mean_target
    if rotation is None:
        rotation = nearest_rotation(offsets_target.T @ offsets_source)
    moved = offsets_source @ rotation.T
    scale = np.sum(offsets_target * moved) / max(np.sum(offsets_source ** 2), 1e-300) \
        if with_scale else 1.0
    return pycolmap.Sim3d(scale, pycolmap.Rotation3d(rotation),
                          mean_target - scale * rotation @ mean_source)


def sampson_angles(E: np.ndarray, rays1: np.ndarray, rays2: np.ndarray) -> np.ndarray:
    """Angular Sampson errors (radians) of corresponding unit rays to rays2^T E rays1 = 0:
    to first order, the angle by which the rays must turn to meet. Rays may point
    anywhere (the solvers' relative-pose error, solvers.relative_pose)."""
    along2 = rays1 @ E.T  # E f1: normal of f1's epipolar plane in camera 2
    along1 = rays2 @ E    # E^T f2
    residual = np.einsum("ij,ij->i", along2, rays2)
    tangent2 = along2 - residual[:, None] * rays2
    tangent1 = along1 - residual[:, None] * rays1
    denominator = np.einsum("ij,ij->i", tangent1, tangent1) + \
        np.einsum("ij,ij->i", tangent2, tangent2)
    return np.abs(residual) / np.sqrt(np.maximum(denominator, 1e-300))
