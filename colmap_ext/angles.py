"""Angles of rotations and between vectors, in the numerically stable atan2 form that
the evaluation and the mapper's model merging both measure with."""

from __future__ import annotations

import numpy as np


def rotation_angles_deg(R: np.ndarray) -> np.ndarray:
    """Angles of rotations (n,3,3) in degrees, as atan2(sin, cos): exact near 0 where arccos is not."""
    cos = (np.trace(R, axis1=1, axis2=2) - 1) / 2
    skew = np.stack([R[:, 2, 1] - R[:, 1, 2], R[:, 0, 2] - R[:, 2, 0], R[:, 1, 0] - R[:, 0, 1]], axis=1)
    sin = np.linalg.norm(skew, axis=1) / 2
    return np.degrees(np.arctan2(sin, cos))


def vector_angles_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Angles between rows of a and b (n,3) in degrees, as atan2(|a x b|, a.b)."""
    return np.degrees(np.arctan2(np.linalg.norm(np.cross(a, b), axis=1), np.sum(a * b, axis=1)))


def mean_rotation(rotations: np.ndarray) -> np.ndarray:
    """The rotation nearest (Frobenius) to the sum of `rotations` (n,3,3): their chordal
    mean."""
    u, _, vt = np.linalg.svd(np.sum(rotations, axis=0))
    return u @ np.diag([1.0, 1.0, np.linalg.det(u @ vt)]) @ vt
