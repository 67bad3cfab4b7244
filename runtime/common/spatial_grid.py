"""A dense uniform grid over 3-D points for "nearest within r" queries, compiled.

Why hand-written nearest neighbours: scipy's cKDTree is the library for this, but a tree built
and queried per object per scan costs ~0.1 ms of Python and allocation each time, and the VPP
stage tracks up to 8 objects inside a 3 ms budget. The queries are all "nearest within r" with r
fixed per query set, which a dense grid of cell >= r answers exactly from the 27 cells around the
query (a point within r of q lies at most one cell away on each axis), in one compiled pass with
no Python per object step. Used by the object tracker (runtime/vpp/tracking/: registration and
labelling) and the odometry's mover exclusion (runtime/odometry/stage.py).

The one index for "nearest within r" / "any within r" over a bounded set of points built per
call. The VPP's other spatial structures answer other questions: the partition's cluster cells
(runtime/vpp/partition/clustering.py: eps-connectivity of a whole scan's movable points, per
object) and the voxel hash (runtime/vpp/voxel_hash.py: the label memory kept between scans, the
template thinning).
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit

MAX_GRID_CELLS = 1 << 20


@njit(cache=True, nogil=True)
def bounds(points):  # pragma: no cover - compiled
    """(min (3,), max (3,)) of (N >= 1, 3) points (numpy's min and max: ~10 us each on small arrays)."""
    lo = points[0].copy()
    hi = points[0].copy()
    for i in range(1, points.shape[0]):
        for a in range(3):
            x = points[i, a]
            if x < lo[a]:
                lo[a] = x
            if x > hi[a]:
                hi[a] = x
    return lo, hi


@njit(cache=True, nogil=True)
def grid(pts, r, split):  # pragma: no cover - compiled
    """A dense grid over pts' bounding box for queries "nearest within r": cells of r / split
    (split 3 for raw scan points: a scanned face holds tens of points in a cell of r, and the
    pruning in `nearest` skips most cells of r / 3; split 1 for thinned templates), grown while
    the grid would have more than MAX_GRID_CELLS cells. Returns the grid as one tuple (lo, cell,
    reach, dims, start, order), the form `nearest` and `any_within` take: the points of cell c
    are order[start[c]:start[c + 1]]; a point within r of a query lies within `reach` cells of
    the query's cell on every axis."""
    n = pts.shape[0]
    lo, hi = bounds(pts)
    lo, hi = lo.astype(np.float64), hi.astype(np.float64)  # float64 whatever the points' type
    cell = r / split
    dims = np.empty(3, np.int64)
    while True:
        for a in range(3):
            dims[a] = int((hi[a] - lo[a]) / cell) + 1
        if dims[0] * dims[1] * dims[2] <= MAX_GRID_CELLS:
            break
        cell *= 2.0
    reach = int(math.ceil(r / cell))
    ncell = dims[0] * dims[1] * dims[2]
    cid = np.empty(n, np.int64)
    start = np.zeros(ncell + 1, np.int64)
    for i in range(n):
        c = 0
        for a in range(3):
            k = int((pts[i, a] - lo[a]) / cell)
            k = min(max(k, 0), dims[a] - 1)
            c = c * dims[a] + k
        cid[i] = c
        start[c + 1] += 1
    for c in range(ncell):
        start[c + 1] += start[c]
    fill = start[:-1].copy()
    order = np.empty(n, np.int64)
    for i in range(n):
        order[fill[cid[i]]] = i
        fill[cid[i]] += 1
    return lo, cell, reach, dims, start, order


@njit(inline="always")
def _home_cell(lo, cell, dims, x, y, z):  # pragma: no cover - compiled
    """The query's cell (clamped to the grid: a query outside is answered from the border cells)."""
    q0 = min(max(int(math.floor((x - lo[0]) / cell)), 0), dims[0] - 1)
    q1 = min(max(int(math.floor((y - lo[1]) / cell)), 0), dims[1] - 1)
    q2 = min(max(int(math.floor((z - lo[2]) / cell)), 0), dims[2] - 1)
    return q0, q1, q2


@njit(inline="always")
def _cell_id(dims, a, b, c):  # pragma: no cover - compiled
    return (a * dims[1] + b) * dims[2] + c


@njit(inline="always")
def _d2(pts, j, x, y, z):  # pragma: no cover - compiled
    """Squared distance from point j to (x, y, z)."""
    dx = pts[j, 0] - x
    dy = pts[j, 1] - y
    dz = pts[j, 2] - z
    return dx * dx + dy * dy + dz * dz


@njit(cache=True, nogil=True)
def gap2(x, lo, cell, k):  # pragma: no cover - compiled
    """Squared distance along one axis from x to cell k's extent."""
    a = lo + k * cell
    if x < a:
        return (a - x) * (a - x)
    b = a + cell
    if x > b:
        return (x - b) * (x - b)
    return 0.0


@njit(cache=True, nogil=True)
def near_any(query, ref, r):  # pragma: no cover - compiled
    """(len(query),) bool: a ref point lies closer than r."""
    out = np.zeros(query.shape[0], np.bool_)
    if ref.shape[0] == 0:
        return out
    lo, cell, reach, dims, start, order = grid(ref, r, 1)
    r2 = r * r
    for i in range(query.shape[0]):
        x = query[i, 0]
        y = query[i, 1]
        z = query[i, 2]
        q0, q1, q2 = _home_cell(lo, cell, dims, x, y, z)
        hit = False
        for a in range(max(q0 - reach, 0), min(q0 + reach + 1, dims[0])):
            for b in range(max(q1 - reach, 0), min(q1 + reach + 1, dims[1])):
                for c in range(max(q2 - reach, 0), min(q2 + reach + 1, dims[2])):
                    cc = _cell_id(dims, a, b, c)
                    for s in range(start[cc], start[cc + 1]):
                        j = order[s]
                        if _d2(ref, j, x, y, z) < r2:
                            hit = True
                            break
                    if hit:
                        break
                if hit:
                    break
            if hit:
                break
        out[i] = hit
    return out


@njit(inline="always")
def _scan_cell(pts, cells, cc, q, found, first):  # pragma: no cover - compiled
    """The points of cell cc (cells: the grid's (start, order)) nearer to q than the best so far
    (found: (index, squared distance)); with `first`, the first such point."""
    start, order = cells
    best, bd = found
    x, y, z = q
    for s in range(start[cc], start[cc + 1]):
        j = order[s]
        d = _d2(pts, j, x, y, z)
        if d < bd:
            bd = d
            best = j
            if first:
                return best, bd
    return best, bd


@njit(inline="always")
def _search(pts, g, x, y, z, r2, first):  # pragma: no cover - compiled
    """nearest's search; with `first` (a constant where it is inlined: the branch compiles away)
    it returns at the first point below r2, before which its pruning bound is r2 itself, so that
    any_within visits the cells nearest would until the first hit."""
    lo, cell, reach, dims, start, order = g
    q0, q1, q2 = _home_cell(lo, cell, dims, x, y, z)
    cells, q = (start, order), (x, y, z)
    best, bd = _scan_cell(pts, cells, _cell_id(dims, q0, q1, q2), q, (-1, r2), first)
    if first and best >= 0:
        return best, bd
    for a in range(max(q0 - reach, 0), min(q0 + reach + 1, dims[0])):
        ga = gap2(x, lo[0], cell, a)
        if ga >= bd:
            continue
        for b in range(max(q1 - reach, 0), min(q1 + reach + 1, dims[1])):
            gb = ga + gap2(y, lo[1], cell, b)
            if gb >= bd:
                continue
            for c in range(max(q2 - reach, 0), min(q2 + reach + 1, dims[2])):
                if a == q0 and b == q1 and c == q2:
                    continue
                if gb + gap2(z, lo[2], cell, c) >= bd:
                    continue
                best, bd = _scan_cell(pts, cells, _cell_id(dims, a, b, c), q, (best, bd), first)
                if first and best >= 0:
                    return best, bd
    if best < 0:
        return -1, np.inf
    return best, bd


@njit(cache=True, nogil=True)
def nearest(pts, g, x, y, z, r2):  # pragma: no cover - compiled
    """(index, squared distance) of the grid's point nearest to (x, y, z) at a squared distance
    below r2; (-1, inf) when there is none (g: the grid of pts, as `grid` returns it). The query's own cell first, then the cells within
    reach whose box is nearer than the best so far (exact: a cell is skipped only when none of
    its points can be nearer). A query outside the grid is clamped to its border cells: a
    point within r is still within reach of them."""
    return _search(pts, g, x, y, z, r2, False)


@njit(cache=True, nogil=True)
def any_within(pts, g, x, y, z, r2):  # pragma: no cover - compiled
    """Whether a grid point lies at a squared distance below r2 from (x, y, z) (g: the grid of
    pts): nearest's search stopping at the first point found (the query's own cell first: on a
    template's surface it mostly holds one, so a pushed box's points each stop there)."""
    return _search(pts, g, x, y, z, r2, True)[0] >= 0


@njit(cache=True, nogil=True)
def near_indices(points, ref, r, planar):  # pragma: no cover - compiled
    """Indices (ascending) of the points (N, 3, any float) closer than r to some ref point (M, 3
    float64; planar: in x and y only, ref's z zero): near_any over the points in ref's box grown
    by r, the box test and the float64 copy done in the same pass (numpy's comparisons of the
    points against the box and its copy of those inside made two 20k-point temporaries a scan).
    A ref with a value that is not finite gives none (its box would be NaN: no point inside)."""
    n_ref = ref.shape[0]
    if n_ref == 0:
        return np.zeros(0, np.int64)
    for j in range(n_ref):
        for a in range(3):
            if not math.isfinite(ref[j, a]):
                return np.zeros(0, np.int64)
    k = 2 if planar else 3
    lo, hi = bounds(ref)
    for a in range(3):
        lo[a] -= r
        hi[a] += r
    inb = np.empty(points.shape[0], np.int64)
    m = 0
    for i in range(points.shape[0]):
        inside = True
        for a in range(k):
            v = np.float64(points[i, a])
            if not (v >= lo[a] and v <= hi[a]):
                inside = False
        if inside:
            inb[m] = i
            m += 1
    if m == 0:
        return np.zeros(0, np.int64)
    q = np.empty((m, 3))
    for s in range(m):
        i = inb[s]
        q[s, 0] = points[i, 0]
        q[s, 1] = points[i, 1]
        q[s, 2] = 0.0 if planar else points[i, 2]
    near = near_any(q, ref, r)
    out = np.empty(m, np.int64)
    u = 0
    for s in range(m):
        if near[s]:
            out[u] = inb[s]
            u += 1
    return out[:u]
