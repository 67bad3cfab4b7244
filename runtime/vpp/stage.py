"""The VPP stage: DCT Algorithm 1 lines 3-13 for one tick, glued from the parts beside it.

Per tick, in this order:
1. answers the backend runner delivered by now (models/vlm/runner.py) are reconciled into the
   mask memory (Phase II, eq. 5), each with the newest scan at its request, placed in the
   capture camera's frame through the odom frame, for the plane of every fresh mask;
2. a new camera image is sent to the backend when the trigger rule says so (line 3: moved more
   than d_thres, or t_thres passed, or the memory is empty) and no request is in flight; the
   camera pose at capture is the pose of the tick that received the image (at 20 Hz, at most
   one period late: 5 cm at 1 m/s);
3. a new scan is partitioned (Phase III, partition.py) against the memory's masks warped to the
   camera pose now (Phase I, homography.py; per pixel: each point's pixel is looked up through
   the warp in the capture mask, no warped image is made, see MaskMemory.lookup): only objects
   the backend called movable with a contact cost below `never_touch_cost` become P_mov;
   everything else, and every point the camera does not see and the label memory does not
   know, stays P_fix.

Cost per scan (issue 13 budget: 3 ms p99 at 20k points and 8 masks, one core): `dct bench vpp`.

The stage never waits: the runner answers beside the tick (lockstep: at a fixed simulated
latency, `settle` is the simulator's barrier; real time: when the backend answers, or an error
after its timeout). A backend that is down or slow means no new masks: the memory ages out and
the points fall back to P_fix (issue 13).

Frames: poses are 4x4 homogeneous transforms; T_a_b maps b coordinates to a. The camera frame
is the optical frame (z forward, x right, y down), as the robot description mounts it.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numba import njit
from pydantic import BaseModel, ConfigDict, Field

from calibration.camera_model import CameraModel
from models.vlm.interface import VlmRequest
from models.vlm.runner import BackendRunner, BackendRunnerConfig
from runtime.sensor_data import CameraImage, LidarScan
from runtime.vpp.homography import lookup_supported, pixel_rays
from runtime.vpp.mask_memory import MaskMemory, MaskMemoryConfig, MaskMemoryError, ReconcileResult
from runtime.vpp.partition import FIXED, MOVABLE, PartitionConfig, PointPartition, PointPartitioner, _transform

DEFAULT_PROMPT = (
    "A small ground robot must drive to its goal through this scene. For each marked object, say "
    "whether the robot may push it or brush past it, and how costly contact would be."
)


class VppConfig(BaseModel):
    """The VPP stage's settings (controller config `vpp:`)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    prompt: str = Field(DEFAULT_PROMPT, min_length=1, max_length=2000)
    #: A movable object with at least this contact cost stays in P_fix (IMPACT: 8+ is fragile).
    never_touch_cost: float = Field(8.0, ge=0.0, le=10.0)
    #: A warped mask grown to more than this many times its captured area (the camera came close
    #: to the object's plane, or the object moved: a pushed box stays in front of the robot while
    #: the warp assumes it stood still) is not trusted: its points stay P_fix. Without it a mask
    #: swells over the whole image and gates fixed objects as movable.
    max_mask_growth: float = Field(2.5, gt=1.0, le=100.0)
    #: Movable objects tracked by their points between scans (a pushed box leaves its mask: the
    #: warp assumes it stands still): a point the masks leave fixed, within track_radius_m of the
    #: previous scan's points of a movable object (odom frame; a 10 Hz scan at 0.5 m/s moves 5 cm),
    #: takes that object's label (the parts of it the camera does not see join it too), for at
    #: most track_max_s after a mask last labelled the object, and only while the object's points
    #: span no more than the extent they had then plus track_extent_margin_m (a fixed structure
    #: the object touches would stretch it: then nothing is added).
    track_radius_m: float = Field(0.08, ge=0.0, le=0.5)
    track_max_s: float = Field(8.0, ge=0.0, le=60.0)
    track_extent_margin_m: float = Field(0.25, ge=0.0, le=5.0)
    #: The controller waits for the first answer (mode dct); after this long without one it drives
    #: on what it has (every point P_fix), and says so.
    first_answer_timeout_s: float = Field(5.0, gt=0.0, le=120.0)
    memory: MaskMemoryConfig = MaskMemoryConfig()
    partition: PartitionConfig = PartitionConfig()
    runner: BackendRunnerConfig = BackendRunnerConfig()


