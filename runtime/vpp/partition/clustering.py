"""Step 4 of the partition, compiled: per-object Euclidean clustering of the movable points,
outlier suppression and completion (the refinement; runtime/vpp/partition/__init__.py).

The spatial index here is the cluster cells: every movable point gets a packed key (its mask's
index in the top bits, then its cell on each axis, cells of side eps/2, 18 bits per axis), and
the keys are sorted; a run of equal keys is an occupied cell. One grid per object falls out of
the key (two touching objects stay apart), and the cells z-2..z+2 of one (x, y) column are one
contiguous key range (one search, then a scan). The points of one cell are all within eps of
each other (diagonal 0.87 eps), so a cell is one node of the connectivity graph; two cells up to
2 apart are joined when any pair of their points is within eps (cell_near, first hit wins). Cost
grows with the number of occupied cells, not with the points per cell.

Why not the dense grid of runtime/common/spatial_grid.py: that one answers "nearest within r"
over one object's bounding box, with cells grown until the box has at most 2^20 of them; this
one must keep cells of exactly eps/2 over a whole scan (tens of metres: far more cells than a
dense grid holds) and separate the objects. The label memory's voxel table
(runtime/vpp/voxel_hash.py) persists between scans and answers "what was here"; these cells live
for one call.

Kernel arguments, grouped: points = (p_cam, the seen points' indices (ascending), pix, midx); keys = (sorted keys, their point
indices) (cell_keys); cells = (point indices sp, the occupied cells' keys, their starts in sp);
gate = (warped, masks, warp tables, lens, costs, completion_dilate_px): the completion's mask
test; limits = (eps, n_min, depth_gap (-1: off), completion on).
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit

from runtime.vpp.homography.kernels import MaskCrops, WarpTables
from runtime.vpp.partition.gating import near_mask, near_warp
from runtime.vpp.voxel_hash import EMPTY, find_slot

_OFF = 1 << 17  # cluster cells: 18 bits per axis, object index above them


@njit(cache=True, nogil=True)
def cell(x, inv):  # pragma: no cover - compiled
    """The cell index of coordinate x (inv: 1 / cell side), offset to be non-negative, clamped."""
    c = int(math.floor(x * inv))
    return min(max(c, -_OFF), _OFF - 1) + _OFF


@njit(cache=True, nogil=True)
def pack(m, cx, cy, cz):  # pragma: no cover - compiled
    """The cell key: mask index m, then the cell on x, y, z."""
    return (np.int64(m) << 54) | (np.int64(cx) << 36) | (np.int64(cy) << 18) | np.int64(cz)


@njit(cache=True, nogil=True)
def _find(parent, a):  # pragma: no cover - compiled
    while parent[a] != a:
        parent[a] = parent[parent[a]]
        a = parent[a]
    return a


@njit(cache=True, nogil=True)
def _movable_keys(pts, midx, rows, inv):  # pragma: no cover - compiled
    """The cell keys and indices of the movable points among rows (ascending point indices)."""
    k = 0
    for j in range(rows.shape[0]):
        if midx[rows[j]] >= 0:
            k += 1
    keys = np.empty(k, np.int64)
    mv = np.empty(k, np.int64)
    k = 0
    for j in range(rows.shape[0]):
        i = rows[j]
        if midx[i] >= 0:
            keys[k] = pack(midx[i], cell(pts[i, 0], inv), cell(pts[i, 1], inv), cell(pts[i, 2], inv))
            mv[k] = i
            k += 1
    return keys, mv


@njit(cache=True, nogil=True)
def _bucket_cells(keys):  # pragma: no cover - compiled
    """The distinct keys (in first-seen order), and per key its distinct key's index and the
    count of each distinct key: one pass through an open-addressing table (voxel_hash)."""
    n = keys.shape[0]
    shift = 64
    cap = 1
    while cap < 2 * n:
        cap <<= 1
        shift -= 1
    slot_key = np.full(cap, EMPTY)
    slot_cell = np.empty(cap, np.int64)
    ukeys = np.empty(n, np.int64)
    counts = np.zeros(n, np.int64)
    pc = np.empty(n, np.int64)
    nc = 0
    for j in range(n):
        h = find_slot(slot_key, keys[j], shift)
        if slot_key[h] == EMPTY:
            slot_key[h] = keys[j]
            slot_cell[h] = nc
            ukeys[nc] = keys[j]
            nc += 1
        c = slot_cell[h]
        pc[j] = c
        counts[c] += 1
    return ukeys[:nc], counts[:nc], pc


@njit(cache=True, nogil=True)
def _scatter_cells(ukeys, counts, pc, mv, order):  # pragma: no cover - compiled
    """Counting sort by cell: (sorted keys, point indices) with the cells in the order `order`
    (of the distinct keys) and each cell's points in their order in mv."""
    nc = ukeys.shape[0]
    start = np.empty(nc, np.int64)
    a = 0
    for r in range(nc):
        c = order[r]
        start[c] = a
        a += counts[c]
    sk = np.empty(mv.shape[0], np.int64)
    sp = np.empty(mv.shape[0], np.int64)
    for j in range(mv.shape[0]):
        c = pc[j]
        sk[start[c]] = ukeys[c]
        sp[start[c]] = mv[j]
        start[c] += 1
    return sk, sp


