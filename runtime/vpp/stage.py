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
from scipy.spatial import cKDTree

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
def _id_boxes(p, label, oid):  # pragma: no cover - compiled
    """(ids, lo, hi): the sorted object ids of the movable points and each id's axis-aligned box."""
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
    for i in range(n):
        if label[i] == 1:
            j = np.searchsorted(uniq, oid[i])
            for a in range(3):
                lo[j, a] = min(lo[j, a], p[i, a])
                hi[j, a] = max(hi[j, a], p[i, a])
    return uniq, lo, hi


@njit(cache=True, nogil=True)
def _fixed_in_box(p, label, lo, hi):  # pragma: no cover - compiled
    """Indices of the fixed points inside the box [lo, hi]."""
    out = np.empty(p.shape[0], np.int64)
    k = 0
    for i in range(p.shape[0]):
        if label[i] == 0 and lo[0] <= p[i, 0] <= hi[0] and lo[1] <= p[i, 1] <= hi[1] and lo[2] <= p[i, 2] <= hi[2]:
            out[k] = i
            k += 1
    return out[:k]


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

        Per-point work in numba (every object's box in one pass: an extent is a box diagonal),
        and the k-d tree is built only on the previous scan's movable points that can be within
        track_radius_m of a candidate: the same labels as a tree over all of them (a nearest
        neighbour within the radius lies in that box)."""
        c = self.config
        r = c.track_radius_m
        label, oid, cost = part.label, part.object_id, part.cost
        ids_now, lo_now, hi_now = _id_boxes(p_odom, label, oid)
        ext_now = np.sqrt(((hi_now - lo_now) ** 2).sum(axis=1)).tolist()
        row = {int(k): i for i, k in enumerate(ids_now)}
        masked = (label == MOVABLE) & part.in_view & ~part.from_memory  # labelled by a mask this scan
        for k in np.unique(oid[masked]).tolist():  # objects a mask labelled this scan: confirmed now, with their extent
            self._confirmed[k] = (now_s, ext_now[row[k]])
        prev = self._tracked
        if prev is not None and r > 0.0:
            pts, ids, costs, lo, hi = prev
            cand = _fixed_in_box(p_odom, label, lo - r, hi + r)
            if cand.size:
                q = p_odom[cand]
                near = np.flatnonzero(np.all((pts >= q.min(axis=0) - r) & (pts <= q.max(axis=0) + r), axis=1))
                if near.size:
                    d, j = cKDTree(pts[near]).query(q, distance_upper_bound=r)
                    hit = np.isfinite(d)
                    cand, j = cand[hit], near[j[hit]]
                else:
                    cand, j = cand[:0], near
                if cand.size:  # per object (one group of candidates each), all at once
                    gid = ids[j]
                    order = np.argsort(gid, kind="stable")
                    gs, cs, js = gid[order], cand[order], j[order]
                    start = np.flatnonzero(np.r_[True, gs[1:] != gs[:-1]])
                    counts = np.diff(np.r_[start, gs.size])
                    ks = gs[start]
                    tq = p_odom[cs]
                    lo_t, hi_t = np.minimum.reduceat(tq, start, axis=0), np.maximum.reduceat(tq, start, axis=0)
                    at = np.minimum(np.searchsorted(ids_now, ks), max(ids_now.size - 1, 0))
                    has = (ids_now[at] == ks) if ids_now.size else np.zeros(ks.size, bool)
                    # the object's points this scan, with the ones it would take
                    lo_t[has] = np.minimum(lo_t[has], lo_now[at[has]])
                    hi_t[has] = np.maximum(hi_t[has], hi_now[at[has]])
                    conf = [self._confirmed.get(k, (-math.inf, 0.0)) for k in ks.tolist()]
                    since = np.array([x[0] for x in conf])
                    extent = np.array([x[1] for x in conf])
                    ok = (now_s - since <= c.track_max_s) & \
                        (np.sqrt(((hi_t - lo_t) ** 2).sum(axis=1)) <= extent + c.track_extent_margin_m)
                    if ok.any():
                        pt_ok = np.repeat(ok, counts)
                        take = cs[pt_ok]
                        label[take] = MOVABLE
                        oid[take] = gs[pt_ok]
                        cost[take] = np.repeat(costs[js[start]], counts)[pt_ok]  # the first match's cost
                        self.points_tracked += int(take.size)
        mov = np.flatnonzero(label == MOVABLE)
        if mov.size:
            pts = p_odom[mov]
            self._tracked = (pts, oid[mov], cost[mov], pts.min(axis=0), pts.max(axis=0))
        else:
            self._tracked = None

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