@njit(cache=True, nogil=True)
def _id_boxes(p, label, oid, in_view, from_memory):  # pragma: no cover - compiled
    """(ids, lo, hi, masked): the sorted object ids of the movable points, each id's axis-aligned
    box, and whether a mask labelled some of its points this scan (in view, not from memory)."""
    n = p.shape[0]
    k = 0
    for i in range(n):
        if label[i] == 1:
            k += 1
    ids = np.empty(k, np.int64)
    k = 0
    for i in range(n):
        if label[i] == 1:
            ids[k] = oid[i]
            k += 1
    uniq = np.unique(ids)
    lo = np.full((uniq.shape[0], 3), np.inf)
    hi = np.full((uniq.shape[0], 3), -np.inf)
    masked = np.zeros(uniq.shape[0], np.bool_)
    for i in range(n):
        if label[i] == 1:
            j = np.searchsorted(uniq, oid[i])
            if in_view[i] and not from_memory[i]:
                masked[j] = True
            for a in range(3):
                lo[j, a] = min(lo[j, a], p[i, a])
                hi[j, a] = max(hi[j, a], p[i, a])
    return uniq, lo, hi, masked


@njit(cache=True, nogil=True)
def _movable_points(p, label, oid, cost):  # pragma: no cover - compiled
    """The movable points (their odom positions, ids, costs) and their box (lo, hi)."""
    k = 0
    for i in range(p.shape[0]):
        if label[i] == 1:
            k += 1
    pts = np.empty((k, 3))
    ids = np.empty(k, oid.dtype)
    cst = np.empty(k, cost.dtype)
    lo = np.full(3, np.inf)
    hi = np.full(3, -np.inf)
    k = 0
    for i in range(p.shape[0]):
        if label[i] == 1:
            for a in range(3):
                pts[k, a] = p[i, a]
                lo[a] = min(lo[a], p[i, a])
                hi[a] = max(hi[a], p[i, a])
            ids[k] = oid[i]
            cst[k] = cost[i]
            k += 1
    return pts, ids, cst, lo, hi