def cell_keys(pts: np.ndarray, midx: np.ndarray, rows: np.ndarray, eps: float) -> tuple[np.ndarray, np.ndarray]:
    """Sorted cell keys (object index, then cells of side eps/2) of the movable points (midx >= 0)
    among rows (ascending point indices: the seen points, the only ones a mask can hold), and the
    point index at each sorted position (ascending within a cell): what a stable argsort of the
    keys gives, the same on every CPU. Thousands of points fall in hundreds of cells, so the
    points are bucketed by cell through a hash table and only the distinct keys are sorted (a
    stable sort of the int64 keys themselves is timsort in numpy: ~150 us on a scan's 5,000
    movable points, against ~40 us for this)."""
    keys, mv = _movable_keys(pts, midx, rows, 2.0 / eps)
    if not keys.shape[0]:
        return keys, mv
    ukeys, counts, pc = _bucket_cells(keys)
    return _scatter_cells(ukeys, counts, pc, mv, np.argsort(ukeys))


def _half_offsets() -> np.ndarray:
    """(dx, dy) in [-2, 2]^2 with (dx, dy) >= (0, 0) lexicographically: with dz in [-2, 2] (and
    only cells after the current one when (dx, dy) = (0, 0)) each neighbour pair comes once."""
    r = range(-2, 3)
    return np.array([(dx, dy) for dx in r for dy in r if (dx, dy) >= (0, 0)], np.int64)


HALF = _half_offsets()


@njit(cache=True, nogil=True)
def lower_bound(a, x):  # pragma: no cover - compiled
    """np.searchsorted(a, x) (side left) for a sorted int64 array: written out, since numba's
    searchsorted costs ~20 ns a call more, and the refinement makes thousands."""
    lo = 0
    hi = a.shape[0]
    while lo < hi:
        mid = (lo + hi) >> 1
        if a[mid] < x:
            lo = mid + 1
        else:
            hi = mid
    return lo


@njit(cache=True, nogil=True)
def cell_near(pts, sp, i, s0, e0, eps2):  # pragma: no cover - compiled
    """Is point i within eps of some point of sorted run [s0, e0)?"""
    for a in range(s0, e0):
        j = sp[a]
        d0 = pts[i, 0] - pts[j, 0]
        d1 = pts[i, 1] - pts[j, 1]
        d2 = pts[i, 2] - pts[j, 2]
        if d0 * d0 + d1 * d1 + d2 * d2 <= eps2:
            return True
    return False


@njit(cache=True, nogil=True)
def cell_runs(sk):  # pragma: no cover - compiled
    """(ckey, cstart): the occupied cells of the sorted keys sk (at least one), each cell's key
    and the start of its run in sk (cstart has one more entry: len(sk))."""
    k = sk.shape[0]
    nc = 1
    for a in range(1, k):
        if sk[a] != sk[a - 1]:
            nc += 1
    ckey = np.empty(nc, np.int64)
    cstart = np.empty(nc + 1, np.int64)
    c = 0
    ckey[0] = sk[0]
    cstart[0] = 0
    for a in range(1, k):
        if sk[a] != sk[a - 1]:
            c += 1
            ckey[c] = sk[a]
            cstart[c] = a
    cstart[nc] = k
    return ckey, cstart


