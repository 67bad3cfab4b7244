"""PointPartitioner: the partition of one scan after another (runtime/vpp/partition/__init__.py),
with the odom-frame label memory held between them.

Per scan: the checks (inputs.py), one projection pass (projection.py), the mask lookup
(gating.py), the refinement (clustering.py), the assembly of the labels and the label memory
(label_memory.py). Work arrays are kept between scans (PointPartitioner._buffers); the outputs
are fresh per scan. Every kernel runs once at construction (_warm_up), so that numba's compile
or cache load happens at start-up, not in the first tick that needs it.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import numpy as np

from calibration.camera_model import CameraModel
from runtime.vpp.homography.kernels import MaskCrops, WarpTables
from runtime.vpp.homography.lookup import WarpLookup, warp_lookup
from runtime.vpp.homography.plane import Plane
from runtime.vpp.partition.clustering import HALF, cell_keys, refine
from runtime.vpp.partition.config import PartitionConfig
from runtime.vpp.partition.gating import assemble, mask_lookup, mask_lookup_warp, union_box
from runtime.vpp.partition.inputs import (MAX_MASKS, check_ids_costs, check_points, check_transform, fail,
                                          stack_masks)
from runtime.vpp.partition.label_memory import LabelMemory, odom_keys
from runtime.vpp.partition.labels import PointPartition
from runtime.vpp.partition.projection import (EYE4, NO_BOX, NO_PODOM, NO_RAYS, NO_UV, mark_ground, project_scan,
                                              seen_pixels, transform)

#: The warp tables of the kernels when the masks are bitmaps (typed placeholders, never read).
_NO_WARP = WarpTables(MaskCrops(np.zeros(1, np.bool_), np.zeros(1, np.int64), np.zeros((0, 4), np.int64)),
                      np.zeros(0, np.int64), np.zeros((0, 3, 3)), np.zeros((0, 2, 3)), np.zeros((0, 4), np.int64),
                      np.zeros((1, 1, 2)))


@dataclass
class _Scan:
    """One partition call's checked inputs, its work arrays (PointPartitioner._buffers) and the
    outputs filled on the way (in_view; p_odom, the scan in the odom frame, with the memory)."""

    p: np.ndarray
    T: np.ndarray
    camera: CameraModel
    masks: np.ndarray  # (M, H, W) bool; an (M, 1, 1) placeholder when lk is set
    lk: WarpLookup | None
    ids: np.ndarray
    costs: np.ndarray
    Tb: np.ndarray
    has_base: bool
    To: np.ndarray | None  # T_odom_lidar; None: no label memory this scan
    stamp_s: float
    wk: dict
    in_view: np.ndarray
    p_odom: np.ndarray


class PointPartitioner:
    """Phase III for a stream of scans; holds the odom-frame label memory between them."""

    def __init__(self, config: PartitionConfig | None = None) -> None:
        self.config = config or PartitionConfig()
        c = self.config
        self.memory = LabelMemory(c.memory_voxel_m, c.memory_max_age_s, c.memory_initial_slots)
        self.last_points_odom: np.ndarray | None = None
        self._work: dict = {"cap": -1}
        self._rigid: dict = {}  # transforms that passed check_transform
        self._ids_costs: tuple | None = None  # (key, checked ids, costs) of the last call
        self._warm_up()

    def _buffers(self, n: int) -> dict:
        """Work arrays of at least n points, reused between scans (no allocation in the tick; a
        scan of another size takes views, a bigger one grows them by a quarter). None of them is
        returned: the partition's outputs are fresh arrays per scan."""
        w = self._work
        if w["cap"] < n:
            cap = max(n, int(1.25 * w["cap"]))
            w.update(cap=cap, ground=np.empty(cap, np.bool_), seen=np.empty(cap, np.bool_),
                     pix=np.empty((cap, 2), np.int64), midx=np.empty(cap, np.int32), keys=np.empty(cap, np.int64),
                     p_cam=np.empty((cap, 3)), cand=np.empty(cap + 1, np.int64), ray=np.empty((cap + 1, 2)),
                     seen_rows=np.empty(cap + 1, np.int64))
        return {k: v[:n + 1] if k in ("cand", "ray", "seen_rows") else v[:n] for k, v in w.items() if k != "cap"}

    def _ids_and_costs(self, object_ids, costs, m: int) -> tuple[np.ndarray, np.ndarray]:
        """check_ids_costs, remembered for the same ids and costs as the last call (the stage
        passes the same few masks scan after scan)."""
        a = np.asarray(object_ids)
        b = np.asarray(costs)
        if a.dtype.kind not in "iu" or b.dtype.kind not in "fiu":  # (bytes of objects say nothing)
            return check_ids_costs(object_ids, costs, m)
        key = (m, a.dtype.str, a.shape, a.tobytes(), b.dtype.str, b.shape, b.tobytes())
        if self._ids_costs is not None and self._ids_costs[0] == key:
            return self._ids_costs[1], self._ids_costs[2]
        ids, cst = check_ids_costs(object_ids, costs, m)
        self._ids_costs = (key, ids, cst)
        return ids, cst

    def _warm_up(self) -> None:
        """Run every kernel once on a tiny frame (compile or cache load at start-up). A scan's
        points are read-only (LidarScan), and so may be a caller's masks: numba compiles another
        signature for them, warmed up too (docs/decisions/vpp-compiled-kernels.md; the transforms
        are copied by check_transform, one signature whatever the caller's)."""
        memory = self.memory
        self.memory = LabelMemory(1.0, 1.0, 64)
        try:
            cam = CameraModel(np.array([[4.0, 0, 3.5], [0, 4.0, 3.5], [0, 0, 1]]), np.zeros(5), 8, 8)
            pts = np.array([[0, 0, 2.0], [0.01, 0, 2.0], [0, 0, -2.0], [0, 0.5, 2.0]], np.float32)
            ro = pts.copy()
            ro.flags.writeable = False
            masks = np.zeros((1, 8, 8), bool)
            masks[0, 3:5, 3:5] = True
            masks_ro = masks.copy()
            masks_ro.flags.writeable = False
            for p in (pts, ro):
                for m in (masks, masks_ro):
                    self.partition(p, np.eye(4), cam, m, [0], [1.0], T_base_lidar=np.eye(4), T_odom_lidar=np.eye(4),
                                   stamp_s=0.0)
            for dist in (np.zeros(5), np.array([-0.05, 0.01, 0.0, 0.0, 0.0])):  # the per-pixel warp path
                wcam = CameraModel(cam.K, dist, 8, 8)
                lk = warp_lookup(wcam, masks, np.eye(4)[None], [Plane(np.array([0.0, 0.0, 1.0]), 2.0)], np.eye(4))
                for p in (pts, ro):
                    self.partition(p, np.eye(4), wcam, lk, [0], [1.0], T_base_lidar=np.eye(4))
            self.memory._rebuild(0.0, 0)
        finally:
            self.memory = memory

    def partition(
        self,
        points_lidar: np.ndarray,
        T_cam_lidar: np.ndarray,
        camera: CameraModel,
        masks: np.ndarray | Sequence[np.ndarray] | WarpLookup,
        object_ids: Sequence[int] | np.ndarray,
        costs: Sequence[float] | np.ndarray,
        *,
        T_base_lidar: np.ndarray | None = None,
        ignore: np.ndarray | None = None,
        T_odom_lidar: np.ndarray | None = None,
        stamp_s: float | None = None,
    ) -> PointPartition:
        """Label every point of one scan (runtime/vpp/partition/__init__.py).

        points_lidar: (N, 3) float, lidar frame. T_cam_lidar: 4x4, p_cam = T p_lidar. masks:
        (M, H, W) bool (or a list of (H, W)), H x W the camera's image size, or a WarpLookup
        (runtime/vpp/homography/lookup.py: capture masks looked up through their warp at each
        point's pixel, the stage's per-scan path: no warped image is made); object_ids (M,)
        distinct ints >= 0; costs (M,) in [0, 10]. Ground: points with z below
        config.ground_max_z_m after T_base_lidar (skipped without it), plus `ignore` (N,) bool.
        Memory: with T_odom_lidar (4x4, the lidar pose at the scan) and stamp_s, unseen points
        read their voxel's label and seen ones write theirs; without them unseen points are fixed.
        """
        s = self._checked(points_lidar, T_cam_lidar, camera, masks, object_ids, costs, T_base_lidar=T_base_lidar,
                          ignore=ignore, T_odom_lidar=T_odom_lidar, stamp_s=stamp_s)
        (nc, ns), p_cam, keys_done = self._project(s)
        midx, removed, added = self._gate(s, (nc, ns), p_cam)
        n = s.p.shape[0]
        label = np.empty(n, np.int8)
        object_id = np.empty(n, np.int32)
        cost = np.empty(n, np.float32)
        assemble(s.wk["ground"], midx, s.ids, s.costs, label, object_id, cost)
        from_memory = np.zeros(n, bool)
        if s.To is not None:
            if not keys_done:
                odom_keys(s.p, s.To, 1.0 / self.memory.voxel_m, s.wk["ground"], s.wk["keys"])  # EMPTY for the ground
            self.memory.read_keys(s.wk["keys"], s.in_view, False, s.stamp_s, (label, object_id, cost, from_memory))
            self.memory.write_keys(s.wk["keys"], s.wk["seen"], label, object_id, cost, s.stamp_s)
        #: The last scan in the odom frame ((N, 3), None without T_odom_lidar): the stage's tracker reads it.
        self.last_points_odom = s.p_odom if s.To is not None else None
        return PointPartition(label, object_id, cost, s.in_view, from_memory, int(removed), int(added))

    def _checked_masks(self, masks, camera: CameraModel) -> tuple[np.ndarray, WarpLookup | None]:
        """(masks (M, H, W) bool, None), or for a WarpLookup ((M, 1, 1) placeholder, the lookup)."""
        if not isinstance(masks, WarpLookup):
            return stack_masks(masks, camera), None
        lk = masks
        if lk.rays.shape[:2] != (camera.height_px, camera.width_px):
            raise fail("masks", f"warp lookup for a {lk.rays.shape[1]}x{lk.rays.shape[0]} image, the camera is "
                                f"{camera.width_px}x{camera.height_px}")
        if len(lk) > MAX_MASKS:
            raise fail("masks", f"at most {MAX_MASKS} masks, got {len(lk)}")
        return np.zeros((len(lk), 1, 1), bool), lk  # placeholder: the kernels read the lookup

    def _checked(self, points_lidar, T_cam_lidar, camera, masks, object_ids, costs, *, T_base_lidar, ignore,
                 T_odom_lidar, stamp_s) -> _Scan:
        """partition()'s inputs checked (PartitionInputError names the first bad one), with the
        ground marked from `ignore`."""
        p = check_points(points_lidar, "points_lidar")
        T = check_transform(T_cam_lidar, "T_cam_lidar", self._rigid)
        if not isinstance(camera, CameraModel):
            raise fail("camera", f"must be a CameraModel, got {type(camera).__name__}")
        m, lk = self._checked_masks(masks, camera)
        ids, cst = self._ids_and_costs(object_ids, costs, m.shape[0])
        n = p.shape[0]
        wk = self._buffers(n)
        if ignore is not None:
            ig = np.asarray(ignore)
            if ig.shape != (n,) or ig.dtype != np.bool_:
                raise fail("ignore", f"must be ({n},) bool, got shape {ig.shape} dtype {ig.dtype}")
            wk["ground"][:] = ig
        else:
            wk["ground"][:] = False
        has_base = T_base_lidar is not None
        Tb = check_transform(T_base_lidar, "T_base_lidar", self._rigid) if has_base else EYE4
        To = None
        if T_odom_lidar is not None or stamp_s is not None:
            if T_odom_lidar is None or stamp_s is None:
                raise fail("T_odom_lidar" if T_odom_lidar is None else "stamp_s",
                           "the label memory needs both T_odom_lidar and stamp_s")
            To = check_transform(T_odom_lidar, "T_odom_lidar")
            if not math.isfinite(float(stamp_s)):
                raise fail("stamp_s", f"must be finite, got {stamp_s}")
        # in_view and p_odom are returned: fresh arrays per scan (the stage keeps p_odom, the
        # tracker follows objects in it)
        return _Scan(p, T, camera, m, lk, ids, cst, Tb, has_base, To, float(stamp_s) if To is not None else 0.0, wk,
                     np.empty(n, bool), np.empty((n, 3)) if To is not None else NO_PODOM)

    def _project(self, s: _Scan) -> tuple[tuple[int, int], np.ndarray, bool]:
        """Steps 1-2 (projection.py): ((candidates of the warped lookup, seen points), p_cam,
        whether the memory's keys were computed on the way)."""
        c, wk, cam = self.config, s.wk, s.camera
        use_memory = s.To is not None
        W, H = cam.width_px, cam.height_px
        per_point = (wk["ground"], wk["p_cam"], s.in_view, wk["seen"], wk["pix"], wk["seen_rows"])
        candidates = (s.lk.rays if s.lk is not None else NO_RAYS, union_box(s.lk.box) if s.lk is not None else NO_BOX,
                      wk["cand"], wk["ray"])
        if len(cam.dist) <= 12:
            odom = (s.To if use_memory else EYE4, use_memory, 1.0 / self.memory.voxel_m, wk["keys"], s.p_odom)
            counts = project_scan(s.p, (s.T, cam.lens, W, H), (s.Tb, s.has_base, c.ground_max_z_m), odom, per_point,
                              (NO_UV, False), candidates)
            return counts, wk["p_cam"], use_memory
        # the 14-coefficient (tilted) model: cv2 through CameraModel.project
        p_cam = transform(s.p, s.T)
        if s.has_base:
            mark_ground(s.p, s.Tb, c.ground_max_z_m, wk["ground"])
        # project only the points in front (half of a 360-degree scan): same result, half the work
        front = np.flatnonzero(p_cam[:, 2] > 1e-9)
        uv = np.zeros((s.p.shape[0], 2))
        s.in_view[:] = False
        uv[front], s.in_view[front] = cam.project(p_cam[front])
        counts = seen_pixels(uv, W, H, per_point, candidates)
        if use_memory:
            s.p_odom = transform(s.p, s.To)
        return counts, p_cam, False

    def _gate(self, s: _Scan, counts: tuple[int, int], p_cam: np.ndarray) -> tuple[np.ndarray, int, int]:
        """Steps 3-4 (gating.py, clustering.py): (mask index per point, outliers removed, points
        completed). Clustered in the camera frame: a rigid transform keeps distances, and p_cam
        is float64."""
        c, wk = self.config, s.wk
        nc, ns = counts  # candidates of the warped lookup, seen points (wk["seen_rows"][:ns])
        midx = wk["midx"]
        if s.lk is not None:
            order = np.argsort(-s.costs, kind="stable")  # cost descending, index ascending among equals
            hits = mask_lookup_warp(s.lk.tables, s.lk.lens, order, wk["pix"], wk["cand"], wk["ray"], nc, midx)
        else:
            hits = mask_lookup(s.masks, s.costs, wk["pix"], wk["seen"], midx)
        if not (s.masks.shape[0] and hits):
            return midx, 0, 0
        seen_rows = wk["seen_rows"][:ns]
        sk, sp = cell_keys(p_cam, midx, seen_rows, c.eps_cluster_m)
        tables, lens = (s.lk.tables, s.lk.lens) if s.lk is not None else (_NO_WARP, s.camera.lens)
        gate = (s.lk is not None, s.masks, tables, lens, s.costs, c.completion_dilate_px)
        limits = (c.eps_cluster_m, c.n_min, c.max_depth_gap_m if c.max_depth_gap_m is not None else -1.0, c.completion)
        return refine((p_cam, seen_rows, wk["pix"], midx), p_cam[:, 2], (sk, sp), gate, limits, HALF)


def partition_points(points_lidar, T_cam_lidar, camera, masks, object_ids, costs,
                     config: PartitionConfig | None = None, **kwargs) -> PointPartition:
    """One scan without memory (unseen points fixed): PointPartitioner(config).partition(...).
    For tests and tools; a stream should keep one PointPartitioner (it warms up at construction)."""
    return PointPartitioner(config).partition(points_lidar, T_cam_lidar, camera, masks, object_ids, costs, **kwargs)


__all__ = ["PointPartitioner", "partition_points"]
