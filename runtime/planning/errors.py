"""Named errors of the planning stage and input checks: each error says what was wrong and where."""
from __future__ import annotations

import numpy as np


class PlannerInputError(ValueError):
    """An input handed to a planning component (pose, points, reference, command) is malformed."""


class DistanceModelError(RuntimeError):
    """The distance model returned arrays of the wrong shape or non-finite values."""


def check_points(points: object, where: str) -> np.ndarray:
    """Return `points` as a C-contiguous float64 (N, 2) array or raise PlannerInputError."""
    arr = np.asarray(points, dtype=np.float64)
    if arr.ndim != 2 or arr.shape[1] != 2:
        raise PlannerInputError(f"{where}: expected points of shape (N, 2), got {arr.shape}")
    if not np.isfinite(arr).all():
        bad = int((~np.isfinite(arr)).any(axis=1).sum())
        raise PlannerInputError(f"{where}: {bad} of {arr.shape[0]} points are NaN or infinite")
    return np.ascontiguousarray(arr)


def check_vector(value: object, size: int, where: str, name: str) -> np.ndarray:
    """Return `value` as a finite float64 vector of length `size` or raise PlannerInputError."""
    arr = np.asarray(value, dtype=np.float64).reshape(-1)
    if arr.shape != (size,):
        raise PlannerInputError(f"{where}: {name} must have {size} values, got shape {np.shape(value)}")
    if not np.isfinite(arr).all():
        raise PlannerInputError(f"{where}: {name} contains NaN or infinite values: {arr.tolist()}")
    return arr