@njit(cache=True, nogil=True)
def join_cells(pts, cells, eps2, half):  # pragma: no cover - compiled
    """Union-find parents of the cells: two cells up to 2 apart (half: _half_offsets) joined when
    a pair of their points is within eps (checked only while they are still apart). Per (dx,
    dy), the first key of the neighbour range is key + a constant offset when every cell index
    stays inside its field (2 <= index < 2^18 - 2): increasing with c, so one pointer per offset
    walks ckey once (a binary search per cell and offset costs its mispredicted branches)."""
    sp, ckey, cstart = cells
    nc = ckey.shape[0]
    parent = np.arange(nc)
    NH = half.shape[0]
    ptr = np.zeros(NH, np.int64)
    for c in range(nc):
        key = ckey[c]
        cz = key & 0x3FFFF
        cy = (key >> 18) & 0x3FFFF
        cx = (key >> 36) & 0x3FFFF
        m = key >> 54
        inner = cx >= 2 and cy >= 2 and cz >= 2 and cx < (1 << 18) - 2 and cy < (1 << 18) - 2
        # For each (dx, dy) the cells cz-2..cz+2 are one contiguous key range: one search, then a
        # scan. Only cells after c in key order (each pair of cells once).
        for h in range(NH):
            lo_key = pack(m, cx + half[h, 0], cy + half[h, 1], cz - 2)
            hi_key = lo_key + 4
            if lo_key <= key:
                d = c + 1
            elif inner:  # lo_key == key + a constant offset
                d = ptr[h]
                while d < nc and ckey[d] < lo_key:
                    d += 1
                ptr[h] = d
            else:
                d = lower_bound(ckey, lo_key)
            while d < nc and ckey[d] <= hi_key:
                rc = _find(parent, c)
                rd = _find(parent, d)
                if rc != rd:
                    for a in range(cstart[c], cstart[c + 1]):
                        if cell_near(pts, sp, sp[a], cstart[d], cstart[d + 1], eps2):
                            parent[rd] = rc
                            break
                d += 1
    return parent


@njit(cache=True, nogil=True)
def suppress(depth, cells, parent, M, limits, out):  # pragma: no cover - compiled
    """Outlier suppression: the points of a component smaller than n_min, or (depth_gap > 0)
    whose mean depth is farther than depth_gap from its object's dominant (largest) component,
    get out = -1. limits: (n_min, depth_gap). Returns (kept per cell, points removed)."""
    sp, ckey, cstart = cells
    n_min, depth_gap = limits
    nc = ckey.shape[0]
    size = np.zeros(nc, np.int64)
    dsum = np.zeros(nc)
    croot = np.empty(nc, np.int64)
    for c in range(nc):
        r = _find(parent, c)
        croot[c] = r
        size[r] += cstart[c + 1] - cstart[c]
        for a in range(cstart[c], cstart[c + 1]):
            dsum[r] += depth[sp[a]]
    dom = np.full(M, -1, np.int64)
    for c in range(nc):
        if croot[c] == c:
            m = ckey[c] >> 54
            if dom[m] < 0 or size[c] > size[dom[m]]:
                dom[m] = c
    ckept = np.zeros(nc, np.bool_)
    removed = 0
    for c in range(nc):
        r = croot[c]
        d = dom[ckey[c] >> 54]
        ok = size[r] >= n_min and size[d] >= n_min
        if ok and depth_gap > 0.0 and r != d:
            ok = abs(dsum[r] / size[r] - dsum[d] / size[d]) <= depth_gap
        ckept[c] = ok
        if not ok:
            for a in range(cstart[c], cstart[c + 1]):
                out[sp[a]] = -1
                removed += 1
    return ckept, removed


@njit(cache=True, nogil=True)
def _kept_boxes(pts, cells, ckept, M, eps):  # pragma: no cover - compiled
    """(M, 6) per mask: the 3-D bounding box (x0, x1, y0, y1, z0, z1) of its kept points grown by
    eps (a cheap exact pre-filter for "within eps of a kept point")."""
    sp, ckey, cstart = cells
    bb = np.empty((M, 6))
    for m in range(M):
        for ax in range(3):
            bb[m, 2 * ax] = np.inf
            bb[m, 2 * ax + 1] = -np.inf
    for c in range(ckey.shape[0]):
        if ckept[c]:
            m = ckey[c] >> 54
            for a in range(cstart[c], cstart[c + 1]):
                i = sp[a]
                for ax in range(3):
                    bb[m, 2 * ax] = min(bb[m, 2 * ax], pts[i, ax] - eps)
                    bb[m, 2 * ax + 1] = max(bb[m, 2 * ax + 1], pts[i, ax] + eps)
    return bb