@njit(cache=True, nogil=True)
def _track_kernel(p, label, oid, cost, prev_pts, prev_ids, prev_costs, lo, hi, r, ids_now, lo_now, hi_now,
                  conf_ids, conf_since, conf_ext, now, max_s, margin):  # pragma: no cover - compiled
    """VppStage._track's search and takeover (its docstring); returns the points taken.

    Candidates: fixed points in the previous movable points' box grown by r. Each takes the
    object of its nearest previous movable point closer than r (a grid of cells of side r over
    the previous points near the candidates: the nearest within r is in one of the 27 cells
    around the candidate's), grouped per object; a group is taken when its object was confirmed
    by a mask within max_s and the object's points now plus the group span at most its extent
    then plus margin (box diagonals), at the cost of the group's first candidate's match."""
    n = p.shape[0]
    cand = np.empty(n, np.int64)
    nc = 0
    qlo = np.full(3, np.inf)
    qhi = np.full(3, -np.inf)
    for i in range(n):
        if label[i] == 0 and lo[0] - r <= p[i, 0] <= hi[0] + r and lo[1] - r <= p[i, 1] <= hi[1] + r \
                and lo[2] - r <= p[i, 2] <= hi[2] + r:
            cand[nc] = i
            nc += 1
            for a in range(3):
                qlo[a] = min(qlo[a], p[i, a])
                qhi[a] = max(qhi[a], p[i, a])
    if nc == 0:
        return 0
    # grid over the previous points that can be within r of a candidate
    P = prev_pts.shape[0]
    keys = np.empty(P, np.int64)
    idx = np.empty(P, np.int64)
    k = 0
    inv = 1.0 / r
    for j in range(P):
        x, y, z = prev_pts[j, 0], prev_pts[j, 1], prev_pts[j, 2]
        if qlo[0] - r <= x <= qhi[0] + r and qlo[1] - r <= y <= qhi[1] + r and qlo[2] - r <= z <= qhi[2] + r:
            cx = int(math.floor((x - qlo[0]) * inv)) + 1
            cy = int(math.floor((y - qlo[1]) * inv)) + 1
            cz = int(math.floor((z - qlo[2]) * inv)) + 1
            keys[k] = (np.int64(cx) << 42) | (np.int64(cy) << 21) | np.int64(cz)
            idx[k] = j
            k += 1
    if k == 0:
        return 0
    order = np.argsort(keys[:k])
    skeys = keys[:k][order]
    sidx = idx[:k][order]
    r2 = r * r
    hit_i = np.empty(nc, np.int64)
    hit_j = np.empty(nc, np.int64)
    nh = 0
    for a in range(nc):
        i = cand[a]
        cx = int(math.floor((p[i, 0] - qlo[0]) * inv)) + 1
        cy = int(math.floor((p[i, 1] - qlo[1]) * inv)) + 1
        cz = int(math.floor((p[i, 2] - qlo[2]) * inv)) + 1
        best = -1
        bd = r2
        for dx in range(-1, 2):
            for dy in range(-1, 2):
                for dz in range(-1, 2):
                    key = (np.int64(cx + dx) << 42) | (np.int64(cy + dy) << 21) | np.int64(cz + dz)
                    b = np.searchsorted(skeys, key)
                    while b < k and skeys[b] == key:
                        j = sidx[b]
                        d0 = p[i, 0] - prev_pts[j, 0]
                        d1 = p[i, 1] - prev_pts[j, 1]
                        d2 = p[i, 2] - prev_pts[j, 2]
                        d = d0 * d0 + d1 * d1 + d2 * d2
                        if d < bd or (d == bd and best >= 0 and j < best):
                            bd = d
                            best = j
                        b += 1
        if best >= 0:
            hit_i[nh] = i
            hit_j[nh] = best
            nh += 1
    if nh == 0:
        return 0
    gids = np.unique(prev_ids[hit_j[:nh]])
    G = gids.shape[0]
    glo = np.full((G, 3), np.inf)
    ghi = np.full((G, 3), -np.inf)
    gfirst = np.full(G, -1, np.int64)
    for a in range(nh):
        g = np.searchsorted(gids, prev_ids[hit_j[a]])
        if gfirst[g] < 0:
            gfirst[g] = hit_j[a]
        for c in range(3):
            glo[g, c] = min(glo[g, c], p[hit_i[a], c])
            ghi[g, c] = max(ghi[g, c], p[hit_i[a], c])
    ok = np.zeros(G, np.bool_)
    for g in range(G):
        kid = gids[g]
        t = np.searchsorted(ids_now, kid)
        if t < ids_now.shape[0] and ids_now[t] == kid:  # the object's points this scan, with the group
            for c in range(3):
                glo[g, c] = min(glo[g, c], lo_now[t, c])
                ghi[g, c] = max(ghi[g, c], hi_now[t, c])
        since = -np.inf
        ext = 0.0
        t = np.searchsorted(conf_ids, kid)
        if t < conf_ids.shape[0] and conf_ids[t] == kid:
            since = conf_since[t]
            ext = conf_ext[t]
        e2 = 0.0
        for c in range(3):
            e2 += (ghi[g, c] - glo[g, c]) ** 2
        ok[g] = now - since <= max_s and math.sqrt(e2) <= ext + margin
    taken = 0
    for a in range(nh):
        g = np.searchsorted(gids, prev_ids[hit_j[a]])
        if ok[g]:
            i = hit_i[a]
            label[i] = 1
            oid[i] = gids[g]
            cost[i] = prev_costs[gfirst[g]]
            taken += 1
    return taken


def pose_matrix(x_m: float, y_m: float, yaw_rad: float) -> np.ndarray:
    """T_odom_base (4x4) of a planar pose."""
    c, s = math.cos(yaw_rad), math.sin(yaw_rad)
    T = np.eye(4)
    T[:2, :2] = [[c, -s], [s, c]]
    T[0, 3], T[1, 3] = x_m, y_m
    return T


