"""The tracker's geometry of point sets, compiled where the tick calls it: bounding boxes
(runtime/common/spatial_grid.py's `bounds`), the size of a set in an object's own frame, and voxel thinning (the first point of each voxel,
through the VPP's voxel hash: runtime/vpp/voxel_hash.py)."""
from __future__ import annotations

import math

import numpy as np
from numba import njit

from runtime.common.spatial_grid import bounds
from runtime.vpp.voxel_hash import EMPTY, find_slot


def extent(points: np.ndarray, yaw: float = 0.0) -> float:
    """The points' size (m): extent_nb."""
    if len(points) < 2:
        return 0.0
    return float(extent_nb(np.ascontiguousarray(points, dtype=np.float64), float(yaw)))


def footprint(points: np.ndarray, yaw: float = 0.0) -> float:
    """The diagonal (m) of the points' bounding box in the plane, in the object's frame (the
    odom frame turned by yaw, as extent_nb): footprint_nb."""
    if len(points) < 2:
        return 0.0
    return float(math.hypot(*footprint_nb(np.ascontiguousarray(points, dtype=np.float64), float(yaw))))


@njit(cache=True, nogil=True)
def footprint_nb(points, yaw):  # pragma: no cover - compiled
    """footprint's two extents (x, y), compiled (numpy's six passes and temporaries cost ~12 us
    a call, twice per object and scan): the same products and sums per point, so the same
    bounds; the caller takes Python's math.hypot of them (numba's differs in the last bit)."""
    c = math.cos(yaw)
    s = math.sin(yaw)
    x0 = x1 = c * points[0, 0] + s * points[0, 1]
    y0 = y1 = -s * points[0, 0] + c * points[0, 1]
    for i in range(1, points.shape[0]):
        x = c * points[i, 0] + s * points[i, 1]
        y = -s * points[i, 0] + c * points[i, 1]
        x0 = min(x0, x)
        x1 = max(x1, x)
        y0 = min(y0, y)
        y1 = max(y1, y)
    return x1 - x0, y1 - y0


@njit(cache=True, nogil=True)
def centre_nb(points, rows):  # pragma: no cover - compiled
    """(x, y) mean of points[rows] (rows None: all): the running sum numpy's mean over axis 0
    makes, divided by the count, so the same bits (held by a test)."""
    n = points.shape[0] if rows is None else rows.shape[0]
    sx = 0.0
    sy = 0.0
    for j in range(n):
        i = j if rows is None else rows[j]
        sx += points[i, 0]
        sy += points[i, 1]
    return sx / n, sy / n


@njit(cache=True, nogil=True)
def stacked_bounds(points, off):  # pragma: no cover - compiled
    """(lo (K, 3), hi (K, 3)): the bounding box of each of K point sets stacked in points (set k:
    rows off[k]:off[k + 1], none empty), in one call."""
    K = off.shape[0] - 1
    lo = np.empty((K, 3))
    hi = np.empty((K, 3))
    for k in range(K):
        for a in range(3):
            lo[k, a] = points[off[k], a]
            hi[k, a] = points[off[k], a]
        for i in range(off[k] + 1, off[k + 1]):
            for a in range(3):
                x = points[i, a]
                if x < lo[k, a]:
                    lo[k, a] = x
                if x > hi[k, a]:
                    hi[k, a] = x
    return lo, hi


@njit(cache=True, nogil=True)
def each_inside_one(lo, hi, outer_lo, outer_hi):  # pragma: no cover - compiled
    """Whether every box (lo[k], hi[k]) lies inside some box of (outer_lo, outer_hi)."""
    for k in range(lo.shape[0]):
        inside = False
        for j in range(outer_lo.shape[0]):
            if lo[k, 0] >= outer_lo[j, 0] and lo[k, 1] >= outer_lo[j, 1] and lo[k, 2] >= outer_lo[j, 2] and \
                    hi[k, 0] <= outer_hi[j, 0] and hi[k, 1] <= outer_hi[j, 1] and hi[k, 2] <= outer_hi[j, 2]:
                inside = True
                break
        if not inside:
            return False
    return True