@njit(cache=True, nogil=True)
def _near_kept(pts, i, m, cells, ckept, at, eps2):  # pragma: no cover - compiled
    """Is point i within eps of a kept point of mask m? at: (cx, cy, cz, inner), point i's cell
    and whether every neighbour cell stays inside its field (the cells cz-2..cz+2 are then one
    key range: one search, then a scan)."""
    sp, ckey, cstart = cells
    cx, cy, cz, inner = at
    nc = ckey.shape[0]
    for dx in range(-2, 3):
        for dy in range(-2, 3):
            if inner:
                lo_key = pack(m, cx + dx, cy + dy, cz - 2)
                d = lower_bound(ckey, lo_key)
                while d < nc and ckey[d] <= lo_key + 4:
                    if ckept[d] and cell_near(pts, sp, i, cstart[d], cstart[d + 1], eps2):
                        return True
                    d += 1
                continue
            for dz in range(-2, 3):
                nk = pack(m, cx + dx, cy + dy, cz + dz)
                d = lower_bound(ckey, nk)
                if d >= nc or ckey[d] != nk or not ckept[d]:
                    continue
                if cell_near(pts, sp, i, cstart[d], cstart[d + 1], eps2):
                    return True
    return False


@njit(cache=True, nogil=True)
def complete(points, cells, ckept, gate, eps, out):  # pragma: no cover - compiled
    """Completion: a seen point no mask labelled joins the highest-cost object m that has a kept
    point within eps of it and whose mask, dilated by a square of half-size dilate_px, holds its
    pixel (out[i] = m). Returns the points added."""
    pts, seen_rows, pix, midx = points
    warped, masks, tables, lens, costs, dilate_px = gate
    # Known defect, kept as the partition behaves: the dilated-mask test of a warped mask reads
    # the flat crop array from the cell runs' starts (cells[2]), not from the crops' own starts
    # (docs/decisions/vpp-completion-crop-offsets.md).
    crops = tables.crops
    mask_test = WarpTables(MaskCrops(crops.crop, cells[2], crops.box), tables.sel, tables.Hinv, tables.rows,
                           tables.box, tables.rays)
    M = masks.shape[0]
    inv = 2.0 / eps
    eps2 = eps * eps
    bb = _kept_boxes(pts, cells, ckept, M, eps)
    added = 0
    for j in range(seen_rows.shape[0]):
        i = seen_rows[j]
        if midx[i] >= 0:
            continue
        best = -1
        bc = -1.0
        cx = cell(pts[i, 0], inv)
        cy = cell(pts[i, 1], inv)
        cz = cell(pts[i, 2], inv)
        inner = cx >= 2 and cy >= 2 and cz >= 2 and cx < (1 << 18) - 2 and cy < (1 << 18) - 2 and cz < (1 << 18) - 2
        for m in range(M):
            if costs[m] <= bc or pts[i, 0] < bb[m, 0] or pts[i, 0] > bb[m, 1] or pts[i, 1] < bb[m, 2] \
                    or pts[i, 1] > bb[m, 3] or pts[i, 2] < bb[m, 4] or pts[i, 2] > bb[m, 5]:
                continue
            if _near_kept(pts, i, m, cells, ckept, (cx, cy, cz, inner), eps2) and (
                    near_warp(mask_test, lens, m, pix[i, 0], pix[i, 1], dilate_px) if warped
                    else near_mask(masks, m, pix[i, 0], pix[i, 1], dilate_px)):
                best = m
                bc = costs[m]
        if best >= 0:
            out[i] = best
            added += 1
    return added


@njit(cache=True, nogil=True)
def refine(points, depth, keys, gate, limits, half):  # pragma: no cover - compiled
    """The cluster refinement (step 4): components (join_cells), suppression, completion.
    keys: (sorted cell keys, their point indices) of the movable points (cell_keys, at least
    one); depth: each point's camera depth. Returns (new midx, n removed, n added)."""
    pts, _, _, midx = points
    eps, n_min, depth_gap, do_complete = limits
    sk, sp = keys
    out = midx.copy()
    ckey, cstart = cell_runs(sk)
    cells = (sp, ckey, cstart)
    parent = join_cells(pts, cells, eps * eps, half)
    ckept, removed = suppress(depth, cells, parent, gate[1].shape[0], (n_min, depth_gap), out)
    if not do_complete:
        return out, removed, 0
    return out, removed, complete(points, cells, ckept, gate, eps, out)


__all__ = ["HALF", "cell", "cell_keys", "cell_near", "cell_runs", "complete", "join_cells", "lower_bound", "pack",
           "refine", "suppress"]
