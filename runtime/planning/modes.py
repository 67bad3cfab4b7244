"""Planner modes: which points the MPC must never touch.

- `all-fixed`: every point is P_fix (the NeuPAN-like baseline; also the mode until the VPP
  partition exists),
- `partitioned`: only the VPP's P_fix constrains the MPC; P_mov may be pushed.
"""
from __future__ import annotations

from enum import Enum

import numpy as np

from runtime.planning.errors import PlannerInputError, check_points


class PlannerMode(str, Enum):
    ALL_FIXED = "all-fixed"
    PARTITIONED = "partitioned"


def constraint_points(
    mode: PlannerMode | str, points_fix_world: np.ndarray, points_mov_world: np.ndarray | None = None
) -> np.ndarray:
    """The (N, 2) points the MPC and the safety supervisor treat as P_fix in this mode."""
    try:
        mode = PlannerMode(mode)
    except ValueError as exc:
        raise PlannerInputError(f"unknown planner mode {mode!r}; known: {[m.value for m in PlannerMode]}") from exc
    fix = check_points(points_fix_world, "constraint_points: points_fix_world")
    if mode is PlannerMode.PARTITIONED or points_mov_world is None:
        return fix
    mov = check_points(points_mov_world, "constraint_points: points_mov_world")
    return np.concatenate([fix, mov]) if mov.shape[0] else fix
