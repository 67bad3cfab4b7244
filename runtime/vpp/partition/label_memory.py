"""The partition's odom-frame label memory (step 5): voxel -> the label last seen there.

Seen, non-ground points write their final label into a 3-D voxel hash (voxel -> label, object
id, cost, stamp); unseen points take their voxel's remembered label if it is younger than the
maximum age, else fixed (the safe default). Within one scan a voxel with any fixed point is
fixed (a voxel straddling a box and the wall behind it must not make the wall touchable); among
movable points the highest cost wins.

The table is runtime/vpp/voxel_hash.py's (shared with the tracker's template thinning); the
voxel keys are this memory's own: 21 bits per axis, offset to be non-negative (memory_voxel_key,
which the partition's projection pass also computes per point).
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit

from runtime.vpp.partition.labels import FIXED, MOVABLE
from runtime.vpp.voxel_hash import EMPTY, find_slot

_MOFF = 1 << 20  # memory voxels: 21 bits per axis (non-negative keys; -1 marks an empty slot)

#: What the label memory holds per slot, beside its key: one record, so that a voxel found
#: costs two cache lines (key, record), not five (the table is mostly out of cache by the next
#: scan); the keys stay an array of their own, so that a voxel not found costs one.
_SLOT = np.dtype([("stamp", np.float64), ("cost", np.float32), ("obj", np.int32), ("label", np.int8)], align=True)


@njit(cache=True, nogil=True)
def memory_voxel_key(x, y, z, inv):  # pragma: no cover - compiled
    """The memory's key of the voxel holding odom-frame point (x, y, z) (inv: 1 / voxel edge)."""
    cx = min(max(int(math.floor(x * inv)), -_MOFF), _MOFF - 1) + _MOFF
    cy = min(max(int(math.floor(y * inv)), -_MOFF), _MOFF - 1) + _MOFF
    cz = min(max(int(math.floor(z * inv)), -_MOFF), _MOFF - 1) + _MOFF
    return (np.int64(cx) << 42) | (np.int64(cy) << 21) | np.int64(cz)


@njit(cache=True, nogil=True)
def _voxel_keys(pts, inv, sel):  # pragma: no cover - compiled
    out = np.full(pts.shape[0], EMPTY)
    for i in range(pts.shape[0]):
        if sel[i]:
            out[i] = memory_voxel_key(pts[i, 0], pts[i, 1], pts[i, 2], inv)
    return out


@njit(inline="always")
def rigid_point(p, i, T):  # pragma: no cover - compiled
    """Point i of p (as float64) and T (4x4) applied to it: (x, y, z, X, Y, Z)."""
    x = np.float64(p[i, 0])
    y = np.float64(p[i, 1])
    z = np.float64(p[i, 2])
    X = T[0, 0] * x + T[0, 1] * y + T[0, 2] * z + T[0, 3]
    Y = T[1, 0] * x + T[1, 1] * y + T[1, 2] * z + T[1, 3]
    Z = T[2, 0] * x + T[2, 1] * y + T[2, 2] * z + T[2, 3]
    return x, y, z, X, Y, Z


@njit(cache=True, nogil=True)
def odom_keys(p, T, inv, ground, out):  # pragma: no cover - compiled
    """out[i] = the voxel key of point i carried to the odom frame by T (as
    projection.transform), for the points not on the ground (EMPTY for those): no p_odom array."""
    for i in range(p.shape[0]):
        if ground[i]:
            out[i] = EMPTY
            continue
        _, _, _, X, Y, Z = rigid_point(p, i, T)
        out[i] = memory_voxel_key(X, Y, Z, inv)


@njit(cache=True, nogil=True)
def _mem_write(table, pkeys, sel, labels, now):  # pragma: no cover - compiled
    """Write the labels (label, object id, cost per point) of the points with sel set (and a key)
    into their voxels of table (keys, records, shift); returns the number of new slots used."""
    keys, tbl, shift = table
    plab, pobj, pcost = labels
    new = 0
    for i in range(pkeys.shape[0]):
        key = pkeys[i]
        if key == EMPTY or not sel[i]:
            continue
        h = find_slot(keys, key, shift)
        r = tbl[h]
        if keys[h] == EMPTY:
            keys[h] = key
            new += 1
        elif r.stamp == now:  # merge with this scan's earlier points: fixed wins, then max cost
            if r.label == 0:
                continue
            if plab[i] == 1 and (pcost[i] < r.cost or (pcost[i] == r.cost and pobj[i] >= r.obj)):
                continue
        r.label = plab[i]
        r.obj = pobj[i]
        r.cost = pcost[i]
        r.stamp = now
    return new


@njit(cache=True, nogil=True)
def _mem_reinsert(table, okeys, records):  # pragma: no cover - compiled
    """Insert distinct entries (a rebuild) with their own records (label, object id, cost,
    stamp); returns the count."""
    keys, tbl, shift = table
    olab, oobj, ocost, ostamp = records
    for i in range(okeys.shape[0]):
        h = find_slot(keys, okeys[i], shift)
        r = tbl[h]
        keys[h] = okeys[i]
        r.label = olab[i]
        r.obj = oobj[i]
        r.cost = ocost[i]
        r.stamp = ostamp[i]
    return okeys.shape[0]


