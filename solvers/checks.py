"""Input checks: every malformed input becomes a ValueError that names the problem."""

from __future__ import annotations

import numpy as np


def _as_float_matrix(values, name: str) -> np.ndarray:
    try:
        array = np.asarray(values, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{name} must be a numeric array: {exc}") from None
    if array.ndim != 2:
        raise ValueError(f"{name} must be 2-D, got shape {array.shape}")
    if not np.isfinite(array).all():
        raise ValueError(f"{name} contains NaN or inf")
    return array


def as_rays(values, name: str) -> np.ndarray:
    """(N, 3) unit bearing vectors from (N, 3) rays or (N, 2) normalized coordinates."""
    array = _as_float_matrix(values, name)
    if array.shape[1] == 2:
        array = np.hstack([array, np.ones((len(array), 1))])
    elif array.shape[1] != 3:
        raise ValueError(f"{name} must have shape (N, 2) or (N, 3), got {array.shape}")
    norms = np.sqrt(np.einsum("ij,ij->i", array, array))
    if not (np.isfinite(norms) & (norms > 0)).all():  # zero, or squares out of range
        largest = np.abs(array).max(axis=1, keepdims=True)
        if (largest == 0).any():
            raise ValueError(f"{name} contains a zero-length ray")
        array = array / largest
        norms = np.linalg.norm(array, axis=1)
    return np.ascontiguousarray(array / norms[:, None])


def as_points3D(values, name: str) -> np.ndarray:
    array = _as_float_matrix(values, name)
    if array.shape[1] != 3:
        raise ValueError(f"{name} must have shape (N, 3), got {array.shape}")
    return np.ascontiguousarray(array)


def check_same_length(a: np.ndarray, b: np.ndarray, name_a: str, name_b: str,
                      minimum: int = 0) -> None:
    if len(a) != len(b):
        raise ValueError(f"{name_a} and {name_b} differ in length: {len(a)} vs {len(b)}")
    if len(a) < minimum:
        raise ValueError(f"need at least {minimum} correspondences, got {len(a)}")


def as_thresholds(max_error, num_data: int) -> np.ndarray:
    """(num_data,) positive finite thresholds from one value or one per datum."""
    try:
        array = np.asarray(max_error, dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError(f"max_error must be a positive finite number or array, "
                         f"got {max_error!r}") from None
    if array.ndim == 0:
        check_positive("max_error", max_error)
        return np.full(num_data, float(array))
    if array.shape != (num_data,):
        raise ValueError(f"max_error must be one number or one per correspondence "
                         f"({num_data}), got shape {array.shape}")
    if not (np.isfinite(array).all() and (array > 0).all()):
        raise ValueError("max_error must hold positive finite numbers")
    return np.ascontiguousarray(array)


def check_positive(name: str, value: float) -> None:
    if not (isinstance(value, (int, float, np.floating)) and np.isfinite(value) and value > 0):
        raise ValueError(f"{name} must be a positive finite number, got {value!r}")


def check_choice(name: str, value: str, choices: tuple[str, ...]) -> None:
    if value not in choices:
        raise ValueError(f"unknown {name} {value!r}; choose one of {', '.join(choices)}")


def as_pose_rows(poses, name: str) -> np.ndarray:
    """(K, 12) rows of the 3x4 matrices [R | t] of a sequence of `pycolmap.Rigid3d`."""
    try:
        rows = [pose.matrix().reshape(-1) for pose in poses]
    except (TypeError, AttributeError):
        raise ValueError(f"{name} must be a sequence of pycolmap.Rigid3d") from None
    return np.array(rows, dtype=np.float64).reshape(-1, 12)


def as_camera_index(values, name: str, num_cameras: int) -> np.ndarray:
    """(N,) int32 indices into a rig's `num_cameras` cameras."""
    array = np.asarray(values)
    if array.ndim != 1 or not (array.size == 0 or np.issubdtype(array.dtype, np.integer)):
        raise ValueError(f"{name} must be a 1-D array of integers, got shape {array.shape} "
                         f"and dtype {array.dtype}")
    if array.size and (array.min() < 0 or array.max() >= num_cameras):
        raise ValueError(f"{name} out of range of the rig's {num_cameras} cameras")
    return np.ascontiguousarray(array, dtype=np.int32)


def check_rig_has_baseline(cams_from_rig_rows: np.ndarray, name: str) -> None:
    """A generalized relative pose needs cameras at two centres at least: the baseline
    gives the translation its scale."""
    matrices = cams_from_rig_rows.reshape(-1, 3, 4)
    centres = -np.einsum("kji,kj->ki", matrices[:, :, :3], matrices[:, :, 3])  # -R^T t
    if len(centres) == 0 or np.ptp(centres, axis=0).max() <= 1e-9 * max(1.0, np.abs(centres).max()):
        raise ValueError(f"{name}: the rig's cameras share one centre (no baseline); "
                         "use relative_pose for a single camera")
