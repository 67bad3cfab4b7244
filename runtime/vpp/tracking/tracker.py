"""ObjectTracker: the tracked objects' templates, and per scan their registration, confirmation,
plausibility check and labelling (runtime/vpp/tracking/__init__.py), driving the compiled
kernels beside it (registration.py, templates.py, labelling.py, scan_select.py)."""
from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, field

import numpy as np

from runtime.common.spatial_grid import near_any
from runtime.vpp.partition.labels import FIXED, MOVABLE, PointPartition
from runtime.vpp.tracking.config import TrackingConfig
from runtime.vpp.tracking.geometry import each_inside_one, extent, stacked_bounds, thin, view_against_template
from runtime.vpp.tracking.labelling import take_all
from runtime.vpp.tracking.registration import icp_all
from runtime.vpp.tracking.scan_select import group_masked, in_boxes
from runtime.vpp.tracking.templates import confirm_all, merge_view, spread_all

#: An object that moved less than this between two instants counts as still (moved_objects: the
#: anchor jitters by a few centimetres between scans).
MIN_MOTION_M = 0.05
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
    #: yaws): its own frame, in which its size is measured (geometry.extent_nb).
    yaw: float = 0.0
    #: (time, anchor x, y, known) after every scan: where the object was when, and whether this
    #: scan registered it or a mask saw it (moved_since).
    history: deque = field(default_factory=lambda: deque(maxlen=HISTORY_SCANS))
    #: The time of the newest scan in history that did not know where the object was.
    last_unknown_s: float = -math.inf
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
        #: The last stack of templates (_stack): (the objects' template arrays, points, offsets).
        self._stacked: tuple | None = None
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
        spread_all(pts, (np.zeros(1, np.int64), np.array([0, 1])), (face, np.array([0, len(face)]), np.zeros(1)),
                   np.ones(1), (float(c.max_spread_m), float(c.template_voxel_m), int(c.max_template_points)))
        view_against_template(face, np.arange(len(face)), face, 0.1)  # the plausibility test's: a few confirmations on
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
        ids, starts, idx = group_masked(label, part.in_view, part.from_memory, oid)
        confirming: dict[int, np.ndarray] = {}
        for k, (a, b) in sorted(zip(ids.tolist(), zip(starts[:-1].tolist(), starts[1:].tolist()))):
            if b - a >= c.min_confirm_points and k not in skip:
                confirming[k] = idx[a:b]  # ascending point indices
        for k in [k for k, o in self.objects.items() if now_s - o.confirmed_s > c.max_unconfirmed_s
                  and k not in confirming]:
            del self.objects[k]
        added = 0
        near, boxes = self._near(label, points_odom, c.search_margin_m)
        followed = self._register_all(label, oid, cost, near, points_odom)
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
        if boxes is None or not each_inside_one(lab[0], lab[1], boxes[0], boxes[1]):
            near, _ = self._near(label, points_odom, reach)
        added = self._label_all(label, oid, cost, near, points_odom)
        for k, obj in self.objects.items():
            # Known this scan: registered, or seen by a mask (whose view, if it disagreed, moved the anchor).
            known = k in followed or k in confirming
            obj.history.append((float(now_s), *obj.anchor, known))
            if not known:
                obj.last_unknown_s = float(now_s)
        self.points_tracked += added
        return added

    def _implausible_views(self, now_s: float, confirming: dict[int, np.ndarray], followed: set[int],
                           points_odom: np.ndarray) -> list[int]:
        """The objects whose mask view this scan cannot be them: the object was known (registered
        this scan, or registered or seen within max_unknown_s) and the view's centre lies
        farther from the template's than half their two footprints' diagonals and max_step_m
        together (two views of one object have their centres on its footprint), once the template
        has min_confirmations views. A mask's view can be a strip of the wall behind the object
        (the refinement may take a wall that outnumbers the object in its mask for the object);
        taken, it would make the wall touchable (docs/decisions/vpp-tracking.md)."""
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
            vx, vy, tx, ty, fv, ft = view_against_template(points_odom, sel, obj.template, obj.yaw)
            d = float(np.hypot(vx - tx, vy - ty))
            if d > 0.5 * (math.hypot(*ft) + math.hypot(*fv)) + c.max_step_m:
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
        if obj.last_unknown_s > t_s:
            return None  # a scan after t_s that did not know where the object was
        # the newest scan at or before t_s (a binary search: the stage asks for every mask every scan)
        hist = obj.history
        lo, hi = 0, len(hist)
        while lo < hi:
            mid = (lo + hi) // 2
            if hist[mid][0] <= t_s:
                lo = mid + 1
            else:
                hi = mid
        h = hist[lo - 1]
        return float(math.hypot(obj.anchor[0] - h[1], obj.anchor[1] - h[2]))

    def displacement(self, object_id: int, t0_s: float, t1_s: float) -> tuple[float, float] | None:
        """How far (dx, dy in the odom frame, m) object_id's anchor moved from time t0_s to t1_s
        (t0_s <= t1_s; each read at the newest scan at or before it); None under moved_since's
        rule: the tracker did not follow the object the whole time."""
        obj = self.objects.get(int(object_id))
        if obj is None or not obj.history or obj.history[0][0] > t0_s or t1_s < t0_s:
            return None
        at1 = None
        for h in reversed(obj.history):
            if at1 is None and h[0] <= t1_s:
                at1 = h
            if h[0] <= t0_s:
                return (at1[1] - h[1], at1[2] - h[2]) if at1 is not None else None
            if at1 is not None and not h[3]:
                return None  # a scan in between that did not know where the object was
        return None

    def moved_objects(self, since: list[tuple[int, float]], t1_s: float) -> dict[int, tuple[float, float]]:
        """Object id -> displacement to t1_s, for each (object id, t0_s) in since whose object the
        tracker followed all that time and saw move more than MIN_MOTION_M."""
        out = {}
        for object_id, t0_s in since:
            d = self.displacement(object_id, t0_s, t1_s)
            if d is not None and math.hypot(*d) > MIN_MOTION_M:
                out[int(object_id)] = d
        return out

    def _confirm_views(self, now_s: float, confirming: dict[int, np.ndarray], points_odom: np.ndarray,
                       cost: np.ndarray) -> None:
        """_confirm for every object a mask saw this scan, in id order. When each of them already
        has a template (every scan but those after a new answer), all in one compiled call
        (templates.confirm_all: the same arithmetic as _confirm, without its Python per object); a new id
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
        merged, noff, outcome, view_extent = confirm_all(points_odom, (np.concatenate(sels), starts), (tpl, ooff, yaws),
                                                    (float(c.template_voxel_m), int(c.max_template_points),
                                                     float(c.max_growth_m)))
        self._adopt(objs, merged, noff)
        for k, (obj, sel) in enumerate(zip(objs, sels)):
            obj.cost = float(cost[sel[0]])
            obj.confirmed_s = now_s
            obj.confirmations += 1
            obj.view_extent_m = max(float(view_extent[k]), obj.view_extent_m)
            if outcome[k] == 2:  # the view replaced the template: its centre is the new anchor
                obj.anchor = obj.centre()

    def _confirm(self, k: int, now_s: float, points: np.ndarray, cost: float) -> None:
        """Merge a mask's view of object k into its template (registered to this scan already)."""
        c = self.config
        new = thin(points, c.template_voxel_m, c.max_template_points)
        old = self.objects.get(k) or self._hand_over(k, new)
        anchor = None
        if old is not None and len(old.template):
            # a far view's face and a near view's top merge; a sliver that disagrees (at the image
            # border) leaves the template; a substantial view that disagrees (the object moved
            # unseen) replaces it, and its anchor (its centre: a jump the history shows as a motion)
            new, outcome = merge_view(new, old.template, c.template_voxel_m, c.max_template_points, c.max_growth_m,
                                       old.yaw)
            anchor = None if outcome == 2 else old.anchor
        yaw = 0.0 if old is None else old.yaw
        view = extent(points, yaw)
        obj = TrackedObject(k, cost, new, now_s, 0 if old is None else old.tracked_scans,
                            view if old is None else max(view, old.view_extent_m), anchor, yaw)
        if old is not None:
            obj.history = old.history
            obj.last_unknown_s = old.last_unknown_s
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
        objs = [o for o in self.objects.values() if len(o.template)]
        if not objs:
            return np.zeros((0, 3)), np.zeros((0, 3))
        lo, hi = stacked_bounds(*self._stack(objs))
        return lo - grow, hi + grow

    def _near(self, label, points_odom: np.ndarray, grow: float):
        """(indices, boxes): the scan points (not ground) in any tracked object's template box
        grown by `grow` (scan_select.in_boxes), the only points a registration (grow = search_margin_m) or
        a labelling (label_radius_m) can use, found in one pass for all objects; the boxes
        (None without objects)."""
        lo, hi = self._boxes(grow)
        if not len(lo):
            return np.zeros(0, np.int64), None
        return in_boxes(points_odom, label, lo, hi), (lo, hi)

    def _stack(self, objs: list[TrackedObject]) -> tuple[np.ndarray, np.ndarray]:
        """The objects' templates concatenated, and each one's row offsets. The kernels return
        the templates stacked and the objects keep views of that stack (_adopt): while the
        objects' templates are the very arrays of the last stack, it is returned again instead of
        a copy."""
        last = self._stacked
        if last is not None and len(last[0]) == len(objs) and all(o.template is t for o, t in zip(objs, last[0])):
            return last[1], last[2]
        off = np.zeros(len(objs) + 1, np.int64)
        off[1:] = np.cumsum([len(o.template) for o in objs])
        tpl = np.ascontiguousarray(np.concatenate([o.template for o in objs]), dtype=np.float64)
        self._stacked = (tuple(o.template for o in objs), tpl, off)
        return tpl, off

    def _adopt(self, objs: list[TrackedObject], tpl: np.ndarray, off: np.ndarray) -> None:
        """Object k's template becomes rows off[k]:off[k + 1] of the stack tpl (a kernel's
        output), and the stack is the last one (_stack)."""
        for k, obj in enumerate(objs):
            obj.template = tpl[off[k]:off[k + 1]]
        self._stacked = (tuple(o.template for o in objs), tpl, off)

    def _register_all(self, label, oid, cost, near: np.ndarray, points_odom: np.ndarray) -> set[int]:
        """Move every template onto this scan's points (planar ICP, registration.icp: the fixed points and the
        object's own in its box grown by search_margin_m), all objects in one compiled call;
        returns the ids registered. A template stays where it was when the scan does not show
        the object or the registration is refused."""
        c = self.config
        objs = [o for o in self.objects.values() if len(o.template)]
        if not objs:
            return set()
        tpl, off = self._stack(objs)
        ids = np.array([o.object_id for o in objs], np.int64)
        fit = (c.search_margin_m, c.max_correspondence_m, c.icp_iterations, c.min_pairs, c.icp_max_points)
        status, moved, res = icp_all((points_odom, label, oid, cost, near), ids, (tpl, off), fit)
        followed = set()
        for k, obj in enumerate(objs):
            yaw, tx, ty, inlier_fraction, rms, step = res[k].tolist()
            if status[k] == 1:
                self.unseen += 1  # not in this scan (occluded, out of range, gone)
                moved[off[k]:off[k + 1]] = tpl[off[k]:off[k + 1]]  # it stays where it was
                continue
            # Too few pairs; a fit that matched too little of the template (it slid half-way onto
            # something else), or matched it loosely, or jumped farther than an object goes in a
            # scan: refused.
            if status[k] == 2 or step > c.max_step_m or inlier_fraction < c.min_inlier_fraction or rms > c.max_rms_m:
                self.lost += 1
                moved[off[k]:off[k + 1]] = tpl[off[k]:off[k + 1]]
                continue
            self.registrations += 1
            cs, sn = math.cos(yaw), math.sin(yaw)
            ax, ay = float(obj.anchor[0]), float(obj.anchor[1])
            obj.anchor = np.array([cs * ax - sn * ay + tx, sn * ax + cs * ay + ty])
            obj.yaw += yaw
            obj.tracked_scans += 1
            followed.add(obj.object_id)
        self._adopt(objs, moved, off)
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
        taken, toff = take_all((points_odom, label, oid, cost, near), (tpl, off), (ids, costs), c.label_radius_m,
                               origin, 0.0)
        if c.max_spread_m > 0.0 and taken.size:
            view_extents = np.array([o.view_extent_m for o in objs])
            yaws = np.array([o.yaw for o in objs])
            merged, noff, grown = spread_all(points_odom, (taken, toff), (tpl, off, yaws), view_extents,
                                             (float(c.max_spread_m), float(c.template_voxel_m), int(c.max_template_points)))
            self._adopt(objs, merged, noff)  # (an object not grown: its template's values again)
        n = int(taken.size)
        if self._origin is not None and c.behind_m > 0.0:
            tpl, off = self._stack(objs)  # as grown
            behind, _ = take_all((points_odom, label, oid, cost, near), (tpl, off), (ids, costs), c.label_radius_m,
                                 origin, float(c.behind_m))
            n += int(behind.size)
        return n


__all__ = ["HISTORY_SCANS", "ObjectTracker", "TrackedObject"]