@dataclass(frozen=True)
class VppFrame:
    """One partitioned scan: per point of the scan, whether it stays fixed (P_fix), and the
    partition itself (labels, object ids, costs)."""

    stamp_s: float
    partition: PointPartition
    masks_used: int  # warped movable masks the scan was gated against

    @property
    def fixed(self) -> np.ndarray:
        """(N,) bool: the scan points that constrain the planner (ground and unseen included:
        the obstacle extractor drops the ground by height itself)."""
        return self.partition.label != MOVABLE

    @property
    def movable_count(self) -> int:
        return int(np.count_nonzero(self.partition.label == MOVABLE))


class VppStage:
    def __init__(self, config: VppConfig, camera: CameraModel, T_base_cam: np.ndarray, T_base_lidar: np.ndarray,
                 runner: BackendRunner) -> None:
        self.config = config
        self.camera = camera
        self.T_base_cam = np.asarray(T_base_cam, dtype=np.float64)
        self.T_base_lidar = np.asarray(T_base_lidar, dtype=np.float64)
        self.T_cam_lidar = np.linalg.inv(self.T_base_cam) @ self.T_base_lidar
        self.runner = runner
        self.memory = MaskMemory(camera, config.memory)
        self.partitioner = PointPartitioner(config.partition)
        self._per_pixel = lookup_supported(camera)
        if self._per_pixel:
            pixel_rays(camera)  # once per camera (~0.1 s with distortion): here, not in the first tick
        self._points_cam_at: dict[float, np.ndarray] = {}  # request stamp -> scan points, capture camera frame
        self._last_scan_odom: np.ndarray | None = None
        self._image: tuple[CameraImage, np.ndarray] | None = None
        self._first_tick_s: float | None = None
        self.gave_up_waiting = False
        self.images_refused = 0  # images from another camera than the calibrated one (named)
        self._tracked: tuple[np.ndarray, ...] | None = None  # odom points, ids, costs, their box (lo, hi)
        self._confirmed: dict[int, tuple[float, float]] = {}  # object id -> (last masked, its extent then)
        self.points_tracked = 0
        self.last_frame: VppFrame | None = None
        self.last_reconcile: ReconcileResult | None = None
        # Counters (never reset).
        self.requests = 0
        self.answers = 0
        self.failed_answers = 0
        self.rejected_answers = 0  # answers the memory refused (named in last_rejection)
        self.masks_distrusted = 0  # warped masks grown past max_mask_growth (kept out of the gate)
        self.last_rejection: str | None = None
        self.frames = 0
        self._warm_up()

    def _warm_up(self) -> None:
        """Run the tracking kernels once on a tiny frame (numba compiles or loads them from its
        cache on first use: here, at start-up, not in the first tick that tracks)."""
        n = 4
        p = np.array([[1.0, 0.0, 0.0], [1.01, 0.0, 0.0], [1.02, 0.0, 0.0], [3.0, 0.0, 0.0]], np.float32)
        p_odom = _transform(p, np.eye(4))
        for step in range(2):
            label = np.array([1, 1, 0, 0], np.int8)
            part = PointPartition(label, np.array([0, 0, -1, -1], np.int32),
                                  np.array([1.0, 1.0, np.nan, np.nan], np.float32), np.ones(n, bool), np.zeros(n, bool),
                                  0, 0)
            self._track(0.1 * step, part, p_odom)
        self._tracked, self._confirmed, self.points_tracked = None, {}, 0

    def settle(self, t_s: float) -> None:
        """Lockstep barrier (the simulator calls it before time t_s): answers due are ready."""
        self.runner.settle(t_s)

    def close(self) -> None:
        self.runner.close()

    def _check_image(self, image: CameraImage) -> None:
        cam = self.camera
        if (image.width, image.height) != (cam.width_px, cam.height_px) or not np.allclose(image.K, cam.K, atol=1e-6):
            raise ValueError(f"VPP: camera image {image.width}x{image.height} with K {image.K.tolist()} does not "
                             f"match the calibrated camera {cam.width_px}x{cam.height_px} K {cam.K.tolist()}")

    def update(self, now_s: float, pose: tuple[float, float, float], image: CameraImage | None,
               scan: LidarScan | None) -> VppFrame | None:
        """One tick (module docstring); returns the partition of `scan` (None without a scan)."""
        T_odom_base = pose_matrix(*pose)
        T_odom_cam = T_odom_base @ self.T_base_cam
        for answer in self.runner.poll(now_s):
            self.answers += 1
            self.failed_answers += int(answer.error is not None)
            points_cam = self._points_cam_at.pop(float(answer.stamp_s), None)
            try:
                self.last_reconcile = self.memory.reconcile(answer, prompt=self.config.prompt,
                                                            points_cam=points_cam, now_s=now_s)
            except MaskMemoryError as exc:  # the memory stays as it was; the answer is named, not raised
                self.rejected_answers += 1
                self.last_rejection = str(exc)
        if image is not None:
            try:
                self._check_image(image)
                self._image = (image, T_odom_cam)  # the newest image and the camera pose that received it
            except ValueError as exc:  # counted and named; the tick goes on with what it has
                self.images_refused += 1
                self.last_rejection = str(exc)
        if scan is None:
            self._maybe_ask(now_s)
            return None
        masks, use = self._masks_now(now_s, T_odom_cam)
        part = self.partitioner.partition(
            scan.points_m, self.T_cam_lidar, self.camera, masks, [e.object_id for e in use],
            [e.contact_cost for e in use], T_base_lidar=self.T_base_lidar,
            T_odom_lidar=T_odom_base @ self.T_base_lidar, stamp_s=scan.stamp_s,
        )
        p_odom = _transform(np.ascontiguousarray(scan.points_m), T_odom_base @ self.T_base_lidar)  # numba: 5x numpy's
        self._track(now_s, part, p_odom)
        self._last_scan_odom = p_odom
        self._maybe_ask(now_s)
        self.frames += 1
        self.last_frame = VppFrame(float(scan.stamp_s), part, len(use))
        return self.last_frame

    def _gates(self, entry, warped_px: float, captured_px: float) -> bool:
        """Does this entry's warped mask gate points this scan? Movable, below never_touch_cost,
        not empty, and not grown past max_mask_growth times its captured area (counted, then
        distrusted)."""
        if not (entry.movable and entry.contact_cost < self.config.never_touch_cost and warped_px > 0):
            return False
        if warped_px > self.config.max_mask_growth * captured_px:
            self.masks_distrusted += 1
            return False
        return True

    def _masks_now(self, now_s: float, T_odom_cam: np.ndarray):
        """Phase I for this scan: (masks for the partition, their entries). The memory's masks are
        carried to the camera pose now per pixel (MaskMemory.lookup: a WarpLookup, looked up by
        the partition only at the points' pixels); a camera whose distortion the per-pixel warp
        does not implement (the 14-coefficient tilted model) gets full-image warps (propagate).
        The growth test takes the warped area from the lookup (exact for a warped mask whose
        bounding box has at most homography.AREA_SAMPLES pixels, else estimated on a grid)."""
        if self._per_pixel:
            entries, lk = self.memory.lookup(now_s, T_odom_cam)
            px = self.memory.mask_px()
            use = [k for k, e in enumerate(entries) if self._gates(e, float(lk.area_px[k]), float(px[k]))]
            return lk.select(use), [entries[k] for k in use]
        warped = [w for w in self.memory.propagate(now_s, T_odom_cam)
                  if self._gates(w.entry, np.count_nonzero(w.mask), np.count_nonzero(w.entry.mask))]
        h, w = self.camera.height_px, self.camera.width_px
        masks = np.stack([m.mask for m in warped]) if warped else np.zeros((0, h, w), bool)
        return masks, [m.entry for m in warped]

    def _track(self, now_s: float, part: PointPartition, p_odom: np.ndarray) -> None:
        """Carry movable labels to the points near the previous scan's movable points (see
        VppConfig.track_*); updates `part`'s arrays in place. p_odom: the scan in the odom frame.

        Per-point work in numba (_id_boxes, _track_kernel: every object's box in one pass, as an
        extent is a box diagonal; the nearest previous movable point from a grid of cells of side
        track_radius_m rather than a k-d tree): the labels of the per-object loop it replaced.
        """
        c = self.config
        r = c.track_radius_m
        label, oid, cost = part.label, part.object_id, part.cost
        ids_now, lo_now, hi_now, masked = _id_boxes(p_odom, label, oid, part.in_view, part.from_memory)
        ext_now = np.sqrt(((hi_now - lo_now) ** 2).sum(axis=1))
        for k, e in zip(ids_now[masked].tolist(), ext_now[masked].tolist()):
            self._confirmed[k] = (now_s, e)  # a mask labelled it this scan: confirmed now, with its extent
        # a confirmation older than track_max_s allows nothing (as none at all): forget it
        self._confirmed = {k: v for k, v in self._confirmed.items() if now_s - v[0] <= c.track_max_s}
        prev = self._tracked
        if prev is not None and r > 0.0:
            pts, ids, costs, lo, hi = prev
            conf_ids = np.array(sorted(self._confirmed), dtype=np.int64)
            conf = [self._confirmed[k] for k in conf_ids.tolist()]
            since = np.array([x[0] for x in conf], dtype=np.float64)
            extent = np.array([x[1] for x in conf], dtype=np.float64)
            self.points_tracked += int(_track_kernel(
                p_odom, label, oid, cost, pts, ids, costs, lo, hi, float(r), ids_now, lo_now, hi_now,
                conf_ids, since, extent, float(now_s), float(c.track_max_s), float(c.track_extent_margin_m)))
        tracked = _movable_points(p_odom, label, oid, cost)
        self._tracked = tracked if tracked[0].shape[0] else None

    def _maybe_ask(self, now_s: float) -> None:
        """Send the newest image when the trigger rule says so and nothing is in flight; not
        before a scan was seen (a mask without the lidar points at capture has no plane, and the
        rotation-only warp loses it within a few decimetres of travel)."""
        if self._image is None or self._last_scan_odom is None or self.runner.busy:
            return
        image, T_odom_cam = self._image
        if not self.memory.query_due(now_s, T_odom_cam):
            return
        self._image = None
        request = VlmRequest(image=image.pixels, stamp_s=image.stamp_s, camera_pose_odom=T_odom_cam,
                             prompt=self.config.prompt, segmentation=image.segmentation)
        # The newest scan, in the camera frame at capture (the scan was placed in the odom frame
        # with its own pose: the two may be up to a camera period apart).
        T_cam_odom = np.linalg.inv(T_odom_cam)
        self._points_cam_at = {float(image.stamp_s):
                               self._last_scan_odom @ T_cam_odom[:3, :3].T + T_cam_odom[:3, 3]}
        self.runner.submit(request, now_s)
        self.memory.note_query(image.stamp_s, T_odom_cam)
        self.requests += 1

    def ready(self, now_s: float) -> bool:
        """A first answer (or failure) has come back, or first_answer_timeout_s passed since the
        stage's first tick: before that the stage knows nothing the all-fixed partition does not,
        and the controller waits rather than commit to a detour (with no camera images or no
        backend it would wait forever: the timeout ends it, `gave_up_waiting` says so)."""
        if self._first_tick_s is None:
            self._first_tick_s = now_s
        if self.answers > 0:
            return True
        if now_s - self._first_tick_s > self.config.first_answer_timeout_s:
            self.gave_up_waiting = True
            return True
        return False

    def describe(self) -> dict:
        return {
            "requests": self.requests, "answers": self.answers, "failed_answers": self.failed_answers,
            "rejected_answers": self.rejected_answers, "last_rejection": self.last_rejection,
            "masks_distrusted": self.masks_distrusted, "points_tracked": self.points_tracked,
            "images_refused": self.images_refused, "gave_up_waiting": self.gave_up_waiting,
            "frames": self.frames, "memory_entries": len(self.memory.entries), "runner": self.runner.counters(),
            "last_movable_points": self.last_frame.movable_count if self.last_frame is not None else 0,
        }


__all__ = ["DEFAULT_PROMPT", "VppConfig", "VppFrame", "VppStage", "pose_matrix"]
