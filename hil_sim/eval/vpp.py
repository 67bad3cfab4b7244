"""`dct vpp eval --scenario`: the VPP stage of one closed-loop HIL run against the simulator's truth.

The run is an ordinary lockstep episode of the controller in planner mode dct (the VPP partition,
the planner on P_fix) with the sim-oracle at the asked quality, the robot waiting at its start for
the first answer (`vpp.before_first_answer: wait`). The camera runs at
`camera_rate_hz` (10 Hz by default, not the 2 Hz of an ordinary dct episode) so that the warped
masks can be compared with the truth every few centimetres of travel; the stage still sends only
the newest image when its trigger rule asks.

Two measurements, both from what the controller itself had at each instant (its odometry poses,
its memory's masks and planes), against ground truth the controller never sees:

* Point partition, per scan the stage partitioned after the first answer arrived (before it every
  point is P_fix by design): a point is truly movable when the lidar ray hit an obstacle of class
  `movable` (SimLidar.ground_truth_geom_ids); predicted movable when the stage labelled it P_mov.
  `point_precision` = TP / (TP + FP); `point_recall` = TP / (TP + FN) over EVERY truly movable
  point of the scan (in the camera's view or not: outside it only the label memory and the
  tracking can know them), `point_recall_in_view` over those the camera sees. Floor points are
  neither movable nor fixed obstacles (the partition removes the ground by height, and the
  planner's obstacle extraction again): they are left out of both figures, and the floor points
  labelled P_mov anyway (a robot pitching as it pushes lifts the floor above the ground cut) are
  counted in `point_counts.floor_labelled_movable`.
* Warped masks: every mask the memory took in (each object of each answer is a capture: its
  mask, its camera pose, its plane) is carried to the camera images that follow, by three
  methods, and compared with the true mask of its object in that image (segmentation == the geom
  the capture mask covered): `plane` (the plane-induced homography the stage uses), `rotation`
  (the rotation-only homography), `reprojection` (the scan at that image, placed in the capture
  camera through the odom frame; its points that fall in the capture mask within
  `REPROJECTION_DEPTH_GATE_M` of their median depth, projected into the current image, filled as
  their convex hull). A capture gives one sample per travel distance d (robot path length since
  capture): the image nearest to d of travel, if it is within max(0.1 m, d / 4) of d. Samples are
  left out, and counted, when the object moved since capture (a pushed box: the warp assumes a
  static object, tracking handles moving ones), when it is out of view (fewer than
  `min_pixels` true pixels), or when the mask had no plane (so the three methods are compared on
  the same samples). Walls are not evaluated (obstacles only).

`stage_ms`: wall-clock time of VppStage.update on the ticks with a new scan (a measurement of this
machine, beside the deterministic figures); `stage_cpu_ms` the same calls' CPU time (the thread's:
what they cost a core, without the time other processes took it). Phase II's image work is not
in them: it runs beside the tick, in the backend runner's worker (runtime/vpp/stage.py).
"""
from __future__ import annotations

import math
import time
from collections import deque
from dataclasses import dataclass, field
from typing import Callable

import cv2
import numpy as np

from hil_sim.sensors.lidar import LidarConfig
from hil_sim.episode.lockstep import LockstepSimulation, run_episode
from hil_sim.world.scenario import load_scenario
from hil_sim.world.sensor_rig import SensorRig, SensorRigConfig
from models.vlm.sim_oracle import SimOracleConfig
from runtime.config import load_controller_config
from runtime.common.sensor_data import CameraImage, LidarScan
from runtime.vpp.homography.image_warp import MaskWarper
from runtime.vpp.homography.plane import relative_motion
from runtime.vpp.partition.labels import MOVABLE
from runtime.vpp.stage import pose_matrix

