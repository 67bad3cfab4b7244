"""The VPP stage: DCT Algorithm 1 lines 3-13 for one tick, glued from the parts beside it.

Per tick, in this order:
1. answers the backend runner delivered by now (models/vlm/runner.py) are reconciled into the
   mask memory (Phase II, eq. 5). Its image work (the plane of every fresh mask from the newest
   scan at the request, placed in the capture camera's frame through the odom frame; every
   remembered mask warped to the capture pose; the IoU matrix: tens of ms) was done beside the
   tick, in the runner's worker when the answer came (`_prepare`, mask_memory.AnswerPreparer);
   the tick only applies it (MaskMemory.apply: the matching, ids, entries);
2. a new camera image is sent to the backend when the trigger rule says so (line 3: moved more
   than d_thres, or t_thres passed, or the memory is empty) and no request is in flight; the
   camera pose at capture is the caller's `image_pose` (the controller's odometry at the image's
   stamp: OdometryStage.pose_at), else the pose of the tick that received the image (at 20 Hz,
   at most one period late: 5 cm at 1 m/s);
3. a new scan is partitioned (Phase III, runtime/vpp/partition/) against the memory's masks
   warped to the camera pose now (Phase I, runtime/vpp/homography/; per pixel: each point's
   pixel is looked up through the warp in the capture mask, no warped image is made, see
   MaskMemory.lookup): only objects the backend called movable with a contact cost below `never_touch_cost` become P_mov;
   everything else, and every point the camera does not see and the label memory does not
   know, stays P_fix.

Cost per scan (budget: 3 ms p99 at 20k points and 8 masks, one core): `dct bench vpp`.

The stage never waits: the runner answers beside the tick (lockstep: at a fixed simulated
latency, `settle` is the simulator's barrier; real time: when the backend answers, or an error
after its timeout). A backend that is down or slow means no new masks: the memory ages out and
the points fall back to P_fix.

Frames: poses are 4x4 homogeneous transforms; T_a_b maps b coordinates to a. The camera frame
is the optical frame (z forward, x right, y down), as the robot description mounts it.
"""
from __future__ import annotations

import dataclasses
import math
import threading
from dataclasses import dataclass
from typing import Callable

import numpy as np
from scipy.spatial import cKDTree

