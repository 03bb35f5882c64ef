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
    largest = np.abs(array).max(axis=1, keepdims=True)
    if (largest == 0).any():
        raise ValueError(f"{name} contains a zero-length ray")
    array = array / largest  # no overflow in the norm for huge entries
    return np.ascontiguousarray(array / np.linalg.norm(array, axis=1, keepdims=True))


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
