"""The partition's output: the label of every lidar point (IGNORED, FIXED: P_fix, MOVABLE: P_mov)
with its object id and contact cost (runtime/vpp/partition/__init__.py)."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: Point labels.
IGNORED = np.int8(-1)  # ground or caller-ignored: not an obstacle for the planner
FIXED = np.int8(0)  # P_fix: hard constraint
MOVABLE = np.int8(1)  # P_mov: contact tolerated at the object's cost

MAX_COST = 10.0  # IMPACT scale: 0 brush freely .. 10 never touch


@dataclass(frozen=True)
class PointPartition:
    """Per point (N,): label (IGNORED / FIXED / MOVABLE, int8), object id (int32, -1 unless
    movable), cost (float32, NaN unless movable), in_view (projected into the image this scan),
    from_memory (an unseen point whose label came from the odom-frame memory). Counts of the
    refinement: outliers removed, points added by completion."""

    label: np.ndarray
    object_id: np.ndarray
    cost: np.ndarray
    in_view: np.ndarray
    from_memory: np.ndarray
    n_outliers_removed: int
    n_completed: int

    @property
    def movable(self) -> np.ndarray:
        return self.label == MOVABLE

    @property
    def fixed(self) -> np.ndarray:
        return self.label == FIXED



__all__ = ["FIXED", "IGNORED", "MAX_COST", "MOVABLE", "PointPartition"]
