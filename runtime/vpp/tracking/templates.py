"""The templates' growth, compiled: a mask's view merged into an object's template, and a
template grown by the fixed points it took (runtime/vpp/tracking/__init__.py: confirmation and
spread), for every object in one call.

Arguments, grouped: templates = (points concatenated (n, 3), each object's row offsets (K + 1,),
each object's yaw (K,)); views = (point indices concatenated, offsets); taken = (point indices
concatenated, offsets); limits as named in each function.
"""
from __future__ import annotations

import numpy as np
from numba import njit

from runtime.common.spatial_grid import near_any
from runtime.vpp.tracking.geometry import extent_nb, thin_nb


@njit(cache=True, nogil=True)
def merge_view(new, old, voxel, max_points, max_growth, yaw):  # pragma: no cover - compiled
    """A mask's thinned view `new` merged into the template `old` (ObjectTracker._confirm):
    (template, outcome) with outcome 0 merged (the view plus the template's points it does not
    cover, while that union spans at most max_growth more than the larger of the two), 1 the
    template kept (a sliver that disagrees), 2 the view taken (it disagrees and is substantial)."""
    near = near_any(old, new, 2.0 * voxel)
    n_extra = 0
    for i in range(near.shape[0]):
        if not near[i]:
            n_extra += 1
    union = np.empty((new.shape[0] + n_extra, 3))
    union[:new.shape[0]] = new
    j = new.shape[0]
    for i in range(old.shape[0]):
        if not near[i]:
            union[j] = old[i]
            j += 1
    if extent_nb(union, yaw) <= max(extent_nb(new, yaw), extent_nb(old, yaw)) + max_growth:
        return thin_nb(union, voxel, max_points), 0
    if new.shape[0] < old.shape[0] // 2:
        return old, 1
    return new, 2


@njit(cache=True, nogil=True)
def _concatenate(outs, K):  # pragma: no cover - compiled
    """(the K point sets of outs concatenated, their row offsets (K + 1,))."""
    noff = np.zeros(K + 1, np.int64)
    for k in range(K):
        noff[k + 1] = noff[k] + outs[k].shape[0]
    merged = np.empty((noff[K], 3))
    for k in range(K):
        merged[noff[k]:noff[k + 1]] = outs[k]
    return merged, noff


@njit(cache=True, nogil=True)
def confirm_all(p, views, templates, limits):  # pragma: no cover - compiled
    """ObjectTracker._confirm's image of every confirming object that has a template, in one
    call: object k's view is p[idx[starts[k]:starts[k + 1]]] (views = (idx, starts)), its
    template and yaw those of `templates`; limits = (voxel, max_points, max_growth). Returns
    (templates concatenated, offsets (K + 1,), outcome (K,) as merge_view's, the view's extent (K,))."""
    idx, starts = views
    old, ooff, yaws = templates
    voxel, max_points, max_growth = limits
    K = starts.shape[0] - 1
    outs = []
    outcome = np.empty(K, np.int64)
    extent = np.empty(K)
    for k in range(K):
        pts = np.empty((starts[k + 1] - starts[k], 3))
        for j in range(pts.shape[0]):
            i = idx[starts[k] + j]
            pts[j, 0] = p[i, 0]
            pts[j, 1] = p[i, 1]
            pts[j, 2] = p[i, 2]
        new = thin_nb(pts, voxel, max_points)
        tpl, outcome[k] = merge_view(new, old[ooff[k]:ooff[k + 1]], voxel, max_points, max_growth, yaws[k])
        extent[k] = extent_nb(pts, yaws[k])
        outs.append(tpl)
    merged, noff = _concatenate(outs, K)
    return merged, noff, outcome, extent


@njit(cache=True, nogil=True)
def spread_all(p, taken, templates, view_extent, limits):  # pragma: no cover - compiled
    """ObjectTracker._label_all's growth of every object's template by the points it took, in
    one call: where template + taken spans at most view_extent[k] + max_spread, the template
    becomes that union thinned (thin_nb), else it stays. limits = (max_spread, voxel,
    max_points). Returns (templates concatenated, offsets, grown (K,))."""
    taken_idx, toff = taken
    tpl, off, yaws = templates
    max_spread, voxel, max_points = limits
    K = off.shape[0] - 1
    outs = []
    grown = np.zeros(K, np.bool_)
    for k in range(K):
        a, b = off[k], off[k + 1]
        nt = toff[k + 1] - toff[k]
        res = tpl[a:b]
        if nt > 0:
            union = np.empty((b - a + nt, 3))
            union[:b - a] = tpl[a:b]
            for j in range(nt):
                i = taken_idx[toff[k] + j]
                union[b - a + j, 0] = p[i, 0]
                union[b - a + j, 1] = p[i, 1]
                union[b - a + j, 2] = p[i, 2]
            if extent_nb(union, yaws[k]) <= view_extent[k] + max_spread:
                res = thin_nb(union, voxel, max_points)
                grown[k] = True
        outs.append(res)
    merged, noff = _concatenate(outs, K)
    return merged, noff, grown


__all__ = ["confirm_all", "merge_view", "spread_all"]
