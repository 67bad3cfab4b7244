"""Movable objects followed between masks: a rigid point template per object, registered to each scan.

Why: the mask memory's warp assumes that an object stands still (Phase I). The object the robot
pushes does not: it stays in front of the robot while the warp carries its mask towards the
image border and grows it, and the stage stops trusting the mask (VppConfig.max_mask_growth).
Between two masks that see it, the object's lidar points must still be P_mov, or the planner
sees a fixed wall in front of the bumper and stops. The camera also sees less than the lidar
(its field of view is narrower): the parts of a tracked object beside the robot are known only
from here.

How, per object, with the points of one scan in the odom frame:
- Confirmation: the scan points a mask labelled movable for the object, in view, become its
  template (plus the previous template's points the new view does not cover, as long as the
  union spans no more than `max_growth_m` beyond the new view: a far view shows one face, a
  near one the rest). A template holds only points a mask confirmed, moved rigidly since: never
  points it picked up by being near them, so it cannot creep into a wall the object touches.
- Tracking: every scan, each template (of an object a mask confirmed less than
  `max_unconfirmed_s` ago) is registered to the scan's fixed points near it (and its own) by a
  few iterations of planar point-to-point ICP (yaw and x, y: a pushed object slides on the
  floor), with correspondences within `max_correspondence_m`; a step larger than `max_step_m`
  is refused (the template stays where it was). Then a mask's view, if any, is merged (a view
  that disagrees with the template: the bigger of the two wins, so that a sliver at the image
  border does not replace the object), and every fixed point within `label_radius_m` of the
  template takes the object's id and cost: the parts of the object the camera does not see.
- Spread: the fixed points a template takes join it (the faces of the object the camera never
  saw, which the robot may be pushing on) while the template spans at most `max_spread_m` more
  than the largest view a mask confirmed: a box pressed against a wall takes at most that much
  of the wall.
- Plausibility: a mask's view of an object the tracker knows where it is (registered this scan,
  or registered or seen within `max_unknown_s`) whose centre lies farther from the template's
  than half their footprints and `max_step_m` is not the object: refused, and its points are
  fixed (_implausible_views: a view that replaced the template there took a wall for a box);
  the caller fixes them in its label memory too (`refused_points`). Only a template of at
  least `min_confirmations` views is trusted so; one whose views are all refused expires.
- Identity: the mask memory gives an object a new id when its warped mask stops matching the
  fresh one (it moved); a new id whose view lies mostly on a tracked template takes that
  template over (and its confirmation time), so one box is one tracked object.
Points a tracked object would take are only ever FIXED ones (not ground, not another object's).

This replaces label spreading from the previous scan's movable points (which, one
`track_radius_m` hop per scan, walked into the wall a pushed box was pressed against; an extent
limit then dropped the whole object).

Cost: a template is voxel-thinned to `template_voxel_m` (a 0.4 m box: ~200 points); per object
and scan one compiled pass each for the registration (a grid of the candidate points, at most
`icp_iterations` nearest-neighbour rounds), the labelling and the merge of a mask's view: about
0.1 ms an object (`dct bench vpp`).
"""
from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, field

import numpy as np
from numba import njit
from pydantic import BaseModel, ConfigDict, Field, model_validator

from runtime.common.spatial_grid import any_within, grid, near_any, nearest
from runtime.vpp.partition import FIXED, MOVABLE, PointPartition


