"""Which scan points the tracker looks at, compiled: those in the tracked objects' boxes (one
pass for all objects), the points each mask labelled grouped by object, and an object's
registration candidates in its box."""
from __future__ import annotations

import numpy as np
from numba import njit

from runtime.vpp.partition.labels import FIXED, MOVABLE


@njit(cache=True, nogil=True)
def in_boxes(p, label, lo, hi):  # pragma: no cover - compiled
    """Indices (ascending) of the points that are not ground and lie in at least one of the
    boxes [lo[k], hi[k]]: one pass over the scan for all tracked objects, which then look only
    at these (a pass per object costs ~40 us at 20k points)."""
    out = np.empty(p.shape[0], np.int64)
    n = 0
    ulo = lo[0].copy()  # the union's box first: most points of a scan are far from every object
    uhi = hi[0].copy()
    for k in range(1, lo.shape[0]):
        for a in range(3):
            ulo[a] = min(ulo[a], lo[k, a])
            uhi[a] = max(uhi[a], hi[k, a])
    for i in range(p.shape[0]):
        if label[i] < 0:
            continue
        x = p[i, 0]
        y = p[i, 1]
        z = p[i, 2]
        if not (ulo[0] <= x <= uhi[0] and ulo[1] <= y <= uhi[1] and ulo[2] <= z <= uhi[2]):
            continue
        for k in range(lo.shape[0]):
            if lo[k, 0] <= x <= hi[k, 0] and lo[k, 1] <= y <= hi[k, 1] and lo[k, 2] <= z <= hi[k, 2]:
                out[n] = i
                n += 1
                break
    return out[:n]


@njit(cache=True, nogil=True)
def group_masked(label, in_view, from_memory, oid):  # pragma: no cover - compiled
    """The points a mask labelled this scan (MOVABLE, in view, not from the label memory),
    grouped by object: (ids in order of first appearance, starts (len(ids) + 1), point indices:
    ascending within each object). A filter pass, then a scatter of the selected; a scan has
    at most as many objects as masks, so the id lookup is a short linear search."""
    n = label.shape[0]
    sel = np.empty(n, np.int64)
    m = 0
    for i in range(n):
        if label[i] == MOVABLE and in_view[i] and not from_memory[i]:
            sel[m] = i
            m += 1
    ids = np.empty(m, np.int64)  # at most one per point (no growth: reassigning an array in the
    counts = np.zeros(m, np.int64)  # loop makes numba count references every iteration)
    slot = np.empty(m, np.int64)
    k_ids = 0
    last = -1
    for s in range(m):
        o = oid[sel[s]]
        if last < 0 or ids[last] != o:  # runs of one object are the common case
            last = -1
            for t in range(k_ids):
                if ids[t] == o:
                    last = t
                    break
            if last < 0:
                ids[k_ids] = o
                last = k_ids
                k_ids += 1
        counts[last] += 1
        slot[s] = last
    starts = np.zeros(k_ids + 1, np.int64)
    for t in range(k_ids):
        starts[t + 1] = starts[t] + counts[t]
    fill = starts[:k_ids].copy()
    idx = np.empty(m, np.int64)
    for s in range(m):
        idx[fill[slot[s]]] = sel[s]
        fill[slot[s]] += 1
    return ids[:k_ids], starts, idx


@njit(cache=True, nogil=True)
def box_candidates(p, label, oid, object_id, lo, hi, near):  # pragma: no cover - compiled
    """The indices of `near` (in_boxes) whose points are inside the box [lo, hi] and FIXED (or
    object_id's own when object_id >= 0)."""
    out = np.empty(near.shape[0], np.int64)
    n = 0
    for s in range(near.shape[0]):
        i = near[s]
        if not (label[i] == FIXED or (object_id >= 0 and oid[i] == object_id)):
            continue
        if lo[0] <= p[i, 0] <= hi[0] and lo[1] <= p[i, 1] <= hi[1] and lo[2] <= p[i, 2] <= hi[2]:
            out[n] = i
            n += 1
    return out[:n]



__all__ = ["box_candidates", "group_masked", "in_boxes"]
