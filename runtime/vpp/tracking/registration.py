"""Registration, compiled: planar point-to-point ICP of each object's template onto the scan
(runtime/vpp/tracking/__init__.py: tracking), all objects in one call.

Arguments, grouped: scan = (points (N, 3) odom frame, label, object id, cost, `near`: the
indices of the points in some object's box, scan_select.in_boxes); templates = (points
concatenated, each object's row offsets); fit = (search margin, correspondence radius,
iterations, min pairs, max points).
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit

from runtime.common.spatial_grid import grid, nearest
from runtime.vpp.tracking.geometry import bounds
from runtime.vpp.tracking.scan_select import box_candidates


@njit(cache=True, nogil=True)
def _candidates(scan, object_id, tpl, margin):  # pragma: no cover - compiled
    """The points of the scan (among `near`) in tpl's box grown by margin that are FIXED or
    object_id's, gathered ((n, 3))."""
    p, label, oid, _, near = scan
    lo, hi = bounds(tpl)
    for a in range(3):
        lo[a] -= margin
        hi[a] += margin
    cand = box_candidates(p, label, oid, object_id, lo, hi, near)
    pts = np.empty((cand.shape[0], 3))
    for i in range(cand.shape[0]):
        for a in range(3):
            pts[i, a] = p[cand[i], a]
    return pts


@njit(cache=True, nogil=True)
def _step(moved, pts, g, r2, stride, match, min_pairs):  # pragma: no cover - compiled
    """One ICP iteration: every stride-th template point matched to its nearest candidate
    within r (g: the candidates' grid), the planar rigid motion that best aligns the pairs
    applied to the whole template (moved, in place). Returns (ok, cos, sin, tx, ty) of the step;
    not ok (moved untouched) with fewer than min_pairs pairs."""
    m = moved.shape[0]
    n = 0
    sx = sy = dx = dy = 0.0
    for i in range(0, m, stride):
        j, _d = nearest(pts, g, moved[i, 0], moved[i, 1], moved[i, 2], r2)
        match[i] = j
        if j >= 0:
            n += 1
            sx += moved[i, 0]
            sy += moved[i, 1]
            dx += pts[j, 0]
            dy += pts[j, 1]
    if n < min_pairs:
        return False, 1.0, 0.0, 0.0, 0.0
    sx /= n
    sy /= n
    dx /= n
    dy /= n
    h00 = h01 = h10 = h11 = 0.0
    for i in range(0, m, stride):
        j = match[i]
        if j >= 0:
            ax = moved[i, 0] - sx
            ay = moved[i, 1] - sy
            bx = pts[j, 0] - dx
            by = pts[j, 1] - dy
            h00 += ax * bx
            h01 += ax * by
            h10 += ay * bx
            h11 += ay * by
    yaw = math.atan2(h01 - h10, h00 + h11)
    c = math.cos(yaw)
    s = math.sin(yaw)
    ux = dx - (c * sx - s * sy)
    uy = dy - (s * sx + c * sy)
    for i in range(m):
        x = moved[i, 0]
        y = moved[i, 1]
        moved[i, 0] = c * x - s * y + ux
        moved[i, 1] = s * x + c * y + uy
    return True, c, s, ux, uy


@njit(cache=True, nogil=True)
def _score(moved, pts, g, r2, stride):  # pragma: no cover - compiled
    """(pairs, rms (m)) of every stride-th template point against its nearest candidate within r."""
    n = 0
    ss = 0.0
    for i in range(0, moved.shape[0], stride):
        j, d = nearest(pts, g, moved[i, 0], moved[i, 1], moved[i, 2], r2)
        if j >= 0:
            n += 1
            ss += d
    return n, (math.sqrt(ss / n) if n else np.inf)


@njit(cache=True, nogil=True)
def _centre_step(tpl, c_tot, s_tot, tx, ty):  # pragma: no cover - compiled
    """How far the rigid motion (rotation c_tot, s_tot; translation tx, ty) moves tpl's centre."""
    m = tpl.shape[0]
    cx = 0.0
    cy = 0.0
    for i in range(m):
        cx += tpl[i, 0]
        cy += tpl[i, 1]
    cx /= m
    cy /= m
    return math.hypot(c_tot * cx - s_tot * cy + tx - cx, s_tot * cx + c_tot * cy + ty - cy)


@njit(cache=True, nogil=True)
def icp(scan, object_id, tpl, fit):  # pragma: no cover - compiled
    """Planar point-to-point ICP of tpl onto the scan's points in tpl's box grown by the margin
    that are FIXED or object_id's (ObjectTracker._register_all).

    Returns (status, moved template, yaw, tx, ty, inlier fraction, rms, step of the template's
    centre): status 0 registered (the caller still checks step, inliers and rms), 1 too few
    candidate points (unseen), 2 too few pairs in an iteration (lost). The rotation (yaw) and
    translation compose every iteration's step: R_total p + t_total maps the template before to
    after. The fit uses every k-th template point, at most max_points of them (the transform
    moves the whole template); the inlier fraction and rms are theirs."""
    margin, r, iterations, min_pairs, max_points = fit
    m = tpl.shape[0]
    stride = max(1, (m + max_points - 1) // max_points)
    used = (m + stride - 1) // stride
    pts = _candidates(scan, object_id, tpl, margin)
    moved = tpl.copy()
    if pts.shape[0] < min_pairs:
        return 1, moved, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0
    g = grid(pts, r, 3)
    r2 = r * r
    match = np.full(m, -1, np.int64)
    c_tot = 1.0
    s_tot = 0.0
    tx = 0.0
    ty = 0.0
    for _ in range(iterations):
        ok, c, s, ux, uy = _step(moved, pts, g, r2, stride, match, min_pairs)
        if not ok:
            return 2, moved, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0
        # compose: R_total <- R R_total, t_total <- R t_total + t
        c_new = c * c_tot - s * s_tot
        s_new = s * c_tot + c * s_tot
        c_tot, s_tot = c_new, s_new
        tx, ty = c * tx - s * ty + ux, s * tx + c * ty + uy
        if abs(ux) + abs(uy) < 5e-4 and abs(s) < 5e-4:
            break  # converged (under 0.5 mm and 0.03 degrees)
    n, rms = _score(moved, pts, g, r2, stride)
    step = _centre_step(tpl, c_tot, s_tot, tx, ty)
    return 0, moved, math.atan2(s_tot, c_tot), tx, ty, n / used, rms, step


@njit(cache=True, nogil=True)
def icp_all(scan, ids, templates, fit):  # pragma: no cover - compiled
    """icp for every tracked object in one call (object k's template: rows off[k]:off[k + 1] of
    templates = (points, off); its id ids[k]): (status (K,), moved templates (concatenated),
    (K, 6) yaw, tx, ty, inlier fraction, rms, step)."""
    tpl, off = templates
    K = ids.shape[0]
    status = np.empty(K, np.int64)
    res = np.zeros((K, 6))
    moved = np.empty_like(tpl)
    for k in range(K):
        a = off[k]
        b = off[k + 1]
        st, mv, yaw, tx, ty, fr, rms, step = icp(scan, ids[k], tpl[a:b], fit)
        status[k] = st
        moved[a:b] = mv
        res[k, 0] = yaw
        res[k, 1] = tx
        res[k, 2] = ty
        res[k, 3] = fr
        res[k, 4] = rms
        res[k, 5] = step
    return status, moved, res


__all__ = ["icp", "icp_all"]