class TrackingConfig(BaseModel):
    """Settings of the movable-object tracker (controller config `vpp.tracking`)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    enabled: bool = True
    #: A template older than this since a mask last confirmed the object is dropped.
    max_unconfirmed_s: float = Field(8.0, gt=0.0, le=120.0)
    #: Fewer mask-labelled points than this do not confirm (a sliver at the image border).
    min_confirm_points: int = Field(10, ge=3, le=100000)
    #: Template thinning (m), and its size cap (points; a 0.4 m box at 3 cm: ~600).
    template_voxel_m: float = Field(0.03, gt=0.0, le=1.0)
    max_template_points: int = Field(600, ge=10, le=100000)
    #: Fixed points within this of the template's box (odom frame) are candidates (m): the
    #: object's motion in one scan (0.1 s) at most.
    search_margin_m: float = Field(0.25, gt=0.0, le=2.0)
    max_correspondence_m: float = Field(0.10, gt=0.0, le=1.0)
    icp_iterations: int = Field(6, ge=1, le=50)
    #: The registration fits every k-th template point, at most this many (a pushed box seen from
    #: 0.2 m fills its 600-point template: 2.5 ms a scan with all of them, ~0.5 ms with 150).
    icp_max_points: int = Field(150, ge=10, le=100000)
    #: Fewer matched pairs than this: not registered (the object is not in the scan this time).
    min_pairs: int = Field(12, ge=3, le=100000)
    #: A registration that moves the object farther than this in one scan is refused (m).
    max_step_m: float = Field(0.2, gt=0.0, le=2.0)
    #: A registration must match at least this share of the template within
    #: max_correspondence_m (its far side is hidden: not all of it), at most this rms (m).
    #: (Measured on case1's registrations: inliers >= 0.72, rms 0.03-0.046 m with the simulated
    #: lidar's 2 cm range noise and point spacing.)
    min_inlier_fraction: float = Field(0.5, gt=0.0, le=1.0)
    max_rms_m: float = Field(0.06, gt=0.0, le=1.0)
    #: Fixed points within this of the registered template join the object (m).
    label_radius_m: float = Field(0.06, gt=0.0, le=0.5)
    #: A fixed point up to this far behind the template along its own lidar ray (the ray passes
    #: within label_radius_m of a template point on its last behind_m) is the object's too: the
    #: lidar does not see through a solid object, and range noise (2 cm sigma on a Mid-360; the
    #: template's points carry theirs) puts 1-3 points a scan of a box's face 6-8 cm deep. One
    #: such point left P_fix on case1's box made the straight push lethal for a replan and sent
    #: the robot round the box's corner (0.25 s). 0: off.
    behind_m: float = Field(0.10, ge=0.0, le=0.5)
    #: The template may span at most this much more than the newest confirming view (m).
    max_growth_m: float = Field(0.3, ge=0.0, le=5.0)
    #: The fixed points a template takes (its faces the camera never saw: the side the robot
    #: pushes on) join it while it spans at most this much more than the largest confirming
    #: view (m): a box pressed against a wall takes at most this much of the wall.
    max_spread_m: float = Field(0.1, ge=0.0, le=2.0)
    #: A mask's view of an object known (registered or seen) within the last max_unknown_s (a few
    #: scans) whose centre lies farther from the template's than half their two footprints and
    #: max_step_m is not the object: refused, and its points fixed
    #: (ObjectTracker._implausible_views), once the template has min_confirmations views (one
    #: view may have been the mistake: the next views replace it). An object unknown for longer
    #: may have moved unseen: its view is taken. A template whose views are all refused is not
    #: confirmed, and is dropped after max_unconfirmed_s.
    max_unknown_s: float = Field(0.3, ge=0.0, le=60.0)
    min_confirmations: int = Field(3, ge=1, le=1000)

    @model_validator(mode="after")
    def _fit_can_pair(self) -> "TrackingConfig":
        if self.icp_max_points < self.min_pairs:
            raise ValueError(f"icp_max_points ({self.icp_max_points}) must be at least min_pairs ({self.min_pairs}): "
                             "no registration could succeed")
        return self


@njit(cache=True, nogil=True)
def _bounds(points):  # pragma: no cover - compiled
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


def _extent(points: np.ndarray, yaw: float = 0.0) -> float:
    """The points' size (m): _extent_nb."""
    if len(points) < 2:
        return 0.0
    return float(_extent_nb(np.ascontiguousarray(points, dtype=np.float64), float(yaw)))


def _footprint(points: np.ndarray, yaw: float = 0.0) -> float:
    """The diagonal (m) of the points' bounding box in the plane, in the object's frame (the
    odom frame turned by yaw, as _extent_nb)."""
    if len(points) < 2:
        return 0.0
    c, s = math.cos(yaw), math.sin(yaw)
    x = c * points[:, 0] + s * points[:, 1]
    y = -s * points[:, 0] + c * points[:, 1]
    return float(math.hypot(np.ptp(x), np.ptp(y)))


def _thin(points: np.ndarray, voxel_m: float, max_points: int = 0) -> np.ndarray:
    """One point per voxel (the first), in a stable order; then at most max_points (0: no cap) by
    an even stride (_thin_first: compiled, ~20 us for 1000 points)."""
    if len(points) == 0:
        return points
    return _thin_nb(np.ascontiguousarray(points, dtype=np.float64), float(voxel_m), int(max_points))


