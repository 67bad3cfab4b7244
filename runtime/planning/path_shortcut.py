"""Post-processing of the searched cell path: any-angle shortcutting, densifying, smoothing.

Any-angle shortcutting (`ReferencePathConfig.shortcut`): the 8-connected cell path turns in
45-degree steps, which the MPC would follow as an S-weave. After the search, a straight segment
replaces a run of cells when it crosses no lethal cell (nor a touchable object's cell the run
avoided) and costs no more than the run (Theta*'s line-of-sight idea, as a post-pass); the result
is resampled at the grid's resolution (`densify`) so that the blocked-ahead check and the
smoothing still read dense points. The smoothing (a moving average) is kept only where it does
not bring the path nearer to a point than allowed.

The numba kernels take the grid as one tuple `(passable, cost, resolution_m, touch)`:
passable (n, n) bool, cost (n, n) >= 1, touch (n, n) bool (a touchable object's cells).
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit
from scipy.spatial import cKDTree


@njit(cache=True, nogil=True)
def _segment_cost(a, b, grid, may_touch):  # pragma: no cover - compiled
    """The cost of the straight segment between two cell centres a = (i, j), b = (i, j) (cells,
    as the search's edges: metres x cell cost), sampled every quarter cell; inf when it crosses an
    impassable cell, or a touchable object's cell when may_touch is False."""
    ai, aj = a
    bi, bj = b
    passable, cost, res, touch = grid
    di, dj = bi - ai, bj - aj
    length = math.sqrt(di * di + dj * dj)
    m = max(1, int(math.ceil(length * 4.0)))
    step = length * res / m
    total = 0.0
    for k in range(m + 1):
        t = k / m
        i = int(math.floor(ai + di * t + 0.5))
        j = int(math.floor(aj + dj * t + 0.5))
        if not passable[i, j] or (touch[i, j] and not may_touch):
            return math.inf
        w = 0.5 if k == 0 or k == m else 1.0  # trapezoid: the ends count half
        total += w * step * cost[i, j]
    return total


@njit(cache=True, nogil=True)
def shortcut(ci, cj, grid):  # pragma: no cover - compiled
    """Indices of the cell path (ci, cj) kept by greedy line-of-sight shortcutting: from each kept
    cell, the farthest next cell such that every cell up to it is reachable by a straight
    segment no more costly than the path's run to it (the search's edge costs: step x mean cell
    cost). A segment enters a touchable object's cells (`touch`) only where the run it replaces
    does: a shortcut never turns a detour into a push (the push-or-detour rule reads the path)."""
    _, cost, res, touch = grid
    n = ci.shape[0]
    cum = np.zeros(n)
    touched = np.zeros(n, np.int64)  # touchable cells on the path up to each index
    touched[0] = int(touch[ci[0], cj[0]])
    for k in range(1, n):
        step = math.sqrt((ci[k] - ci[k - 1]) ** 2 + (cj[k] - cj[k - 1]) ** 2) * res
        cum[k] = cum[k - 1] + step * 0.5 * (cost[ci[k - 1], cj[k - 1]] + cost[ci[k], cj[k]])
        touched[k] = touched[k - 1] + int(touch[ci[k], cj[k]])
    keep = np.empty(n, np.int64)
    keep[0] = 0
    nk = 1
    i = 0
    while i < n - 1:
        j = i + 1
        while j + 1 < n:
            c = _segment_cost((ci[i], cj[i]), (ci[j + 1], cj[j + 1]), grid, touched[j + 1] > touched[i])
            if c > cum[j + 1] - cum[i] + 1e-9:
                break
            j += 1
        keep[nk] = j
        nk += 1
        i = j
    return keep[:nk]


def compile_shortcut() -> None:
    """Compile the kernels (or load them from numba's cache) now, not in the first search."""
    free = np.ones((4, 4), np.bool_)
    shortcut(np.arange(4, dtype=np.int64), np.zeros(4, np.int64), (free, np.ones((4, 4)), 0.05, ~free))


def densify(path: np.ndarray, spacing_m: float) -> np.ndarray:
    """The polyline with points inserted so that no two consecutive ones are farther apart than
    spacing_m (the blocked-ahead check and the smoothing read the path's points)."""
    seg = np.diff(path, axis=0)
    count = np.maximum(1, np.ceil(np.hypot(seg[:, 0], seg[:, 1]) / spacing_m).astype(np.int64))
    t = np.concatenate([np.arange(c) / c for c in count])
    base = np.repeat(np.arange(len(seg)), count)
    return np.concatenate([path[base] + t[:, None] * seg[base], path[-1:]])


def smooth_path(path: np.ndarray, points_world: np.ndarray, window: int, inflation_radius_m: float) -> np.ndarray:
    """The path's moving average over `window` points (ends kept), except where it would come
    nearer to points_world than the path itself and than the inflation radius."""
    w = window
    if w <= 1 or path.shape[0] <= w:
        return path
    pad = w // 2
    padded = np.concatenate([np.repeat(path[:1], pad, 0), path, np.repeat(path[-1:], pad, 0)])
    kernel = np.ones(w) / w
    smooth = np.stack([np.convolve(padded[:, k], kernel, mode="valid") for k in range(2)], axis=1)
    smooth[0], smooth[-1] = path[0], path[-1]
    if points_world.shape[0] == 0:
        return smooth
    tree = cKDTree(points_world)
    d_raw, _ = tree.query(path)
    d_s, _ = tree.query(smooth)
    # Keep the smoothing only where it does not bring the path nearer than allowed.
    bad = d_s < np.minimum(d_raw, inflation_radius_m)
    smooth[bad] = path[bad]
    return smooth
