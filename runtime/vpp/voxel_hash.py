"""Open-addressing hash of packed voxel keys (int64), compiled: the one voxel table of the VPP.

Fibonacci hashing (the key times 2^64 / golden ratio, the top bits) and linear probing in a
power-of-two table whose empty slots hold EMPTY (-1; packed keys are non-negative). Two users:
the partition's odom-frame label memory (runtime/vpp/partition/label_memory.py: voxel -> the
label last seen there, kept between scans) and the tracker's template thinning
(runtime/vpp/tracking/geometry.py: the first point of each voxel, one call). Each packs its own
keys (the memory's are absolute odom cells, the thinning's relative to the points' lowest cell);
both ask one question of the table: where is this key, or where would it go.

The VPP's other spatial structures answer other questions: the partition's cluster cells
(runtime/vpp/partition/clustering.py: sorted per-object cell keys, eps-connectivity of one
scan's movable points) and the dense grid for "nearest within r" (runtime/common/spatial_grid.py:
the tracker's registration and labelling, the odometry's mover exclusion).
"""
from __future__ import annotations

import numpy as np
from numba import njit

#: The empty slot's key.
EMPTY = np.int64(-1)
#: 2^64 / golden ratio: Fibonacci hashing's multiplier.
GOLDEN = np.uint64(0x9E3779B97F4A7C15)


@njit(cache=True, nogil=True)
def find_slot(keys, key, shift):  # pragma: no cover - compiled
    """The slot of `keys` (power-of-two length, 2^(64 - shift)) holding key, or the empty slot
    where it would go (linear probing from its hash)."""
    mask = keys.shape[0] - 1
    h = np.int64((np.uint64(key) * GOLDEN) >> np.uint64(shift))
    while keys[h] != key and keys[h] != EMPTY:
        h = (h + 1) & mask
    return h


__all__ = ["EMPTY", "GOLDEN", "find_slot"]