@njit(cache=True, nogil=True)
def _in_boxes(p, label, lo, hi):  # pragma: no cover - compiled
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
def _group_masked(label, in_view, from_memory, oid):  # pragma: no cover - compiled
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
    counts = np.zeros(m, np.int64)  # loop makes numba count references every iteration: 10x slower)
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
def _box_candidates(p, label, oid, object_id, lo, hi, near):  # pragma: no cover - compiled
    """The indices of `near` (_in_boxes) whose points are inside the box [lo, hi] and FIXED (or
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


@njit(cache=True, nogil=True)
def _thin_nb(points, voxel, max_points):  # pragma: no cover - compiled
    """_thin, compiled: the first point of each voxel in their order, then an even stride of
    max_points (0: all) of them (numpy's linspace, truncated)."""
    out = points[_thin_first(points, voxel)]
    n = out.shape[0]
    if max_points > 0 and n > max_points:
        pick = np.linspace(0, n - 1, max_points).astype(np.int64)
        out = out[pick]
    return out


@njit(cache=True, nogil=True)
def _extent_nb(points, yaw):  # pragma: no cover - compiled
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
def _merge_view(new, old, voxel, max_points, max_growth, yaw):  # pragma: no cover - compiled
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
    if _extent_nb(union, yaw) <= max(_extent_nb(new, yaw), _extent_nb(old, yaw)) + max_growth:
        return _thin_nb(union, voxel, max_points), 0
    if new.shape[0] < old.shape[0] // 2:
        return old, 1
    return new, 2


@njit(cache=True, nogil=True)
def _confirm_all(p, idx, starts, old, ooff, yaws, voxel, max_points, max_growth):  # pragma: no cover - compiled
    """ObjectTracker._confirm's image of every confirming object that has a template, in one
    call: object k's view is p[idx[starts[k]:starts[k + 1]]], its template old[ooff[k]:ooff[k +
    1]], its yaw yaws[k]. Returns (templates concatenated, offsets (K + 1,), outcome (K,) as
    _merge_view's, the view's extent (K,))."""
    K = starts.shape[0] - 1
    outs = []
    noff = np.zeros(K + 1, np.int64)
    outcome = np.empty(K, np.int64)
    extent = np.empty(K)
    for k in range(K):
        pts = np.empty((starts[k + 1] - starts[k], 3))
        for j in range(pts.shape[0]):
            i = idx[starts[k] + j]
            pts[j, 0] = p[i, 0]
            pts[j, 1] = p[i, 1]
            pts[j, 2] = p[i, 2]
        new = _thin_nb(pts, voxel, max_points)
        tpl, outcome[k] = _merge_view(new, old[ooff[k]:ooff[k + 1]], voxel, max_points, max_growth, yaws[k])
        extent[k] = _extent_nb(pts, yaws[k])
        outs.append(tpl)
        noff[k + 1] = noff[k] + tpl.shape[0]
    merged = np.empty((noff[K], 3))
    for k in range(K):
        merged[noff[k]:noff[k + 1]] = outs[k]
    return merged, noff, outcome, extent


@njit(cache=True, nogil=True)
def _spread_all(p, taken, toff, tpl, off, yaws, view_extent, max_spread, voxel, max_points):  # pragma: no cover
    """_label_all's growth of every object's template by the points it took, in one call: where
    template + taken spans at most view_extent[k] + max_spread, the template becomes that union
    thinned (_thin_nb), else it stays. Returns (templates concatenated, offsets, grown (K,))."""
    K = off.shape[0] - 1
    outs = []
    noff = np.zeros(K + 1, np.int64)
    grown = np.zeros(K, np.bool_)
    for k in range(K):
        a, b = off[k], off[k + 1]
        nt = toff[k + 1] - toff[k]
        res = tpl[a:b]
        if nt > 0:
            union = np.empty((b - a + nt, 3))
            union[:b - a] = tpl[a:b]
            for j in range(nt):
                i = taken[toff[k] + j]
                union[b - a + j, 0] = p[i, 0]
                union[b - a + j, 1] = p[i, 1]
                union[b - a + j, 2] = p[i, 2]
            if _extent_nb(union, yaws[k]) <= view_extent[k] + max_spread:
                res = _thin_nb(union, voxel, max_points)
                grown[k] = True
        outs.append(res)
        noff[k + 1] = noff[k] + res.shape[0]
    merged = np.empty((noff[K], 3))
    for k in range(K):
        merged[noff[k]:noff[k + 1]] = outs[k]
    return merged, noff, grown


@njit(cache=True, nogil=True)
def _icp(p, label, oid, near, object_id, tpl, margin, r, iterations, min_pairs, max_points):  # pragma: no cover
    """Planar point-to-point ICP of tpl onto the points of p (among `near`) in tpl's box grown
    by margin that are FIXED or object_id's (ObjectTracker._register).

    Returns (status, moved template, yaw, tx, ty, inlier fraction, rms, step of the template's
    centre): status 0 registered
    (the caller still checks step, inliers and rms), 1 too few candidate points (unseen), 2
    too few pairs in an iteration (lost). The rotation (yaw) and translation compose every
    iteration's step: R_total p + t_total maps the template before to after. The fit uses every
    k-th template point, at most max_points of them (the transform moves the whole template);
    the inlier fraction and rms are theirs."""
    m = tpl.shape[0]
    stride = max(1, (m + max_points - 1) // max_points)
    used = (m + stride - 1) // stride
    lo, hi = _bounds(tpl)
    for a in range(3):
        lo[a] -= margin
        hi[a] += margin
    cand = _box_candidates(p, label, oid, object_id, lo, hi, near)
    moved = tpl.copy()
    if cand.shape[0] < min_pairs:
        return 1, moved, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0
    pts = np.empty((cand.shape[0], 3))
    for i in range(cand.shape[0]):
        for a in range(3):
            pts[i, a] = p[cand[i], a]
    glo, cell, reach, dims, start, order = grid(pts, r, 3)
    r2 = r * r
    match = np.full(m, -1, np.int64)
    c_tot = 1.0
    s_tot = 0.0
    tx = 0.0
    ty = 0.0
    for _ in range(iterations):
        n = 0
        sx = sy = dx = dy = 0.0
        for i in range(0, m, stride):
            j, _d = nearest(pts, glo, cell, reach, dims, start, order, moved[i, 0], moved[i, 1], moved[i, 2], r2)
            match[i] = j
            if j >= 0:
                n += 1
                sx += moved[i, 0]
                sy += moved[i, 1]
                dx += pts[j, 0]
                dy += pts[j, 1]
        if n < min_pairs:
            return 2, moved, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0
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
        # compose: R_total <- R R_total, t_total <- R t_total + t
        c_new = c * c_tot - s * s_tot
        s_new = s * c_tot + c * s_tot
        c_tot, s_tot = c_new, s_new
        tx, ty = c * tx - s * ty + ux, s * tx + c * ty + uy
        if abs(ux) + abs(uy) < 5e-4 and abs(s) < 5e-4:
            break  # converged (under 0.5 mm and 0.03 degrees)
    n = 0
    ss = 0.0
    for i in range(0, m, stride):
        j, d = nearest(pts, glo, cell, reach, dims, start, order, moved[i, 0], moved[i, 1], moved[i, 2], r2)
        if j >= 0:
            n += 1
            ss += d
    rms = math.sqrt(ss / n) if n else np.inf
    cx = 0.0
    cy = 0.0
    for i in range(m):
        cx += tpl[i, 0]
        cy += tpl[i, 1]
    cx /= m
    cy /= m
    step = math.hypot(c_tot * cx - s_tot * cy + tx - cx, s_tot * cx + c_tot * cy + ty - cy)
    return 0, moved, math.atan2(s_tot, c_tot), tx, ty, n / used, rms, step


@njit(cache=True, nogil=True)
def _icp_all(p, label, oid, near, ids, tpl, off, margin, r, iterations, min_pairs, max_points):  # pragma: no cover
    """_icp for every tracked object in one call (templates concatenated, object k's rows
    off[k]:off[k + 1]): (status (K,), moved templates (concatenated), (K, 6) yaw, tx, ty,
    inlier fraction, rms, step)."""
    K = ids.shape[0]
    status = np.empty(K, np.int64)
    res = np.zeros((K, 6))
    moved = np.empty_like(tpl)
    for k in range(K):
        a = off[k]
        b = off[k + 1]
        st, mv, yaw, tx, ty, fr, rms, step = _icp(p, label, oid, near, ids[k], tpl[a:b], margin, r, iterations,
                                                 min_pairs, max_points)
        status[k] = st
        moved[a:b] = mv
        res[k, 0] = yaw
        res[k, 1] = tx
        res[k, 2] = ty
        res[k, 3] = fr
        res[k, 4] = rms
        res[k, 5] = step
    return status, moved, res


@njit(cache=True, nogil=True)
def _take_all(p, label, oid, cost, near, tpl, off, r, ids, costs, origin, behind):  # pragma: no cover - compiled
    """ObjectTracker._label's take for every object in order (an object takes only the FIXED
    points left by those before it), labelling in place: (taken point indices concatenated,
    offsets (K + 1,)). behind > 0: also the points seen behind a template (_take_near)."""
    K = ids.shape[0]
    out = np.empty(near.shape[0], np.int64)
    toff = np.zeros(K + 1, np.int64)
    n = 0
    for k in range(K):
        take = _take_near(p, label, near, tpl[off[k]:off[k + 1]], r, origin, behind)
        for i in take:
            label[i] = MOVABLE
            oid[i] = ids[k]
            cost[i] = costs[k]
            out[n] = i
            n += 1
        toff[k + 1] = n
    return out[:n], toff


@njit(cache=True, nogil=True)
def _take_near(p, label, near, tpl, r, origin, behind):  # pragma: no cover - compiled
    """Indices of the FIXED points of p (among `near`) closer than r to a template point, or (with
    behind > 0) whose ray from the lidar at `origin` passes closer than r to one on its last
    `behind` metres: seen behind the object's surface (ObjectTracker._label)."""
    lo, hi = _bounds(tpl)
    glo, cell, reach, dims, start, order = grid(tpl, r, 1)
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
        if any_within(tpl, glo, cell, reach, dims, start, order, x, y, z, r2):
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
            if any_within(tpl, glo, cell, reach, dims, start, order, x - t * ux, y - t * uy, z - t * uz, r2):
                out[n] = i
                n += 1
                break
    return out[:n]


@njit(cache=True, nogil=True)
def _thin_first(points, voxel):  # pragma: no cover - compiled
    """Indices (ascending) of the first point in each voxel: one pass with an open-addressing
    table of the voxel keys (three 21-bit cell indices packed in an int64, from the points'
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
    shift = np.uint64(64 - bits)
    table = np.full(size, -1, np.int64)
    out = np.empty(n, np.int64)
    u = 0
    for i in range(n):
        key = ((kk[i, 0] - kmin[0]) << 42) | ((kk[i, 1] - kmin[1]) << 21) | (kk[i, 2] - kmin[2])
        h = np.int64((np.uint64(key) * np.uint64(0x9E3779B97F4A7C15)) >> shift)  # Fibonacci hashing
        while True:
            if table[h] == -1:
                table[h] = key
                out[u] = i
                u += 1
                break
            if table[h] == key:
                break
            h = (h + 1) & (size - 1)
    return out[:u]


#: Scans of centre history kept per object (30 s at 10 Hz: longer than the mask memory's max age).
HISTORY_SCANS = 300


@dataclass
class TrackedObject:
    object_id: int
    cost: float
    template: np.ndarray  # (M, 3) odom frame, thinned
    confirmed_s: float
    tracked_scans: int = 0
    view_extent_m: float = 0.0  # the largest extent a confirming view had
    #: A point fixed to the object (x, y), moved only by the registrations' rigid motions (the
    #: template's centre also shifts as views and spread add points: not a motion).
    anchor: np.ndarray | None = None
    #: What the object turned since the tracker first saw it (rad, the sum of its registrations'
    #: yaws): its own frame, in which its size is measured (_extent_nb).
    yaw: float = 0.0
    #: (time, anchor x, y, known) after every scan: where the object was when, and whether this
    #: scan registered it or a mask saw it (moved_since).
    history: deque = field(default_factory=lambda: deque(maxlen=HISTORY_SCANS))
    #: Mask views merged into the template (a template one view made may be that view's mistake).
    confirmations: int = 1

    def __post_init__(self) -> None:
        if self.anchor is None:
            self.anchor = self.centre()

    def centre(self) -> np.ndarray:
        return self.template[:, :2].mean(axis=0)


class ObjectTracker:
    """Templates of movable objects and their registration to each scan (module docstring)."""

    def __init__(self, config: TrackingConfig | None = None) -> None:
        self.config = config or TrackingConfig()
        self.objects: dict[int, TrackedObject] = {}
        # Counters (never reset).
        self.points_tracked = 0
        self.registrations = 0
        self.lost = 0  # registrations refused (too few pairs, too big a step)
        self.handovers = 0  # templates passed to a new mask id of the same object
        self.refused_views = 0  # mask views refused as implausible jumps (their points fixed)
        self.refused_points = np.zeros(0, np.int64)
        self.unseen = 0  # object-scans with too few points near the template to register
        #: (old id, new id) of the handovers since the caller last emptied it (the stage moves
        #: the object's belief with it)
        self.handover_pairs: list[tuple[int, int]] = []
        self._origin: np.ndarray | None = None  # this scan's lidar position (update)
        self._warm_up()

    def _warm_up(self) -> None:
        """Run every kernel once on a tiny scene (a box seen by a mask, then tracked and handed
        to a new id), so that numba's compile or cache load happens at start-up, not in the first
        tick that tracks an object; then forget it."""
        g = np.arange(0.0, 0.31, 0.03)
        a, b = np.meshgrid(g, g)
        face = np.c_[np.full(a.size, 1.0), a.ravel() - 0.15, b.ravel() + 0.05]
        pts = np.concatenate([face, face + [0.3, 0.0, 0.0], np.c_[np.full(40, 1.15), np.linspace(-0.5, 0.5, 40),
                                                                   np.full(40, 0.2)]])
        n = len(pts)
        for k, (oid, shift) in enumerate(((0, 0.0), (0, 0.02), (1, 0.04))):
            label = np.full(n, FIXED, np.int8)
            obj = np.full(n, -1, np.int32)
            label[: 2 * len(face)], obj[: 2 * len(face)] = MOVABLE, oid
            part = PointPartition(label, obj, np.where(label == MOVABLE, 2.0, np.nan).astype(np.float32),
                                  np.ones(n, bool), np.zeros(n, bool), 0, 0)
            self.update(0.1 * k, part, pts + [shift, 0.0, 0.0], origin_odom=np.zeros(3))
        # a template's growth by the points it took (a scene above may not take any)
        c = self.config
        _spread_all(pts, np.zeros(1, np.int64), np.array([0, 1]), face, np.array([0, len(face)]), np.zeros(1), np.ones(1),
                    float(c.max_spread_m), float(c.template_voxel_m), int(c.max_template_points))
        self.objects.clear()
        self._origin = None
        self.points_tracked = self.registrations = self.lost = self.handovers = self.unseen = 0
        self.refused_views = 0
        self.handover_pairs.clear()

    def update(self, now_s: float, part: PointPartition, points_odom: np.ndarray, skip=(),
               origin_odom: np.ndarray | None = None) -> int:
        """Register every object's template to this scan, merge what the masks confirmed, label
        the objects' points in `part` (in place); returns the points labelled by tracking.
        skip: object ids not to track (deformable objects: they do not move as one body,
        runtime/vpp/deformable.py); a template of one of them is dropped. origin_odom: the
        lidar's position (3,) the scan was seen from (None: no behind-the-surface labelling)."""
        self._origin = None if origin_odom is None else np.ascontiguousarray(origin_odom, np.float64)
        c = self.config
        if not c.enabled:
            return 0
        for k in skip:
            self.objects.pop(k, None)
        label, oid, cost = part.label, part.object_id, part.cost
        # the points each mask labelled, by object, in one pass (not a pass per object)
        ids, starts, idx = _group_masked(label, part.in_view, part.from_memory, oid)
        confirming: dict[int, np.ndarray] = {}
        for k, (a, b) in sorted(zip(ids.tolist(), zip(starts[:-1].tolist(), starts[1:].tolist()))):
            if b - a >= c.min_confirm_points and k not in skip:
                confirming[k] = idx[a:b]  # ascending point indices
        for k in [k for k, o in self.objects.items() if now_s - o.confirmed_s > c.max_unconfirmed_s
                  and k not in confirming]:
            del self.objects[k]
        added = 0
        near, boxes = self._near(label, points_odom, c.search_margin_m)
        followed = self._register_all(label, oid, near, points_odom)
        refused = []
        for k in self._implausible_views(now_s, confirming, followed, points_odom):
            sel = confirming.pop(k)
            label[sel], oid[sel], cost[sel] = FIXED, -1, np.nan
            refused.append(sel)
            self.refused_views += 1
            if now_s - self.objects[k].confirmed_s > c.max_unconfirmed_s:
                del self.objects[k]  # (its views refused all that time: not the object it was taken for)
        #: The scan points whose mask view was refused this scan (fixed above): the caller's label
        #: memory, written before, must hold them fixed too.
        self.refused_points = np.concatenate(refused) if refused else np.zeros(0, np.int64)
        self._confirm_views(now_s, confirming, points_odom, cost)
        # the templates as registered and merged: their points to label are those of `near`
        # unless a template now reaches out of every box `near` was taken from (a new object, a
        # view beyond the old template): then one more pass
        reach = c.label_radius_m + (c.behind_m if origin_odom is not None else 0.0)
        lab = self._boxes(reach)
        if boxes is None or not all(((lo >= boxes[0]) & (hi <= boxes[1])).all(axis=1).any()
                                    for lo, hi in zip(*lab)):
            near, _ = self._near(label, points_odom, reach)
        added = self._label_all(label, oid, cost, near, points_odom)
        for k, obj in self.objects.items():
            # Known this scan: registered, or seen by a mask (whose view, if it disagreed, moved the anchor).
            obj.history.append((float(now_s), *obj.anchor, k in followed or k in confirming))
        self.points_tracked += added
        return added

    def _implausible_views(self, now_s: float, confirming: dict[int, np.ndarray], followed: set[int],
                           points_odom: np.ndarray) -> list[int]:
        """The objects whose mask view this scan cannot be them: the object was known (registered
        this scan, or registered or seen within max_unknown_s) and the view's centre lies
        farther from the template's than half their two footprints' diagonals and max_step_m
        together (two views of one object have their centres on its footprint), once the template
        has min_confirmations views. Measured on BEACON cluttered seed 0: 9 scans running of a
        box's view on the room's wall 2.4 m away. And (BEACON
        collision-required seed 0, on a route an experimental planner change took past a low box
        0.7 m from a wall): one scan's mask view of the box was a strip of the wall behind it (the
        partition's refinement took the wall, which outnumbered the box in the mask, for the
        object); the view replaced the box's template 1.15 m away, the tracker labelled
        thousands of wall points touchable, and the robot drove into the wall."""
        c = self.config
        out = []
        for k, sel in confirming.items():
            obj = self.objects.get(k)
            if obj is None or not len(obj.template) or not len(sel) or obj.confirmations < c.min_confirmations:
                continue
            known = k in followed
            for h in reversed(obj.history):  # (time, x, y, known), newest last
                if known or now_s - h[0] > c.max_unknown_s + 1e-6:
                    break
                known = bool(h[3])
            if not known:
                continue
            view = points_odom[sel]
            d = float(np.hypot(*(view[:, :2].mean(axis=0) - obj.centre())))
            if d > 0.5 * (_footprint(obj.template, obj.yaw) + _footprint(view, obj.yaw)) + c.max_step_m:
                out.append(k)
        return out

    def moved_since(self, object_id: int, t_s: float) -> float | None:
        """How far (m) object_id moved since time t_s (its anchor: rigid motions only); None when
        the tracker did not follow it all that time: not tracked, tracked only since later (a
        mask's capture precedes the answer that starts the track by the backend's latency), or a
        scan since then in which it was neither registered nor seen by a mask (occluded, knocked
        away, a registration refused): what it did then is unknown, and the caller must not read
        "stood still" into it."""
        obj = self.objects.get(int(object_id))
        if obj is None or not obj.history or obj.history[0][0] > t_s:
            return None
        # newest first: a capture is a few scans old, the history up to HISTORY_SCANS long
        for h in reversed(obj.history):
            if h[0] <= t_s:
                return float(math.hypot(obj.anchor[0] - h[1], obj.anchor[1] - h[2]))
            if not h[3]:
                return None  # a scan after t_s that did not know where the object was
        return None

    def _confirm_views(self, now_s: float, confirming: dict[int, np.ndarray], points_odom: np.ndarray,
                       cost: np.ndarray) -> None:
        """_confirm for every object a mask saw this scan, in id order. When each of them already
        has a template (every scan but those after a new answer), all in one compiled call
        (_confirm_all: the same arithmetic as _confirm, without its Python per object); a new id
        may take over another object's template (_hand_over), so those scans go one by one."""
        if not confirming:
            return
        objs = [self.objects.get(k) for k in confirming]
        if any(o is None or not len(o.template) for o in objs):
            for k, sel in confirming.items():
                self._confirm(k, now_s, points_odom[sel], float(cost[sel[0]]))
            return
        c = self.config
        sels = list(confirming.values())
        starts = np.zeros(len(sels) + 1, np.int64)
        starts[1:] = np.cumsum([len(x) for x in sels])
        tpl, ooff = self._stack(objs)
        yaws = np.array([o.yaw for o in objs])
        merged, noff, outcome, extent = _confirm_all(points_odom, np.concatenate(sels), starts, tpl, ooff, yaws,
                                                     float(c.template_voxel_m), int(c.max_template_points),
                                                     float(c.max_growth_m))
        for k, (obj, sel) in enumerate(zip(objs, sels)):
            obj.cost = float(cost[sel[0]])
            obj.template = merged[noff[k]:noff[k + 1]]
            obj.confirmed_s = now_s
            obj.confirmations += 1
            obj.view_extent_m = max(float(extent[k]), obj.view_extent_m)
            if outcome[k] == 2:  # the view replaced the template: its centre is the new anchor
                obj.anchor = obj.centre()

    def _confirm(self, k: int, now_s: float, points: np.ndarray, cost: float) -> None:
        """Merge a mask's view of object k into its template (registered to this scan already)."""
        c = self.config
        new = _thin(points, c.template_voxel_m, c.max_template_points)
        old = self.objects.get(k) or self._hand_over(k, new)
        anchor = None
        if old is not None and len(old.template):
            # a far view's face and a near view's top merge; a sliver that disagrees (at the image
            # border) leaves the template; a substantial view that disagrees (the object moved
            # unseen) replaces it, and its anchor (its centre: a jump the history shows as a motion)
            new, outcome = _merge_view(new, old.template, c.template_voxel_m, c.max_template_points, c.max_growth_m,
                                       old.yaw)
            anchor = None if outcome == 2 else old.anchor
        yaw = 0.0 if old is None else old.yaw
        view = _extent(points, yaw)
        obj = TrackedObject(k, cost, new, now_s, 0 if old is None else old.tracked_scans,
                            view if old is None else max(view, old.view_extent_m), anchor, yaw)
        if old is not None:
            obj.history = old.history
            obj.confirmations = old.confirmations + 1
        self.objects[k] = obj

    def _hand_over(self, k: int, new: np.ndarray) -> TrackedObject | None:
        """The tracked object a new mask id is seen on (the mask memory gives a moved object a new
        id when its warped mask no longer matches the fresh one): it leaves the tracker and its
        template goes to k. Most of the new view must lie on its template."""
        c = self.config
        for j, obj in list(self.objects.items()):
            if np.mean(near_any(new, obj.template, 2 * c.label_radius_m)) >= 0.5:
                self.handovers += 1
                self.handover_pairs.append((int(j), int(k)))
                return self.objects.pop(j)
        return None

    def _boxes(self, grow: float) -> tuple[np.ndarray, np.ndarray]:
        """(lo (K, 3), hi (K, 3)): the tracked templates' boxes grown by `grow`."""
        b = [_bounds(o.template) for o in self.objects.values() if len(o.template)]
        if not b:
            return np.zeros((0, 3)), np.zeros((0, 3))
        return np.array([x[0] for x in b]) - grow, np.array([x[1] for x in b]) + grow

    def _near(self, label, points_odom: np.ndarray, grow: float):
        """(indices, boxes): the scan points (not ground) in any tracked object's template box
        grown by `grow` (_in_boxes), the only points a registration (grow = search_margin_m) or
        a labelling (label_radius_m) can use, found in one pass for all objects; the boxes
        (None without objects)."""
        lo, hi = self._boxes(grow)
        if not len(lo):
            return np.zeros(0, np.int64), None
        return _in_boxes(points_odom, label, lo, hi), (lo, hi)

    @staticmethod
    def _stack(objs: list[TrackedObject]) -> tuple[np.ndarray, np.ndarray]:
        """The objects' templates concatenated, and each one's row offsets."""
        off = np.zeros(len(objs) + 1, np.int64)
        off[1:] = np.cumsum([len(o.template) for o in objs])
        return np.ascontiguousarray(np.concatenate([o.template for o in objs]), dtype=np.float64), off

    def _register_all(self, label, oid, near: np.ndarray, points_odom: np.ndarray) -> set[int]:
        """Move every template onto this scan's points (planar ICP, _icp: the fixed points and the
        object's own in its box grown by search_margin_m), all objects in one compiled call;
        returns the ids registered. A template stays where it was when the scan does not show
        the object or the registration is refused."""
        c = self.config
        objs = [o for o in self.objects.values() if len(o.template)]
        if not objs:
            return set()
        tpl, off = self._stack(objs)
        ids = np.array([o.object_id for o in objs], np.int64)
        status, moved, res = _icp_all(points_odom, label, oid, near, ids, tpl, off, c.search_margin_m,
                                      c.max_correspondence_m, c.icp_iterations, c.min_pairs, c.icp_max_points)
        followed = set()
        for k, obj in enumerate(objs):
            yaw, tx, ty, inlier_fraction, rms, step = res[k].tolist()
            if status[k] == 1:
                self.unseen += 1  # not in this scan (occluded, out of range, gone)
                continue
            # Too few pairs; a fit that matched too little of the template (it slid half-way onto
            # something else), or matched it loosely, or jumped farther than an object goes in a
            # scan: refused.
            if status[k] == 2 or step > c.max_step_m or inlier_fraction < c.min_inlier_fraction or rms > c.max_rms_m:
                self.lost += 1
                continue
            self.registrations += 1
            obj.template = moved[off[k]:off[k + 1]]
            cs, sn = math.cos(yaw), math.sin(yaw)
            ax, ay = float(obj.anchor[0]), float(obj.anchor[1])
            obj.anchor = np.array([cs * ax - sn * ay + tx, sn * ax + cs * ay + ty])
            obj.yaw += yaw
            obj.tracked_scans += 1
            followed.add(obj.object_id)
        return followed

    def _label_all(self, label, oid, cost, near: np.ndarray, points_odom: np.ndarray) -> int:
        """Fixed points within label_radius_m of an object's template become that object's (in
        the objects' order: one compiled call), and join its template while it spans at most
        max_spread_m more than its largest confirming view; then (with the scan's lidar origin)
        the fixed points seen behind a template (behind_m) become that object's too, without
        joining it (a template grown by them would creep, scan by scan, towards a wall behind
        the object); returns the points labelled."""
        c = self.config
        objs = [o for o in self.objects.values() if len(o.template)]
        if not objs:
            return 0
        tpl, off = self._stack(objs)
        ids = np.array([o.object_id for o in objs], np.int64)
        costs = np.array([o.cost for o in objs], np.float32)
        origin = np.zeros(3) if self._origin is None else np.ascontiguousarray(self._origin, np.float64)
        taken, toff = _take_all(points_odom, label, oid, cost, near, tpl, off, c.label_radius_m, ids, costs,
                                origin, 0.0)
        if c.max_spread_m > 0.0 and taken.size:
            extent = np.array([o.view_extent_m for o in objs])
            yaws = np.array([o.yaw for o in objs])
            merged, noff, grown = _spread_all(points_odom, taken, toff, tpl, off, yaws, extent, float(c.max_spread_m),
                                              float(c.template_voxel_m), int(c.max_template_points))
            for k in np.flatnonzero(grown):
                objs[k].template = merged[noff[k]:noff[k + 1]]
        n = int(taken.size)
        if self._origin is not None and c.behind_m > 0.0:
            tpl, off = self._stack(objs)  # as grown
            behind, _ = _take_all(points_odom, label, oid, cost, near, tpl, off, c.label_radius_m, ids, costs,
                                  origin, float(c.behind_m))
            n += int(behind.size)
        return n


__all__ = ["ObjectTracker", "TrackedObject", "TrackingConfig"]