#: Travel distances (m) after capture at which warped masks are scored.
DISTANCES_M = (0.25, 0.5, 1.0, 2.0)
METHODS = ("plane", "rotation", "reprojection")
REPROJECTION_DEPTH_GATE_M = 0.5
#: An object whose centre moved more than this since capture is left out of the mask scores.
MOVED_TOLERANCE_M = 0.02
#: Camera history kept for the scores (s): longer than the VLM latency plus 2 m of slow travel.
HISTORY_S = 12.0


@dataclass
class _View:
    """One camera image as the controller placed it, with the truth beside it."""

    stamp_s: float
    segmentation: np.ndarray  # (H, W) int32 geom ids
    positions: dict[int, np.ndarray]  # geom id -> true centre (world) at the image
    T_odom_cam: np.ndarray | None = None  # the controller's camera pose at the tick that took the image
    travel_m: float = math.nan  # the robot's odometry path length then
    scan_odom: np.ndarray | None = None  # the newest scan then, odom frame


@dataclass
class _Capture:
    object_id: int
    stamp_s: float
    geom: int
    mask: np.ndarray
    plane: object
    T_odom_cam: np.ndarray
    travel_m: float
    positions: dict[int, np.ndarray]
    done: set = field(default_factory=set)


class VppProbe:
    """Attached to one episode (run_episode's on_start and observe): collects the scores."""

    def __init__(self, distances_m=DISTANCES_M, min_pixels: int = 200) -> None:
        self.distances = tuple(float(d) for d in distances_m)
        self.min_pixels = int(min_pixels)
        self.views: deque[_View] = deque()
        self._pending: list[_View] = []
        self.captures: dict[tuple[int, float], _Capture | None] = {}
        self.open: list[_Capture] = []
        self.tp = self.fp = self.fn = 0
        self.fn_in_view = self.tp_in_view = 0
        self.floor_movable = 0
        self.frames = 0
        self.frames_before_answer = 0
        self.iou: dict[str, dict[float, list[float]]] = {m: {d: [] for d in self.distances} for m in METHODS}
        self.left_out = {"moved": 0, "out_of_view": 0, "no_plane": 0, "no_image_near_distance": 0}
        self.stage_s: list[float] = []
        self.stage_cpu_s: list[float] = []
        self.samples: list[dict] = []  # every scored (capture, distance): object, IoU per method
        self._travel = 0.0
        self._last_xy: tuple[float, float] | None = None
        self._last_frame_stamp: float | None = None
        self._scan_odom: np.ndarray | None = None

    # -- wiring ---------------------------------------------------------------------------
    def attach(self, sim: LockstepSimulation, controller) -> None:
        rigs = [d for d in sim.devices if isinstance(d, SensorRig)]
        if not rigs or rigs[0].lidar is None or rigs[0].camera is None:
            raise ValueError("dct vpp eval: the episode has no lidar or camera")
        if controller.vpp is None:
            raise ValueError("dct vpp eval: the controller is not in planner mode dct")
        self.world, self.rig, self.stage = sim.world, rigs[0], controller.vpp
        self.warper = MaskWarper(self.stage.camera)
        names = [n for n in self.world.obstacle_names if n not in set(self.world.scenario.wall_names())]
        self.geom_of = {n: int(self.world.obstacle_geom_id(n)) for n in names}
        self.name_of = {g: n for n, g in self.geom_of.items()}
        self.objects = set(self.geom_of.values())
        self.movable = np.array(sorted(g for n, g in self.geom_of.items()
                                       if self.world.obstacle_class(n) == "movable"), dtype=np.int32)
        import mujoco

        self.floor = int(mujoco.mj_name2id(self.world.model, mujoco.mjtObj.mjOBJ_GEOM, "floor"))
        self.rig.listeners.append(self._on_sensor)
        update = self.stage.update

        def timed_update(now_s, pose, image, scan, image_pose=None):  # the stage's own work, timed on scan ticks
            t0, c0 = time.perf_counter(), time.thread_time()
            out = update(now_s, pose, image, scan, image_pose)
            if scan is not None:
                self.stage_s.append(time.perf_counter() - t0)
                self.stage_cpu_s.append(time.thread_time() - c0)
            return out

        self.stage.update = timed_update

    def _on_sensor(self, msg: LidarScan | CameraImage) -> None:
        if isinstance(msg, CameraImage) and msg.segmentation is not None:
            positions = {g: self.world.obstacle_position(n) for n, g in self.geom_of.items()}
            self._pending.append(_View(float(msg.stamp_s), np.asarray(msg.segmentation), positions))

    # -- after every tick -----------------------------------------------------------------
    def after_tick(self, controller) -> None:
        pose = controller.pose
        if self._last_xy is not None:
            self._travel += math.hypot(pose.x_m - self._last_xy[0], pose.y_m - self._last_xy[1])
        self._last_xy = (pose.x_m, pose.y_m)
        stage = self.stage
        T_odom_base = pose_matrix(pose.x_m, pose.y_m, pose.yaw_rad)
        frame = stage.last_frame
        if frame is not None and frame.stamp_s != self._last_frame_stamp:
            # The partition ran this tick, on this tick's lidar frame (deskewed to the tick: the
            # frame is stamped with the tick, the ground truth with the sensor frame's start).
            self._last_frame_stamp = frame.stamp_s
            scan = controller.monitor.good_scan
            self._score_partition(frame, None if scan is None else scan.stamp_s)
            if stage._last_scan_odom is not None:
                self._scan_odom = np.array(stage._last_scan_odom, np.float64)
        for view in self._pending:
            # the camera where it took the frame (as the stage's masks are placed: pose_at)
            at = controller.odometry.pose_at(view.stamp_s)
            T_view = T_odom_base if at is None else pose_matrix(at.x_m, at.y_m, at.yaw_rad)
            view.T_odom_cam = T_view @ stage.T_base_cam
            view.travel_m = self._travel
            view.scan_odom = self._scan_odom
            self.views.append(view)
        self._pending.clear()
        while self.views and self.views[-1].stamp_s - self.views[0].stamp_s > HISTORY_S:
            self.views.popleft()
        for entry in stage.memory.entries:
            key = (int(entry.object_id), float(entry.stamp_s))
            if key not in self.captures:
                self.captures[key] = cap = self._capture(entry)
                if cap is not None:
                    self.open.append(cap)
        self._score_masks(final=False)

    def finish(self) -> None:
        self._score_masks(final=True)

    # -- the partition --------------------------------------------------------------------
    def _score_partition(self, frame, sensor_stamp_s: float | None) -> None:
        if self.stage.answers == 0:
            self.frames_before_answer += 1
            return
        gids = None if sensor_stamp_s is None else self.rig.lidar.ground_truth_geom_ids(sensor_stamp_s)
        part = frame.partition
        if gids is None or len(gids) != len(part.label):
            raise RuntimeError(f"dct vpp eval: no ground truth for the scan at {sensor_stamp_s} s "
                               f"(its points: {len(part.label)})")
        floor = gids == self.floor
        truth = np.isin(gids, self.movable)
        pred = (part.label == MOVABLE) & ~floor
        self.floor_movable += int(np.count_nonzero(floor & (part.label == MOVABLE)))
        self.frames += 1
        self.tp += int(np.count_nonzero(truth & pred))
        self.fp += int(np.count_nonzero(~truth & pred))
        self.fn += int(np.count_nonzero(truth & ~pred))
        self.tp_in_view += int(np.count_nonzero(truth & pred & part.in_view))
        self.fn_in_view += int(np.count_nonzero(truth & ~pred & part.in_view))

    # -- the masks ------------------------------------------------------------------------
    def _capture(self, entry) -> _Capture | None:
        view = next((v for v in self.views if v.stamp_s == float(entry.stamp_s)), None)
        if view is None:
            return None
        ids, counts = np.unique(view.segmentation[entry.mask], return_counts=True)
        geom = int(ids[np.argmax(counts)])
        if geom not in self.objects:
            return None  # a wall, or the floor
        return _Capture(int(entry.object_id), float(entry.stamp_s), geom, entry.mask, entry.plane,
                        np.asarray(entry.camera_pose_odom), view.travel_m, view.positions)

    def _score_masks(self, final: bool) -> None:
        still = []
        for cap in self.open:
            later = [v for v in self.views if v.stamp_s > cap.stamp_s and v.T_odom_cam is not None]
            for d in self.distances:
                if d in cap.done:
                    continue
                past = [v for v in later if v.travel_m - cap.travel_m >= d]
                if not past:
                    if final:
                        cap.done.add(d)  # the run ended first: no sample
                    continue
                cap.done.add(d)
                # The image nearest to d of travel: the first past it or the last before it.
                before = [v for v in later if v.travel_m - cap.travel_m < d]
                near = past[0]
                if before and d - (before[-1].travel_m - cap.travel_m) < (near.travel_m - cap.travel_m) - d:
                    near = before[-1]
                self._score_one(cap, near, d)
            if len(cap.done) < len(self.distances):
                still.append(cap)
        self.open = still

    def _score_one(self, cap: _Capture, view: _View, d: float) -> None:
        if abs(view.travel_m - cap.travel_m - d) > max(0.1, d / 4):
            self.left_out["no_image_near_distance"] += 1
            return
        if np.linalg.norm(view.positions[cap.geom] - cap.positions[cap.geom]) > MOVED_TOLERANCE_M:
            self.left_out["moved"] += 1
            return
        truth = view.segmentation == cap.geom
        if np.count_nonzero(truth) < self.min_pixels:
            self.left_out["out_of_view"] += 1
            return
        if cap.plane is None:
            self.left_out["no_plane"] += 1
            return
        R, t = relative_motion(cap.T_odom_cam, view.T_odom_cam)
        masks = {
            "plane": self.warper.warp(cap.mask, R, t, cap.plane),
            "rotation": self.warper.warp(cap.mask, R, t, None),
            "reprojection": self._reproject(cap, view),
        }
        sample = {"object": self.name_of[cap.geom], "capture_s": round(cap.stamp_s, 3), "after_m": d,
                  "travelled_m": round(view.travel_m - cap.travel_m, 3), "true_pixels": int(np.count_nonzero(truth))}
        for method, mask in masks.items():
            union = np.count_nonzero(mask | truth)
            iou = np.count_nonzero(mask & truth) / union if union else 0.0
            self.iou[method][d].append(iou)
            sample[method] = round(iou, 4)
        self.samples.append(sample)

    def _reproject(self, cap: _Capture, view: _View) -> np.ndarray:
        camera = self.stage.camera
        out = np.zeros((camera.height_px, camera.width_px), np.uint8)
        if view.scan_odom is None or len(view.scan_odom) == 0:
            return out.view(bool)
        T_cap = np.linalg.inv(cap.T_odom_cam)
        p_cap = view.scan_odom @ T_cap[:3, :3].T + T_cap[:3, 3]
        uv, valid = camera.project(p_cap)
        iu = np.clip(np.rint(np.where(valid, uv[:, 0], 0)).astype(np.intp), 0, camera.width_px - 1)
        iv = np.clip(np.rint(np.where(valid, uv[:, 1], 0)).astype(np.intp), 0, camera.height_px - 1)
        inside = valid & cap.mask[iv, iu]
        if np.count_nonzero(inside) < 3:
            return out.view(bool)
        depth = p_cap[inside, 2]
        keep = np.flatnonzero(inside)[np.abs(depth - np.median(depth)) <= REPROJECTION_DEPTH_GATE_M]
        T_cur = np.linalg.inv(view.T_odom_cam)
        uv2, ok = camera.project(view.scan_odom[keep] @ T_cur[:3, :3].T + T_cur[:3, 3])
        pts = uv2[ok]
        if len(pts) >= 3:
            hull = cv2.convexHull(np.rint(pts).astype(np.int32))
            cv2.fillConvexPoly(out, hull, 1)
        return out.view(bool)

    # -- the report -----------------------------------------------------------------------
    def report(self) -> dict:
        def ratio(a: int, b: int) -> float | None:
            return a / b if b else None

        stage_ms = np.asarray(self.stage_s) * 1e3
        cpu_ms = np.asarray(self.stage_cpu_s) * 1e3
        return {
            "frames": self.frames,
            "frames_before_first_answer": self.frames_before_answer,
            "point_precision": ratio(self.tp, self.tp + self.fp),
            "point_recall": ratio(self.tp, self.tp + self.fn),
            "point_recall_in_view": ratio(self.tp_in_view, self.tp_in_view + self.fn_in_view),
            "point_counts": {"true_movable_labelled_movable": self.tp, "fixed_labelled_movable": self.fp,
                             "movable_labelled_fixed": self.fn, "floor_labelled_movable": self.floor_movable},
            "iou_after_m": {m: {f"{d:g}": (float(np.mean(v)) if v else None) for d, v in per.items()}
                            for m, per in self.iou.items()},
            "iou_min_after_m": {m: {f"{d:g}": (float(np.min(v)) if v else None) for d, v in per.items()}
                                for m, per in self.iou.items()},
            "iou_samples": {f"{d:g}": len(v) for d, v in self.iou["plane"].items()},
            "iou_left_out": dict(self.left_out),
            "iou_sample_list": self.samples,
            "captures": sum(c is not None for c in self.captures.values()),
            "stage_ms": {
                "p50": float(np.percentile(stage_ms, 50)) if stage_ms.size else None,
                "p99": float(np.percentile(stage_ms, 99)) if stage_ms.size else None,
                "max": float(stage_ms.max()) if stage_ms.size else None,
                "frames": int(stage_ms.size),
            },
            "stage_cpu_ms": {
                "p50": float(np.percentile(cpu_ms, 50)) if cpu_ms.size else None,
                "p99": float(np.percentile(cpu_ms, 99)) if cpu_ms.size else None,
                "max": float(cpu_ms.max()) if cpu_ms.size else None,
            },
        }


