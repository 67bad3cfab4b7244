"""Labelling, compiled: the FIXED points of a scan near a tracked template (or seen behind it
along the lidar ray) become the object's (runtime/vpp/tracking/__init__.py), every object in
one call.

Arguments, grouped: scan = (points (N, 3) odom frame, label, object id, cost: labelled in place,
`near`: the indices of the points in some object's box); templates = (points concatenated,
each object's row offsets); objects = (ids, costs).
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit

from runtime.common.spatial_grid import any_within, grid
from runtime.vpp.partition.labels import FIXED, MOVABLE
from runtime.vpp.tracking.geometry import bounds


@njit(cache=True, nogil=True)
def take_all(scan, templates, objects, r, origin, behind):  # pragma: no cover - compiled
    """ObjectTracker._label_all's take for every object in order (an object takes only the FIXED
    points left by those before it), labelling the scan in place (objects = (ids, costs)):
    (taken point indices concatenated, offsets (K + 1,)). behind > 0: also the points seen
    behind a template (take_near)."""
    p, label, oid, cost, near = scan
    tpl, off = templates
    ids, costs = objects
    K = ids.shape[0]
    out = np.empty(near.shape[0], np.int64)
    toff = np.zeros(K + 1, np.int64)
    n = 0
    for k in range(K):
        take = take_near(p, label, near, tpl[off[k]:off[k + 1]], r, origin, behind)
        for i in take:
            label[i] = MOVABLE
            oid[i] = ids[k]
            cost[i] = costs[k]
            out[n] = i
            n += 1
        toff[k + 1] = n
    return out[:n], toff


@njit(cache=True, nogil=True)
def take_near(p, label, near, tpl, r, origin, behind):  # pragma: no cover - compiled
    """Indices of the FIXED points of p (among `near`) closer than r to a template point, or (with
    behind > 0) whose ray from the lidar at `origin` passes closer than r to one on its last
    `behind` metres: seen behind the object's surface (ObjectTracker._label_all)."""
    lo, hi = bounds(tpl)
    g = grid(tpl, r, 1)
    out = np.empty(near.shape[0], np.int64)
    n = 0
    r2 = r * r
    m = int(math.ceil(behind / (0.5 * r))) if behind > 0.0 else 0  # ray samples, r/2 apart
    rb = r + behind
    for s in range(near.shape[0]):
        i = near[s]
        if label[i] != FIXED:
            continue
        x = p[i, 0]
        y = p[i, 1]
        z = p[i, 2]
        if x < lo[0] - rb or x > hi[0] + rb or y < lo[1] - rb or y > hi[1] + rb or z < lo[2] - rb or z > hi[2] + rb:
            continue
        if any_within(tpl, g, x, y, z, r2):
            out[n] = i
            n += 1
            continue
        if m == 0:
            continue
        ux, uy, uz = x - origin[0], y - origin[1], z - origin[2]
        d = math.sqrt(ux * ux + uy * uy + uz * uz)
        if d <= behind:
            continue
        ux, uy, uz = ux / d, uy / d, uz / d
        for k in range(1, m + 1):
            t = min(k * 0.5 * r, behind)
            if any_within(tpl, g, x - t * ux, y - t * uy, z - t * uz, r2):
                out[n] = i
                n += 1
                break
    return out[:n]


__all__ = ["take_all", "take_near"]