from calibration.camera_model import CameraModel
from models.vlm.interface import VlmAnswer, VlmRequest
from models.vlm.runner import BackendRunner
from runtime.common.sensor_data import CameraImage, LidarScan
from runtime.vpp.belief import BeliefTable, ContactEvidence, PushResistanceEstimator
from runtime.vpp.config import VppConfig
from runtime.vpp.deformable import DeformableRegions, RobotBox
from runtime.vpp.homography.lookup import lookup_supported, pixel_rays
from runtime.vpp.in_front import in_front, movable_in_front, object_extent_in_base
from runtime.vpp.mask_memory import AnswerPreparer, MaskMemory, MaskMemoryError, PreparedAnswer, ReconcileResult
from runtime.vpp.partition.labels import FIXED, MOVABLE, PointPartition
from runtime.vpp.partition.partitioner import PointPartitioner
from runtime.vpp.tracking.tracker import ObjectTracker


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
                 runner: BackendRunner, resistance: PushResistanceEstimator | None = None,
                 robot_box: RobotBox = RobotBox()) -> None:
        """resistance: the push-resistance estimate from the wheel currents (the robot's; None:
        push outcomes alone update the belief). robot_box: the robot's footprint (a deformable
        object's parts lying on the robot, deformable.py)."""
        self.config = config
        self.camera = camera
        self.T_base_cam = np.asarray(T_base_cam, dtype=np.float64)
        self.T_base_lidar = np.asarray(T_base_lidar, dtype=np.float64)
        self.T_cam_lidar = np.linalg.inv(self.T_base_cam) @ self.T_base_lidar
        self.runner = runner
        self.memory = MaskMemory(camera, config.memory)
        # Phase II's image work beside the tick: its own camera model and warper (not the tick's)
        self._preparer = AnswerPreparer(camera, config.memory)
        self._prepared: dict[float, PreparedAnswer] = {}  # answer stamp -> prepared (worker writes, tick pops)
        self._prepare_lock = threading.Lock()
        # the demoted objects' last entries when each request was sent (snapshot on the tick's
        # thread: what the worker compares does not depend on thread timing)
        self._stones_at: dict[float, tuple] = {}
        self._motions_at: dict[float, dict] = {}  # per request: how far the tracked objects moved
        runner.post = self._prepare
        self.partitioner = PointPartitioner(config.partition)
        self._per_pixel = lookup_supported(camera)
        if self._per_pixel:
            pixel_rays(camera)  # once per camera (~0.1 s with distortion): here, not in the first tick
        self._points_cam_at: dict[float, np.ndarray] = {}  # request stamp -> scan points, capture camera frame
        self._last_scan_odom: np.ndarray | None = None
        self._last_scan_pose = (0.0, 0.0, 0.0)  # the pose the last scan was placed with
        self._image: tuple[CameraImage, np.ndarray] | None = None
        self._first_tick_s: float | None = None
        self.gave_up_waiting = False
        self.images_refused = 0  # images from another camera than the calibrated one (named)
        self.tracker = ObjectTracker(config.tracking)
        self.deformable = DeformableRegions(config.deformable)
        self.robot_box = robot_box
        #: What each touchable object is believed to be (BEACON), and the evidence pushes give it.
        self.belief = BeliefTable(config.belief, config.never_touch_cost)
        self.contact = ContactEvidence(self.belief, resistance, window_s=config.belief_window_s)
        self.belief_demotions = 0  # objects the belief made fixed (heavy or fragile)
        self._now_s = 0.0  # the controller time of the last update
        self._last_scan_lidar: np.ndarray | None = None
        self.last_frame: VppFrame | None = None
        self.last_reconcile: ReconcileResult | None = None
        self.delivered: tuple[VlmAnswer, ...] = ()  # the answers of the last poll that returned any
        # Counters (never reset).
        self.requests = 0
        self.answers = 0
        self.failed_answers = 0
        self.rejected_answers = 0  # answers the memory refused (named in last_rejection)
        self.masks_distrusted = 0  # warped masks of moved (or, untracked, grown) objects kept out of the gate
        self.last_rejection: str | None = None
        self.frames = 0
        self.demotions = 0  # objects demoted to fixed by correcting mode
        self.reidentified = 0  # fresh mask ids found on a demoted object (3-D), demoted too
        self._demoted_xy: np.ndarray | None = None  # odom xy of the demoted objects' points (a tree)
        self._demoted_tree = None

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
               scan: LidarScan | None, image_pose: tuple[float, float, float] | None = None) -> VppFrame | None:
        """One tick (module docstring); returns the partition of `scan` (None without a scan).
        scan: its points where they are at now_s (deskewed), placed with `pose`. image_pose: the
        pose at the image's capture (None: `pose`): the camera pose its masks are warped from
        (docs/decisions/vpp-image-pose.md)."""
        self._now_s = float(now_s)
        if scan is not None:
            self._last_scan_lidar = scan.points_m
        T_odom_base = pose_matrix(*pose)
        T_odom_cam = T_odom_base @ self.T_base_cam
        self._apply_answers(now_s)
        if image is not None:
            try:
                self._check_image(image)
                T_img = T_odom_cam if image_pose is None else pose_matrix(*image_pose) @ self.T_base_cam
                self._image = (image, T_img)  # the newest image and the camera pose at its capture
            except ValueError as exc:  # counted and named; the tick goes on with what it has
                self.images_refused += 1
                self.last_rejection = str(exc)
        if scan is None:
            self._maybe_ask(now_s)
            return None
        part, n_masks = self._partition_scan(now_s, pose, scan, T_odom_base, T_odom_cam)
        for old, new in self.tracker.handover_pairs:  # one object under a new mask id keeps its belief
            self.belief.rename(old, new)
        self.tracker.handover_pairs.clear()
        self._maybe_ask(now_s)
        self.frames += 1
        self.last_frame = VppFrame(float(scan.stamp_s), part, n_masks)
        return self.last_frame

    def _apply_answers(self, now_s: float) -> None:
        """Phase II in the tick: the answers the runner delivered by now, applied to the mask
        memory (prepared beside the tick, or here when they were not)."""
        answers = self.runner.poll(now_s)
        if answers:
            self.delivered = tuple(answers)  # as the runner handed them (a recording keeps them)
        for answer in answers:
            self.answers += 1
            self.failed_answers += int(answer.error is not None)
            stamp = float(answer.stamp_s)
            points_cam = self._points_cam_at.pop(stamp, None)
            prepared = self._prepared.pop(stamp, None)
            if prepared is None or prepared.answer.objects is not answer.objects:
                # not prepared beside the tick (an error answer: nothing to prepare, cheap); the
                # memory's own preparer (the worker's may be in use by an abandoned request)
                prepared = self.memory.preparer.prepare(answer, tuple(self.memory.entries), prompt=self.config.prompt,
                                                        points_cam=points_cam, tombstones=self.memory.tombstones(),
                                                        motions=self._motions_at.get(stamp))
            self._stones_at.pop(stamp, None)
            self._motions_at.pop(stamp, None)
            try:
                self.last_reconcile = self.memory.apply(prepared, now_s)
                for e in self.memory.entries:  # a new object starts from the answer's prior
                    self.belief.observe_answer(e.object_id, e.movable, e.contact_cost, e.confidence, now_s)
                self.belief.forget({e.object_id for e in self.memory.entries}
                                   | self.memory.demoted.keys() | self.tracker.objects.keys())
            except MaskMemoryError as exc:  # the memory stays as it was; the answer is named, not raised
                self.rejected_answers += 1
                self.last_rejection = str(exc)

    def _partition_scan(self, now_s: float, pose, scan: LidarScan, T_odom_base: np.ndarray,
                        T_odom_cam: np.ndarray) -> tuple[PointPartition, int]:
        """Phases I and III for a scan, then the tracker and the deformable regions: (the
        partition, labelled in place by them, the masks it was gated against)."""
        masks, use = self._masks_now(now_s, T_odom_cam)
        part = self.partitioner.partition(
            scan.points_m, self.T_cam_lidar, self.camera, masks, [e.object_id for e in use],
            [e.contact_cost for e in use], T_base_lidar=self.T_base_lidar,
            T_odom_lidar=T_odom_base @ self.T_base_lidar, stamp_s=scan.stamp_s,
        )
        p_odom = self.partitioner.last_points_odom  # the scan in the odom frame, from the partition's pass
        self._last_scan_odom = p_odom
        self._last_scan_pose = tuple(float(v) for v in pose)
        if self._demoted_tree is not None:
            self._reidentify_demoted(part, p_odom)
        deformable = self._deformable_objects()
        # the scan's time (the controller deskews it to the tick and stamps it so)
        T_odom_lidar = T_odom_base @ self.T_base_lidar
        self.tracker.update(float(scan.stamp_s), part, p_odom, skip=deformable if self.deformable.config.enabled else (),
                            origin_odom=T_odom_lidar[:3, 3])
        refused = self.tracker.refused_points
        if refused.size:  # a mask view the tracker refused (its points fixed): this scan's voxels were written movable
            write = np.zeros(len(p_odom), bool)
            write[refused] = True
            self.partitioner.memory.write(p_odom, write, part.label, part.object_id, part.cost, float(scan.stamp_s))
        self.deformable.update(float(scan.stamp_s), part, p_odom, deformable, (pose[0], pose[1]))
        self.deformable.label(float(scan.stamp_s), part, p_odom, pose, self.robot_box)
        return part, len(use)

    def _prepare(self, request: VlmRequest, answer: VlmAnswer) -> None:
        """Phase II's image work for an answer, in the runner's worker (lockstep: in settle, the
        simulator's barrier): against the entries the memory holds now (only the tick changes
        them, by applying answers, one in flight at a time, and by ageing out: an entry gone by
        the time the tick applies this has no IoU row then)."""
        # the answer as the runner will deliver it: the request's stamp and camera pose
        answer = dataclasses.replace(answer, stamp_s=request.stamp_s, camera_pose_odom=request.camera_pose_odom)
        stamp = float(answer.stamp_s)
        request_state = self._points_cam_at, self._stones_at, self._motions_at
        if stamp not in request_state[0]:
            return  # a request abandoned for its timeout (real time): the tick no longer waits for it
        with self._prepare_lock:  # an abandoned worker may still be in here: the preparer's buffers are shared
            self._prepared[stamp] = self._preparer.prepare(
                answer, tuple(self.memory.entries), prompt=self.config.prompt, points_cam=request_state[0][stamp],
                tombstones=request_state[1].get(stamp, ()), motions=request_state[2].get(stamp))

    def _deformable_objects(self) -> dict[int, float]:
        """id -> contact cost of the objects the backend called deformable that may be passed
        through (movable, below the never-touch cost, not demoted, not believed heavy or fragile);
        the region of one that no longer may is dropped."""
        out = {e.object_id: e.contact_cost for e in self.memory.entries
               if e.deformable and self._may_gate(e) and not self.memory.is_demoted(e.object_id)
               and not self._believed_fixed(e.object_id)}
        remembered = {e.object_id for e in self.memory.entries}
        for k in list(self.deformable.regions):
            # demoted, believed heavy or fragile, or a newer answer no longer calls it deformable
            # and touchable: its region goes (an entry that aged out leaves the region be)
            if self.memory.is_demoted(k) or self._believed_fixed(k) or (k in remembered and k not in out):
                self.deformable.remove(k)
        return out

    def _may_gate(self, entry) -> bool:
        """An entry that can gate points at all (movable, below never_touch_cost): the others are
        not warped per scan."""
        return entry.movable and entry.contact_cost < self.config.never_touch_cost

    def _moved(self, entry) -> float | None:
        """How far the tracker saw entry's object move since the mask's capture (None: it did not
        follow it all that time)."""
        return self.tracker.moved_since(entry.object_id, entry.stamp_s)

    def _gates(self, entry, moved: float | None, warped_px: Callable[[], float], captured_px: float,
               in_image: bool) -> bool:
        """Does this entry's warped mask gate points this scan? Movable, below never_touch_cost,
        in the image (in_image: its warped bounding box is not empty), and trusted: the warp
        assumes the object stood still since capture. The tracker knows whether it did: a moved
        one is not warped but tracked; a still one is trusted however much the camera's approach
        grew it. Not followed all that time: the growth rule (max_mask_growth) on the warped
        area (warped_px(), counted only then; an empty warp does not gate). Distrusted masks are
        counted. moved: _moved(entry)."""
        if not (entry.movable and entry.contact_cost < self.config.never_touch_cost and in_image):
            return False
        if entry.object_id in self.memory.demoted:  # correcting mode: a push on it failed (eq. 14)
            return False
        if self._believed_fixed(entry.object_id):  # believed heavy or fragile (it becomes demoted)
            return False
        if moved is not None:
            distrust = moved > self.config.moved_tolerance_m
        else:
            area = warped_px()
            if not area > 0:
                return False
            distrust = area > self.config.max_mask_growth * captured_px
        if distrust:
            self.masks_distrusted += 1
            return False
        return True

    def carried_region(self, half_length_m: float, half_width_m: float, margin_m: float,
                       pad_m: float = 0.05) -> tuple[float, float, float, float] | None:
        """Where the object the robot is pushing lies relative to the robot, as the last scan saw
        it: (x min, x max, y min, y max) in base_link, padded by pad_m; None when the robot pushes
        nothing (no P_mov object within its footprint + margin_m ahead). A pushed object moves
        with the robot: its points of the next scan are deskewed with it, not with the world
        (ObstaclePointExtractor.deskew)."""
        pose = self._last_scan_pose
        oid = self.movable_in_front(pose, half_length_m, half_width_m, margin_m)
        # a curtain does not move as one body with the robot (its slats drape over it), and a
        # demoted object did not move when pushed: neither is carried
        if oid is None or oid in self.deformable.regions or oid in self.memory.demoted:
            return None
        part = self.last_frame.partition
        sel = (part.label == MOVABLE) & (part.object_id == oid)
        return object_extent_in_base(self._last_scan_odom[sel], pose, half_width_m, pad_m)

    def movable_in_front(self, pose: tuple[float, float, float], half_length_m: float, half_width_m: float,
                         margin_m: float, forward: bool = True, min_points: int = 3) -> int | None:
        """The movable object the robot is pushing: the object id with the most P_mov points of
        the last scan in front of the robot (behind it when reversing: `forward` False) within its
        footprint + margin_m (odom pose of the robot now); None when there is none."""
        frame, p = self.last_frame, self._last_scan_odom
        if frame is None or p is None:
            return None
        return movable_in_front(frame.partition, p, pose, (half_length_m, half_width_m, margin_m), forward=forward,
                                min_points=min_points)

    def observe_contact(self, now_s: float, pose: tuple[float, float, float], v_mps: float, currents_a,
                        half_length_m: float, half_width_m: float, margin_m: float) -> None:
        """One tick of push evidence for the belief (runtime.vpp.belief.ContactEvidence): the object in
        front of the robot while it drives forward, the wheel currents, the tracker's view of the
        object's motion. An object the belief comes to call heavy or fragile is demoted to fixed
        (as correcting mode does after a failed push)."""
        oid = self.movable_in_front(pose, half_length_m, half_width_m, margin_m) if v_mps > 0.0 else None
        # The drive's own losses are learned only with nothing at all in front (no P_mov, no
        # P_fix: pressing on a wall or a demoted box is not free driving).
        free = oid is None and not self._anything_in_front(pose, half_length_m, half_width_m, margin_m)
        # Push outcomes come from correcting mode's stuck test (demote: "did not move"), not from
        # the tracker: while the wheels slip, the odometry carries the scan, and with it the
        # object, forward, and the tracker sees a motion that did not happen.
        self.contact.update(now_s, v_mps, currents_a, oid, lambda _oid, _since: None, free=free)
        if oid is not None and self._believed_fixed(oid) and oid not in self.memory.demoted:
            self.demote(oid, failed_push=False)
            self.belief_demotions += 1

    def movable_points_lidar(self) -> np.ndarray | None:
        """The last partitioned scan's P_mov in the lidar frame (None: none)."""
        frame = self.last_frame
        if frame is None or self._last_scan_lidar is None or len(self._last_scan_lidar) != len(frame.partition.label):
            return None
        mov = frame.partition.label == MOVABLE
        return self._last_scan_lidar[mov] if mov.any() else None

    def _believed_fixed(self, object_id: int) -> bool:
        """Heavy or fragile by the belief, or an expected contact cost at the never-touch cost."""
        return self.belief.is_fixed(object_id) or (
            self.belief.config.enabled and object_id in self.belief.beliefs
            and self.belief.expected_cost(object_id, self.belief.beliefs[object_id].backend_cost)
            >= self.config.never_touch_cost)

    def _anything_in_front(self, pose, half_length_m: float, half_width_m: float, margin_m: float) -> bool:
        """A lidar point of the last scan (not ground) in front of the robot within its footprint
        plus margin_m (unknown without a scan: not free)."""
        frame, p = self.last_frame, self._last_scan_odom
        if frame is None or p is None:
            return True
        return bool(np.any(in_front(p, pose, (half_length_m, half_width_m, margin_m)) & (frame.partition.label >= 0)))

    def expected_costs(self, object_id: np.ndarray, cost: np.ndarray) -> np.ndarray:
        """Per point of P_mov: its object's expected contact cost under the belief (the backend's
        cost when the belief is off or the object has none)."""
        out = np.asarray(cost, dtype=np.float64).copy()
        if not self.belief.config.enabled or not self.belief.beliefs:
            return out
        for oid in np.unique(object_id):
            sel = object_id == oid
            out[sel] = self.belief.expected_cost(int(oid), float(out[sel][0]))
        return np.minimum(out, 10.0)

    def demote(self, object_id: int, failed_push: bool = True) -> int:
        """Correcting mode (DCT eq. 14): object_id is fixed for the rest of the episode. Its masks
        no longer gate (`_gates`; the mask memory carries the demotion to fresh detections of the
        object), the tracker forgets it (it would label its points movable), and its voxels in
        the odom-frame label memory become fixed (the points the camera does not see). Returns
        the voxels relabelled. failed_push: a push on it failed (correcting mode: the belief takes
        it as "not moved" evidence); False: the belief itself made it fixed."""
        oid = int(object_id)
        if failed_push:
            self.belief.observe_push(oid, moved=False, t_s=self._now_s)
        if self.last_frame is not None and self._last_scan_odom is not None:
            part = self.last_frame.partition
            xy = self._last_scan_odom[(part.label == MOVABLE) & (part.object_id == oid), :2]
            if len(xy):
                self._demoted_xy = xy if self._demoted_xy is None else np.concatenate([self._demoted_xy, xy])
                self._demoted_tree = cKDTree(self._demoted_xy)
        self.memory.demote(oid)
        self.tracker.objects.pop(oid, None)
        self.deformable.remove(oid)
        self.demotions += int(failed_push)
        return self.partitioner.memory.fix_object(oid)

    def _reidentify_demoted(self, part: PointPartition, p_odom: np.ndarray, radius_m: float = 0.10) -> None:
        """A movable object most of whose points lie where a demoted one's were (odom frame: the
        demoted object did not move, that is why it was demoted) is that object under a new mask
        id (the mask memory gives a new id when the warped mask no longer matches, e.g. after the
        object was out of view): its id is demoted too and its points are fixed in this scan."""
        mov = np.flatnonzero(part.label == MOVABLE)
        if not mov.size:
            return
        d, _ = self._demoted_tree.query(p_odom[mov, :2], distance_upper_bound=radius_m)
        near = np.isfinite(d)
        for oid in np.unique(part.object_id[mov]):
            sel = part.object_id[mov] == oid
            if np.mean(near[sel]) >= 0.5:
                if not self.memory.is_demoted(int(oid)):
                    self.reidentified += 1
                self.memory.demote(int(oid))
                self.tracker.objects.pop(int(oid), None)
                self.partitioner.memory.fix_object(int(oid))  # this scan's voxels were written movable
                pts = mov[sel]
                part.label[pts] = FIXED
                part.object_id[pts] = -1
                part.cost[pts] = np.nan

    def _masks_now(self, now_s: float, T_odom_cam: np.ndarray):
        """Phase I for this scan: (masks for the partition, their entries). The memory's masks are
        carried to the camera pose now per pixel (MaskMemory.lookup: a WarpLookup, looked up by
        the partition only at the points' pixels); a camera whose distortion the per-pixel warp
        does not implement (the 14-coefficient tilted model) gets full-image warps (propagate).
        The growth test takes the warped area from the lookup (exact for a warped mask whose
        bounding box has at most homography.lookup.AREA_SAMPLES pixels, else estimated on a grid)."""
        if self._per_pixel:
            # the growth test reads the warped area only of objects the tracker did not follow
            moved: dict[int, float | None] = {}

            def not_followed(e) -> bool:
                moved[id(e)] = self._moved(e)
                return moved[id(e)] is None

            entries, lk = self.memory.lookup(now_s, T_odom_cam, select=self._may_gate, area_of=not_followed)
            px = self.memory.mask_px()
            use = [k for k, e in enumerate(entries)
                   if self._gates(e, moved[id(e)], lambda k=k: float(lk.area_px[k]), float(px[k]),
                                  lk.box[k, 0] <= lk.box[k, 2])]
            return lk.select(use), [entries[k] for k in use]
        warped = [w for w in self.memory.propagate(now_s, T_odom_cam)
                  if self._gates(w.entry, self._moved(w.entry), lambda w=w: np.count_nonzero(w.mask),
                                 np.count_nonzero(w.entry.mask), bool(w.mask.any()))]
        h, w = self.camera.height_px, self.camera.width_px
        masks = np.stack([m.mask for m in warped]) if warped else np.zeros((0, h, w), bool)
        return masks, [m.entry for m in warped]

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
        self._stones_at = {float(image.stamp_s): self.memory.tombstones()}
        # the tracked objects that moved since their masks' captures (a pushed box): warped with it
        self._motions_at = {float(image.stamp_s): self.tracker.moved_objects(
            [(e.object_id, e.stamp_s) for e in self.memory.entries], image.stamp_s)}
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
            "masks_distrusted": self.masks_distrusted, "points_tracked": self.tracker.points_tracked,
            "tracking": {"objects": len(self.tracker.objects), "registrations": self.tracker.registrations,
                         "lost": self.tracker.lost, "unseen": self.tracker.unseen,
                         "handovers": self.tracker.handovers, "refused_views": self.tracker.refused_views},
            "deformable": self.deformable.describe(),
            "images_refused": self.images_refused, "gave_up_waiting": self.gave_up_waiting,
            "frames": self.frames, "memory_entries": len(self.memory.entries), "runner": self.runner.counters(),
            "last_movable_points": self.last_frame.movable_count if self.last_frame is not None else 0,
            "demoted_objects": sorted(self.memory.demoted), "demoted_reidentified": self.reidentified,
            "belief": {**self.belief.describe(), "demotions": self.belief_demotions,
                       "evidence_windows": self.contact.windows},
        }


__all__ = ["VppFrame", "VppStage", "pose_matrix"]