@njit(cache=True, nogil=True)
def view_against_template(points, rows, template, yaw):  # pragma: no cover - compiled
    """The tracker's plausibility test's figures, in one call: the centres (x, y) of a mask's view
    points[rows] and of the template (centre_nb), and the footprint extents (footprint_nb; none
    below two points) of each, in the object's frame turned by yaw. float64 points and template
    (the tracker's): numpy would average float32 ones in float32."""
    vx, vy = centre_nb(points, rows)
    tx, ty = centre_nb(template, None)
    fv = (0.0, 0.0)
    if rows.shape[0] >= 2:
        fv = footprint_nb(points[rows], yaw)
    ft = (0.0, 0.0)
    if template.shape[0] >= 2:
        ft = footprint_nb(template, yaw)
    return vx, vy, tx, ty, fv, ft


def thin(points: np.ndarray, voxel_m: float, max_points: int = 0) -> np.ndarray:
    """One point per voxel (the first), in a stable order; then at most max_points (0: no cap) by
    an even stride (thin_first: compiled, ~20 us for 1000 points)."""
    if len(points) == 0:
        return points
    return thin_nb(np.ascontiguousarray(points, dtype=np.float64), float(voxel_m), int(max_points))


@njit(cache=True, nogil=True)
def thin_nb(points, voxel, max_points):  # pragma: no cover - compiled
    """thin, compiled: the first point of each voxel in their order, then an even stride of
    max_points (0: all) of them (numpy's linspace, truncated)."""
    out = points[thin_first(points, voxel)]
    n = out.shape[0]
    if max_points > 0 and n > max_points:
        pick = np.linspace(0, n - 1, max_points).astype(np.int64)
        out = out[pick]
    return out


@njit(cache=True, nogil=True)
def extent_nb(points, yaw):  # pragma: no cover - compiled
    """The points' size (m): the diagonal of their bounding box in the object's frame, the odom
    frame turned by `yaw` (what the object turned since the tracker first saw it: the sum of
    its registrations' yaws). In the odom frame the box of a pushed box that turned would grow
    (45 degrees: a 0.4 m cube's diagonal from 0.69 to 0.90 m) and the limits on a template's
    growth would refuse the object's own newly seen faces; in its own frame it stays the box's."""
    n = points.shape[0]
    if n < 2:
        return 0.0
    c = math.cos(yaw)
    s = math.sin(yaw)
    lo = np.empty(3)
    hi = np.empty(3)
    for i in range(n):
        x = c * points[i, 0] + s * points[i, 1]  # R(yaw)^T p: the object's frame
        y = -s * points[i, 0] + c * points[i, 1]
        z = points[i, 2]
        if i == 0:
            lo[0] = hi[0] = x
            lo[1] = hi[1] = y
            lo[2] = hi[2] = z
            continue
        lo[0] = min(lo[0], x)
        hi[0] = max(hi[0], x)
        lo[1] = min(lo[1], y)
        hi[1] = max(hi[1], y)
        lo[2] = min(lo[2], z)
        hi[2] = max(hi[2], z)
    return math.sqrt((hi[0] - lo[0]) ** 2 + (hi[1] - lo[1]) ** 2 + (hi[2] - lo[2]) ** 2)


@njit(cache=True, nogil=True)
def thin_first(points, voxel):  # pragma: no cover - compiled
    """Indices (ascending) of the first point in each voxel: one pass with the voxel hash
    (runtime/vpp/voxel_hash.py) of the voxel keys (three 21-bit cell indices packed in an int64, from the points'
    lowest cell: 63 km at 3 cm), so the order of the points is kept without a sort."""
    n = points.shape[0]
    kk = np.empty((n, 3), np.int64)
    kmin = np.empty(3, np.int64)
    for i in range(n):
        for a in range(3):
            k = np.int64(math.floor(points[i, a] / voxel))
            kk[i, a] = k
            if i == 0 or k < kmin[a]:
                kmin[a] = k
    size = 16
    bits = 4
    while size < 2 * n:
        size *= 2
        bits += 1
    table = np.full(size, EMPTY, np.int64)
    out = np.empty(n, np.int64)
    u = 0
    for i in range(n):
        key = ((kk[i, 0] - kmin[0]) << 42) | ((kk[i, 1] - kmin[1]) << 21) | (kk[i, 2] - kmin[2])
        h = find_slot(table, key, 64 - bits)
        if table[h] == EMPTY:  # the voxel's first point
            table[h] = key
            out[u] = i
            u += 1
    return out[:u]



__all__ = ["bounds", "centre_nb", "each_inside_one", "extent", "extent_nb", "footprint", "stacked_bounds", "thin",
           "thin_first", "thin_nb", "view_against_template"]