def evaluate_scenario(scenario: str, seed: int = 0, oracle: SimOracleConfig | None = None,
                      progress: Callable[[float, float], None] | None = None,
                      camera_rate_hz: float = 10.0, distances_m=DISTANCES_M) -> dict:
    """One closed-loop dct episode with the probe attached (module docstring); JSON-ready figures."""
    sc = load_scenario(scenario, seed=seed)  # a generated scene is drawn from the seed
    config = load_controller_config()
    # The robot waits at its start for the first answer (vpp.before_first_answer: wait), as the
    # figures were defined: driving first (the default), its approach grows the first masks past
    # the stage's growth rule and they are distrusted, which would measure the start, not the stage.
    config = config.with_planner_mode("dct")
    config = config.model_copy(update={"vpp": config.vpp.model_copy(update={"before_first_answer": "wait"})})
    oracle = (oracle or SimOracleConfig()).model_copy(update={"seed": seed})
    rig = SensorRigConfig(seed=seed, camera_rate_hz=camera_rate_hz, camera_segmentation=True,
                          lidar=LidarConfig(ground_truth_frames=8))
    probe = VppProbe(distances_m)
    result = run_episode(sc, config=config, seed=seed, sensors=rig, oracle=oracle, on_start=probe.attach,
                         observe=probe.after_tick,
                         progress=(lambda t: progress(t, sc.time_limit_s)) if progress else None)
    probe.finish()
    m = result.metrics
    return {
        "scenario": sc.name, "seed": seed,
        "oracle": oracle.model_dump(),
        "camera_rate_hz": camera_rate_hz,
        **probe.report(),
        "episode": {"success": m["success"], "navigation_time_s": m["navigation_time_s"],
                    "fixed_contacts": m["fixed_contacts"], "failure_reason": m.get("failure_reason")},
        "definitions": __doc__,
    }


__all__ = ["DISTANCES_M", "METHODS", "VppProbe", "evaluate_scenario"]
