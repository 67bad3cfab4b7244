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
- Identity: the mask memory gives an object a new id when its warped mask stops matching the
  fresh one (it moved); a new id whose view lies mostly on a tracked template takes that
  template over (and its confirmation time), so one box is one tracked object.
Points a tracked object would take are only ever FIXED ones (not ground, not another object's).

This replaces label spreading from the previous scan's movable points (which, one
`track_radius_m` hop per scan, walked into the wall a pushed box was pressed against; an extent
limit then dropped the whole object).

Cost: a template is voxel-thinned to `template_voxel_m` (a 0.4 m box: ~200 points); one cKDTree
of the candidate points per object per scan and `icp_iterations` queries.
"""
from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, field

import numpy as np
from numba import njit
from pydantic import BaseModel, ConfigDict, Field
from scipy.spatial import cKDTree

from runtime.vpp.partition import MOVABLE, PointPartition


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
    #: The template may span at most this much more than the newest confirming view (m).
    max_growth_m: float = Field(0.3, ge=0.0, le=5.0)
    #: The fixed points a template takes (its faces the camera never saw: the side the robot
    #: pushes on) join it while it spans at most this much more than the largest confirming
    #: view (m): a box pressed against a wall takes at most this much of the wall.
    max_spread_m: float = Field(0.1, ge=0.0, le=2.0)


def _extent(points: np.ndarray) -> float:
    return float(np.linalg.norm(points.max(axis=0) - points.min(axis=0))) if len(points) > 1 else 0.0


def _thin(points: np.ndarray, voxel_m: float, max_points: int = 0) -> np.ndarray:
    """One point per voxel (the first), in a stable order; then at most max_points (0: no cap) by
    an even stride. Voxel keys packed into one int64 (21 bits an axis: 63 km at 3 cm), so the
    deduplication is a 1-D np.unique (np.unique over rows sorts records: 10x slower)."""
    if len(points) == 0:
        return points
    k = np.floor(points / voxel_m).astype(np.int64)
    k -= k.min(axis=0)
    packed = (k[:, 0] << 42) | (k[:, 1] << 21) | k[:, 2]
    _, first = np.unique(packed, return_index=True)
    out = points[np.sort(first)]
    if max_points and len(out) > max_points:
        out = out[np.linspace(0, len(out) - 1, max_points).astype(np.intp)]
    return out


@njit(cache=True, nogil=True)
def _box_candidates(p, label, oid, object_id, lo, hi):  # pragma: no cover - compiled
    """Indices of the points inside the box [lo, hi] that are FIXED (or object_id's own when
    object_id >= 0): one pass (numpy's masks over 20k x 3 points cost ~0.3 ms an object)."""
    out = np.empty(p.shape[0], np.int64)
    n = 0
    for i in range(p.shape[0]):
        if not (label[i] == 0 or (object_id >= 0 and oid[i] == object_id)):
            continue
        if lo[0] <= p[i, 0] <= hi[0] and lo[1] <= p[i, 1] <= hi[1] and lo[2] <= p[i, 2] <= hi[2]:
            out[n] = i
            n += 1
    return out[:n]


def _rigid_2d(src: np.ndarray, dst: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(R 2x2, t 2) minimizing sum |R src + t - dst|^2 over planar rotations (Kabsch in 2-D)."""
    cs, cd = src.mean(axis=0), dst.mean(axis=0)
    H = (src - cs).T @ (dst - cd)
    yaw = math.atan2(H[0, 1] - H[1, 0], H[0, 0] + H[1, 1])
    c, s = math.cos(yaw), math.sin(yaw)
    R = np.array([[c, -s], [s, c]])
    return R, cd - R @ cs


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
    #: (time, anchor x, y, known) after every scan: where the object was when, and whether this
    #: scan registered it or a mask saw it (moved_since).
    history: deque = field(default_factory=lambda: deque(maxlen=HISTORY_SCANS))

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
        self.unseen = 0  # object-scans with too few points near the template to register

    def update(self, now_s: float, part: PointPartition, points_odom: np.ndarray) -> int:
        """Register every object's template to this scan, merge what the masks confirmed, label
        the objects' points in `part` (in place); returns the points labelled by tracking."""
        c = self.config
        if not c.enabled:
            return 0
        label, oid, cost = part.label, part.object_id, part.cost
        masked = (label == MOVABLE) & part.in_view & ~part.from_memory
        confirming: dict[int, np.ndarray] = {}
        for k in np.unique(oid[masked]):
            sel = masked & (oid == k)
            if np.count_nonzero(sel) >= c.min_confirm_points:
                confirming[int(k)] = sel
        for k in [k for k, o in self.objects.items() if now_s - o.confirmed_s > c.max_unconfirmed_s
                  and k not in confirming]:
            del self.objects[k]
        added = 0
        followed = {k for k, obj in self.objects.items() if self._register(obj, label, oid, points_odom)}
        for k, sel in confirming.items():
            self._confirm(k, now_s, points_odom[sel], float(cost[sel][0]))
        for k, obj in self.objects.items():
            added += self._label(obj, label, oid, cost, points_odom)
            # Known this scan: registered, or seen by a mask (whose view, if it disagreed, moved the anchor).
            obj.history.append((float(now_s), *obj.anchor, k in followed or k in confirming))
        self.points_tracked += added
        return added

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
        i = max(j for j, h in enumerate(obj.history) if h[0] <= t_s)
        if not all(h[3] for h in list(obj.history)[i + 1:]):
            return None
        return float(np.hypot(*(obj.anchor - np.asarray(obj.history[i][1:3]))))

    def _confirm(self, k: int, now_s: float, points: np.ndarray, cost: float) -> None:
        """Merge a mask's view of object k into its template (registered to this scan already)."""
        c = self.config
        new = _thin(points, c.template_voxel_m, c.max_template_points)
        old = self.objects.get(k) or self._hand_over(k, new)
        anchor = None
        if old is not None and len(old.template):
            anchor = old.anchor
            d, _ = cKDTree(new).query(old.template, distance_upper_bound=2 * c.template_voxel_m)
            extra = old.template[~np.isfinite(d)]
            union = np.concatenate([new, extra]) if len(extra) else new
            if _extent(union) <= max(_extent(new), _extent(old.template)) + c.max_growth_m:
                new = _thin(union, c.template_voxel_m, c.max_template_points)  # a far view's face and a near view's top
            elif len(new) < len(old.template) // 2:
                new = old.template  # a sliver that disagrees (at the image border): keep the object
            else:  # the view disagrees and is substantial (the object moved unseen): take the view
                anchor = None  # (its centre: a jump the history shows as a motion)
        view = _extent(points)
        obj = TrackedObject(k, cost, new, now_s, 0 if old is None else old.tracked_scans,
                            view if old is None else max(view, old.view_extent_m), anchor)
        if old is not None:
            obj.history = old.history
        self.objects[k] = obj

    def _hand_over(self, k: int, new: np.ndarray) -> TrackedObject | None:
        """The tracked object a new mask id is seen on (the mask memory gives a moved object a new
        id when its warped mask no longer matches the fresh one): it leaves the tracker and its
        template goes to k. Most of the new view must lie on its template."""
        c = self.config
        for j, obj in list(self.objects.items()):
            d, _ = cKDTree(obj.template).query(new, distance_upper_bound=2 * c.label_radius_m)
            if np.mean(np.isfinite(d)) >= 0.5:
                self.handovers += 1
                return self.objects.pop(j)
        return None

    def _register(self, obj: TrackedObject, label, oid, points_odom: np.ndarray) -> bool:
        """Move obj's template onto this scan's points (planar ICP); False (the template stays
        where it was) when the scan does not show it or the registration is refused."""
        c = self.config
        tpl = obj.template
        lo = tpl.min(axis=0) - c.search_margin_m
        hi = tpl.max(axis=0) + c.search_margin_m
        cand = _box_candidates(points_odom, label, oid, obj.object_id, lo, hi)
        if len(cand) < c.min_pairs:
            self.unseen += 1
            return False  # not in this scan (occluded, out of range, gone)
        pts = points_odom[cand]
        tree = cKDTree(pts)
        moved = tpl.copy()
        R_total, t_total = np.eye(2), np.zeros(2)
        for _ in range(c.icp_iterations):
            d, j = tree.query(moved, distance_upper_bound=c.max_correspondence_m)
            ok = np.isfinite(d)
            if np.count_nonzero(ok) < c.min_pairs:
                self.lost += 1
                return False
            R, t = _rigid_2d(moved[ok, :2], pts[j[ok], :2])
            moved[:, :2] = moved[:, :2] @ R.T + t
            R_total, t_total = R @ R_total, R @ t_total + t
            if abs(t[0]) + abs(t[1]) < 5e-4 and abs(R[1, 0]) < 5e-4:
                break  # converged (under 0.5 mm and 0.03 degrees)
        centre = tpl[:, :2].mean(axis=0)
        d, _ = tree.query(moved, distance_upper_bound=c.max_correspondence_m)
        inliers = np.isfinite(d)
        # A fit that matched too little of the template (it slid half-way onto something else),
        # or matched it loosely, or jumped farther than an object goes in a scan: refused.
        if (np.linalg.norm(R_total @ centre + t_total - centre) > c.max_step_m
                or np.mean(inliers) < c.min_inlier_fraction
                or float(np.sqrt(np.mean(d[inliers] ** 2))) > c.max_rms_m):
            self.lost += 1
            return False
        self.registrations += 1
        obj.template = moved
        obj.anchor = R_total @ obj.anchor + t_total
        obj.tracked_scans += 1
        return True

    def _label(self, obj: TrackedObject, label, oid, cost, points_odom: np.ndarray) -> int:
        """Fixed points within label_radius_m of obj's template become obj's."""
        c = self.config
        tpl = obj.template
        lo = tpl.min(axis=0) - c.label_radius_m
        hi = tpl.max(axis=0) + c.label_radius_m
        cand = _box_candidates(points_odom, label, oid, -1, lo, hi)
        if not len(cand):
            return 0
        d, _ = cKDTree(tpl).query(points_odom[cand], distance_upper_bound=c.label_radius_m)
        take = cand[np.isfinite(d)]
        label[take], oid[take], cost[take] = MOVABLE, obj.object_id, obj.cost
        if c.max_spread_m > 0.0 and take.size:
            grown = np.concatenate([tpl, points_odom[take]])
            if _extent(grown) <= obj.view_extent_m + c.max_spread_m:
                obj.template = _thin(grown, c.template_voxel_m, c.max_template_points)
        return int(take.size)


__all__ = ["ObjectTracker", "TrackedObject", "TrackingConfig"]