@njit(cache=True, nogil=True)
def _mem_read(table, pkeys, sel, want, now, max_age, out):  # pragma: no cover - compiled
    """Read the voxels of the points whose sel[i] == want (and that have a key) into out (label,
    object id, cost, found)."""
    keys, tbl, shift = table
    olab, oobj, ocost, found = out
    for i in range(pkeys.shape[0]):
        key = pkeys[i]
        if key == EMPTY or sel[i] != want:
            continue
        h = find_slot(keys, key, shift)
        if keys[h] != key:
            continue
        r = tbl[h]
        if now - r.stamp <= max_age:
            found[i] = True
            olab[i] = r.label
            oobj[i] = r.obj
            ocost[i] = r.cost


class LabelMemory:
    """Odom-frame voxel hash: voxel -> (label, object id, cost, stamp of the scan that wrote it).

    An open-addressing table (keys, and a numpy record array of _SLOT) driven by numba (a Python
    dict would mean a loop over points). Entries older than max_age_s read as absent; they are
    dropped when the table is rebuilt (at half full), and the table doubles only if the live
    entries still fill it.
    """

    def __init__(self, voxel_m: float, max_age_s: float, initial_slots: int = 1 << 15) -> None:
        self.voxel_m = float(voxel_m)
        self.max_age_s = float(max_age_s)
        self._alloc(1 << max(6, int(initial_slots - 1).bit_length()))

    def _alloc(self, slots: int) -> None:
        self.keys = np.full(slots, EMPTY)
        self.table = np.zeros(slots, _SLOT)
        self.table["obj"] = -1
        self.table["cost"] = np.nan
        self.table["stamp"] = -np.inf
        self.shift = 64 - (slots.bit_length() - 1)
        self.used = 0

    # the table's columns (views)
    label = property(lambda self: self.table["label"])
    object_id = property(lambda self: self.table["obj"])
    cost = property(lambda self: self.table["cost"])
    stamp = property(lambda self: self.table["stamp"])

    def __len__(self) -> int:
        """Slots in use (live and expired, until the next rebuild)."""
        return self.used

    def _tables(self) -> tuple:
        return self.keys, self.table, self.shift

    def _rebuild(self, now: float, incoming: int) -> None:
        live = (self.keys != EMPTY) & (now - self.stamp <= self.max_age_s)
        old = (self.label[live], self.object_id[live], self.cost[live], self.stamp[live])
        okeys = self.keys[live]
        slots = self.keys.shape[0]
        while 2 * (int(live.sum()) + incoming) > slots:
            slots *= 2
        self._alloc(slots)
        self.used = _mem_reinsert(self._tables(), okeys, old)

    def voxel_keys(self, points_odom: np.ndarray, sel: np.ndarray) -> np.ndarray:
        """Voxel key of each selected point (-1 for the others)."""
        return _voxel_keys(points_odom, 1.0 / self.voxel_m, sel)

    def write(self, points_odom: np.ndarray, write: np.ndarray, label: np.ndarray, object_id: np.ndarray,
              cost: np.ndarray, stamp_s: float, keys: np.ndarray | None = None) -> None:
        """Store the labels of the points where `write` is True (seen, non-ground). keys: from
        voxel_keys (computed here when not given; read only where `write` is True)."""
        pkeys = self.voxel_keys(points_odom, write) if keys is None else keys
        self.write_keys(pkeys, write, label, object_id, cost, stamp_s)

    def write_keys(self, keys, write, label, object_id, cost, stamp_s: float) -> None:
        """write() with the keys given (EMPTY: no voxel), where `write` is True."""
        incoming = int(np.count_nonzero(write))
        if 2 * (self.used + incoming) > self.keys.shape[0]:
            self._rebuild(stamp_s, incoming)
        labels = (np.asarray(label, np.int8), np.asarray(object_id, np.int32), np.asarray(cost, np.float32))
        self.used += _mem_write(self._tables(), keys, write, labels, float(stamp_s))

    def read(self, points_odom: np.ndarray, read: np.ndarray, now_s: float):
        """(found, label, object_id, cost) for the points where `read` is True."""
        n = points_odom.shape[0]
        found = np.zeros(n, bool)
        lab = np.zeros(n, np.int8)
        obj = np.full(n, -1, np.int32)
        cost = np.full(n, np.nan, np.float32)
        self.read_into(points_odom, read, now_s, lab, obj, cost, found)
        return found, lab, obj, cost

    def read_into(self, points_odom, read, now_s, label, object_id, cost, found, keys=None) -> None:
        """As read, overwriting label/object_id/cost and setting found only where found."""
        pkeys = self.voxel_keys(points_odom, read) if keys is None else keys
        self.read_keys(pkeys, read, True, now_s, (label, object_id, cost, found))

    def read_keys(self, keys, sel, want: bool, now_s, out) -> None:
        """read_into with the keys given (EMPTY: no voxel), for the points whose sel is `want`;
        out: (label, object_id, cost, found), overwritten where found."""
        _mem_read(self._tables(), keys, sel, bool(want), float(now_s), self.max_age_s, out)

    def fix_object(self, object_id: int) -> int:
        """Correcting mode (DCT eq. 14): every remembered voxel of object_id becomes FIXED (object
        id -1, cost NaN; stamps kept, so they age out as before). Returns the voxels relabelled.
        A vectorized pass over the table (rare: once per failed push), no kernel."""
        hit = (self.keys != EMPTY) & (self.label == MOVABLE) & (self.object_id == int(object_id))
        self.label[hit] = FIXED
        self.object_id[hit] = -1
        self.cost[hit] = np.nan
        return int(np.count_nonzero(hit))


__all__ = ["LabelMemory", "memory_voxel_key", "odom_keys"]
