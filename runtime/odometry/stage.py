"""The tick's odometry stage: wheels + gyro every tick, KISS-ICP beside the tick, one fused pose.

Per tick (`update`): integrate the wheels (0x311, scaled by the calibrated wheel scale) and the
gyro (the wheels' yaw with the calibrated effective track when there is no IMU sample) into the
dead-reckoning pose; hand a new good lidar frame to the ICP worker with the wheel/gyro motion
since the previous frame as its prior; fuse every ICP result that is ready; output the newest
ICP-corrected pose predicted forward with wheels and gyro (runtime.odometry.fusion).

Nothing here waits for ICP. What it says in telemetry (`describe`): ICP results fused, refused and
dropped, degenerate frames and the weak direction, the age of the newest ICP correction, the
worker's compute time, and the pose covariance.
"""
from __future__ import annotations

import dataclasses
import functools
import math
from collections import deque
from typing import Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from runtime.common.events import EventLog
from runtime.common.geometry import Pose2D
from runtime.odometry.degeneracy import DegeneracyConfig
from runtime.odometry.fusion import FusionConfig, PoseFusion
from runtime.odometry.icp import IcpEngine, IcpJob, IcpResult
from runtime.odometry.icp_config import IcpConfig
from runtime.odometry.icp_settings import RangeGate
from runtime.odometry.se2 import se2_between, se2_compose, se2_inverse
from runtime.odometry.wheels import OdometerWatch, WheelGyroOdometry, WheelOdometry
from runtime.odometry.worker import InlineIcpWorker, ProcessIcpWorker
from runtime.common.sensor_data import LidarScan


class OdometryConfig(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)

    #: fused: wheels + gyro + KISS-ICP (the default); wheels_imu: dead reckoning only.
    source: Literal["fused", "wheels_imu"] = "fused"
    icp: IcpConfig = IcpConfig()
    #: KISS-ICP's initial guess (and, with deskew "kiss", its deskew motion): "odometry" = the
    #: wheel/gyro motion since the previous frame; "constant_velocity" = KISS-ICP's own.
    icp_prior: Literal["odometry", "constant_velocity"] = "odometry"
    degeneracy: DegeneracyConfig = DegeneracyConfig()
    fusion: FusionConfig = FusionConfig()
    #: Where ICP runs in lockstep: "process" (beside the simulator) or "inline" (in the
    #: simulator's time advance). On the robot and in real time it is always a process.
    lockstep_worker: Literal["process", "inline"] = "process"
    #: Lockstep: an ICP result is delivered this long (simulated) after its frame's end.
    lockstep_latency_s: float = Field(0.1, gt=0.0, le=2.0)
    #: No ICP correction for longer than this: "icp_lost" event (wheels and gyro carry the pose).
    max_icp_age_s: float = Field(0.6, gt=0.05, le=30.0)
    #: 0x311's wheel distances unchanged for at least this long while the 0x221 speed accounts
    #: for `wheels_frozen_speed_mps` x `wheels_frozen_s` of wheel travel (5 mm; the odometer counts
    #: millimetres): frozen readings, not a robot standing still (both come from the same
    #: encoders; runtime.odometry.wheels.OdometerWatch). The distances are then not used until
    #: they change; the base's speed carries the translation from their last change, and they
    #: re-anchor on the next new one (0: off, every fresh reading is used).
    wheels_frozen_s: float = Field(0.1, ge=0.0, le=5.0)
    wheels_frozen_speed_mps: float = Field(0.05, gt=0.0, le=5.0)


def _pose_vec(p: Pose2D) -> np.ndarray:
    return np.array([p.x_m, p.y_m, p.yaw_rad])


class OdometryStage:
    def __init__(self, config: OdometryConfig, track_m: float, effective_track_factor: float,
                 lidar_mount: np.ndarray, lockstep: bool, events: EventLog | None = None,
                 wheel_scale: float = 1.0, uses_lidar: bool = True) -> None:
        self.config = config
        self.lockstep = lockstep
        self.events = events
        self.wheels = WheelGyroOdometry(track_m, effective_track_factor, wheel_scale=wheel_scale)
        self.fusion = PoseFusion(config.fusion)
        self.mount = np.asarray(lidar_mount, dtype=float)
        self.icp_enabled = config.source == "fused" and config.icp.enabled and uses_lidar
        self.worker = None
        self._seq = 0
        #: Lidar-frame points of things that may move with the robot (the last partitioned scan's
        #: P_mov: a box the robot pushes stays where it was in the lidar frame): the next frame's
        #: points within `exclude_radius_m` of them are left out of the ICP, which would otherwise
        #: register the world to the box and report the robot standing still while it pushes.
        self._exclude: np.ndarray | None = None
        self.exclude_radius_m = 0.10
        #: Lidar-frame ground-plane positions (x, y) of people walking (runtime.perception.moving_obstacles):
        #: the next frame's points within `mover_radius_m` of them, at any height, are left out of
        #: the ICP. A person walking head-on is a feature coming at the robot: in an open room,
        #: registered as static, it made the odometry overshoot by 2-3% (person_approaching: the
        #: robot stopped 0.15-0.18 m short of the goal, believing it there).
        self._exclude_xy: np.ndarray | None = None
        self.mover_radius_m = 0.30
        self._pose_dr: np.ndarray | None = None
        self._bias_step_seen: tuple[float, float] | None = None
        self.points_excluded = 0  # counter
        self._first_submit_s: float | None = None
        self._last_update_s: float | None = None
        self._last_wheels: tuple[float, float] | None = None
        self._last_wheels_s: float | None = None  # when the wheel distances last changed
        self._blind_since_s: float | None = None  # the base has said nothing of its motion since
        self._speed_m = 0.0  # the base's reported speed (0x221) integrated: a distance odometer
        self._speed_m_at_change = 0.0  # ... when the wheel distances last changed
        self._wheels_used = False  # the last update used wheel distances
        self.frozen_wheels_since_s: float | None = None  # 0x311 frozen while 0x221 reports motion
        self._odometer = OdometerWatch(config.wheels_frozen_speed_mps * config.wheels_frozen_s, config.wheels_frozen_s)
        self.frozen_wheel_spells = 0  # counter
        self.pose = Pose2D(0.0, 0.0, 0.0)
        self.covariance = np.zeros((3, 3))
        #: This tick's ICP correction as a planar transform of the odom frame (None: none):
        #: apply it to anything placed in the odom frame with the pose before it.
        self.correction: np.ndarray | None = None
        self.frames_submitted = 0
        #: The ICP results this tick fused or refused (IcpResult, immutable): a recording notes each
        #: one's seq and frame stamp per tick, so that a replay delivers it at the tick it came live
        #: (runtime.app.replay), and its compute time, for a trace.
        self.delivered: tuple[IcpResult, ...] = ()
        self.compute_ms: deque[float] = deque(maxlen=4000)  # wall clock: measurements only
        self.latency_ms: deque[float] = deque(maxlen=4000)
        #: The worker's counters, kept when it is closed (reports are taken after the run).
        self._worker_final: dict = {"dropped": 0, "failed": None, "round_trip_s": ()}
        self.icp_age_s = float("inf")
        self._icp_lost = False
        self._degenerate = False
        self.last_degeneracy: str | None = None
        self.last_refusal: str | None = None
        #: What ICP's range gate dropped, summed over the results (runtime.odometry.icp_settings).
        self.gate = RangeGate.empty()
        self._gate_warned = False
        #: The settings the worker uses (auto ones resolved on its first frame), from its first result.
        self.icp_settings: dict | None = None
        self.iteration_caps: tuple[int, int] = (10**9, 0)  # (min, max) over the results
        #: An earlier run's frame to continue (resume_from), until the first wheel reading.
        self._resume: tuple[Pose2D, tuple[float, float], float] | None = None
        #: What became of it: None (not asked), else a sentence (continued, or why a new frame).
        self.resume_outcome: str | None = None

    # -- lifecycle -----------------------------------------------------------------------------
    def start(self) -> None:
        """Start the ICP worker (a process: it takes a moment; call at start-up, never in a tick:
        the assembly calls it as the parts are built, activation otherwise; wait_ready after)."""
        if not self.icp_enabled or self.worker is not None:
            return
        c = self.config
        factory = functools.partial(IcpEngine, c.icp, c.degeneracy, self.mount, c.icp_prior == "odometry")
        from runtime.common.spatial_grid import near_indices

        read_only = np.zeros((1, 3), np.float32)
        read_only.flags.writeable = False  # a scan's points (LidarScan): another signature
        for points in (np.zeros((1, 3), np.float32), read_only):
            for planar in (False, True):  # the exclusions' kernel loaded now, not in the first tick that excludes
                near_indices(points, np.zeros((1, 3)), 0.1, planar)
        if self.lockstep and c.lockstep_worker == "inline":
            self.worker = InlineIcpWorker(factory)
        else:
            # lockstep: the episodes of a campaign hand the worker process on (no 0.4 s start each)
            self.worker = ProcessIcpWorker(factory, lockstep=self.lockstep, reuse=self.lockstep)

    def wait_ready(self) -> None:
        """Block until the ICP worker has started and warmed up (start() first; start-up work)."""
        if self.worker is not None:
            self.worker.wait_ready()

    def close(self) -> None:
        if self.worker is not None:
            w = self.worker
            try:
                w.close()
            finally:
                self._worker_final = {"dropped": w.dropped, "failed": w.failed,
                                      "round_trip_s": tuple(getattr(w, "round_trip_s", ()))}
                self.worker = None

    def _worker_stat(self, name: str):
        return getattr(self.worker, name) if self.worker is not None else self._worker_final[name]

    def settle(self, t_s: float) -> None:
        """Lockstep: the simulator calls this once physics has reached t_s, before the tick at
        t_s runs (the ICP barrier: every result due by t_s is then there)."""
        if self.worker is not None:
            self.worker.settle(t_s)

    # -- the tick ------------------------------------------------------------------------------
    def calibrate_bias(self, imu_samples) -> None:
        self.wheels.calibrate_bias(imu_samples)
        self.fusion.gyro_bias.restart(self.wheels.gyro_bias_radps)

    def _follow_gyro_bias(self, now_s: float) -> None:
        """The dead reckoning integrates the gyro with the fusion's newest bias estimate from the
        next sample on (runtime.odometry.gyro_bias); a step is an event."""
        est = self.fusion.gyro_bias
        if not est.config.enabled:
            return
        step = est.last_step
        if step is not None and step != self._bias_step_seen:
            self._bias_step_seen = step
            if self.events is not None:
                self.events.add(now_s, "gyro_bias_step",
                                f"the gyro's yaw rate disagrees with ICP's rotation: bias now {step[1]:+.4f} rad/s "
                                f"(was {self.wheels.gyro_bias_radps:+.4f}); ICP leads the heading until it is learnt")
        self.wheels.gyro_bias_radps = est.bias_radps

    @property
    def yaw_rate_radps(self) -> float:
        return self.wheels.yaw_rate_radps

    @property
    def last_wheels_m(self) -> tuple[float, float] | None:
        """The base's cumulative wheel distances of the newest reading given to update()."""
        return self._last_wheels

    def _unless_frozen(self, now_s: float, wheels: tuple[float, float] | None,
                       speed_mps: float | None) -> tuple[float, float] | None:
        """The wheel distances, or None while they are frozen (OdometryConfig.wheels_frozen_s,
        runtime.odometry.wheels.OdometerWatch), until they change (a robot the stuck readings'
        fault stopped still has them withheld: the next new reading re-anchors, its jump over the
        spell is not counted beside the speed's)."""
        frozen = self._odometer.update(now_s, wheels, speed_mps) if self.config.wheels_frozen_s > 0.0 else False
        if wheels is None:
            return None
        if self.frozen_wheels_since_s is not None:
            if wheels != self._last_wheels:
                self.frozen_wheels_since_s = None
                return wheels
            return None
        if frozen:
            self.frozen_wheels_since_s = self._last_wheels_s
            self.frozen_wheel_spells += 1
            return None
        return wheels

    def base_restarted(self) -> None:
        """The base rebooted: its odometers start again from zero (the next reading re-anchors)."""
        self.wheels.reanchor()

    def resume_from(self, pose: Pose2D, wheels_m: tuple[float, float], max_step_m: float) -> None:
        """Continue an earlier run's odometry frame (runtime.app.resume), before the first update:
        `pose` is where it was when the base's cumulative wheel distances read `wheels_m`. At the
        first wheel reading the pose starts there, moved by what the wheels did since (their own
        heading: the gyro was not read meanwhile); a wheel that moved more than `max_step_m` (the
        base rebooted and counts from zero, or the robot was carried) gives a new frame instead."""
        self._resume = (pose, (float(wheels_m[0]), float(wheels_m[1])), float(max_step_m))

    def _take_up_resume(self, wheels: tuple[float, float]) -> Pose2D | None:
        pose, saved, max_step = self._resume
        self._resume = None
        dl, dr = wheels[0] - saved[0], wheels[1] - saved[1]
        if not (abs(dl) <= max_step and abs(dr) <= max_step):
            self.resume_outcome = (f"a new frame: the base's odometers moved {dl:+.2f} / {dr:+.2f} m since the saved "
                                   f"state, more than the {max_step:.2f} m it could have driven (a rebooted base "
                                   "counts from zero)")
            return None
        between = WheelOdometry(self.wheels.effective_track_m, wheel_scale=self.wheels.wheel_scale)
        between.reset(pose)
        between.update(*saved)
        start = between.update(*wheels)
        self.resume_outcome = (f"continued: the wheels moved {dl:+.3f} / {dr:+.3f} m since the saved pose; starting "
                               f"at {start.x_m:.3f} {start.y_m:.3f} {start.yaw_rad:.3f}")
        return start

    def update(self, now_s: float, wheels: tuple[float, float] | None, imu_samples,
               good_scan: LidarScan | None, speed_mps: float | None = None) -> Pose2D:
        """wheels: the cumulative wheel distances (0x311) when fresh, else None; speed_mps: the
        base's reported linear speed (0x221) when fresh, else None: it carries the translation
        while the wheel distances are missing (never "no data = standing still")."""
        resumed = None
        if self._resume is not None and wheels is not None:
            resumed = self._take_up_resume(wheels)
            if resumed is not None:  # the dead reckoning and a fresh fusion start at the resumed pose
                self.wheels.reset(resumed)
                self.fusion = PoseFusion(self.fusion.config, gyro_bias=self.fusion.gyro_bias)
                self.fusion.start_at(resumed)
        if speed_mps is not None and self._last_update_s is not None:
            self._speed_m += speed_mps * (now_s - self._last_update_s)
        wheels = self._unless_frozen(now_s, wheels, speed_mps)
        fallback = None
        if wheels is None and speed_mps is not None and self._last_update_s is not None:
            # The distances given since their last change added no motion: the first tick
            # without them takes what the base's speed says it moved since that change.
            fallback = self._speed_m - self._speed_m_at_change if self._wheels_used \
                else speed_mps * (now_s - self._last_update_s)
        self._wheels_used = wheels is not None
        self._last_update_s = now_s
        gap = None
        known = wheels is not None or fallback is not None
        fusion = self.fusion
        if not known and self._blind_since_s is None:
            self._blind_since_s = now_s
        elif known and self._blind_since_s is not None:
            # The base speaks again after saying nothing of its motion. Where ICP measured the
            # translation meanwhile (fused after the silence began), the wheels' jump over the
            # silence would count it twice: they re-anchor. Without ICP the jump is all we know.
            if fusion.last_fused_t is not None and fusion.last_fused_t >= self._blind_since_s:
                self.wheels.reanchor()
            self._blind_since_s = None
        if wheels is not None:
            # since the distances last changed (a stuck 0x311's frozen readings are no movement
            # limit: the wheels turned meanwhile)
            gap = None if self._last_wheels_s is None else now_s - self._last_wheels_s
            if wheels != self._last_wheels:
                self._last_wheels, self._last_wheels_s = wheels, now_s
                self._speed_m_at_change = self._speed_m
        d_now = _pose_vec(self.wheels.update_with_imu(wheels, imu_samples, fallback, gap))
        w = self.wheels
        fusion.add_dead_reckoning(now_s, d_now, translation_known=known,
                                  gyro=(w.raw_gyro_yaw_rad, w.gyro_covered_s) if w.imu_samples_used else None)
        self.correction = None
        self.delivered = ()
        if self.worker is not None:
            if good_scan is not None:
                self._submit(good_scan)
            results = self.worker.poll(now_s)
            self.delivered = tuple(results)
            if results:
                before, _ = fusion.pose_now(d_now, now_s)
                for result in results:
                    self._take(result, now_s)
        pose, cov = fusion.pose_now(d_now, now_s)
        self._follow_gyro_bias(now_s)
        if self.worker is not None and results:
            # What the corrections did to the pose now, as a motion of the odom frame: whatever
            # was placed in the odom frame with the pose before them (the obstacle points of the
            # newest frame, which is younger than any ICP result) moves with it.
            self.correction = se2_compose(pose, se2_inverse(before))
        self.pose = Pose2D(float(pose[0]), float(pose[1]), float(pose[2]))
        self._pose_dr = d_now  # the dead-reckoning pose that goes with it
        self.covariance = cov
        self._watch_age(now_s)
        return self.pose

    def pose_at(self, t_s: float) -> Pose2D | None:
        """The pose at a past time within the dead-reckoning history (a camera image's capture):
        the fused pose now, taken back by the wheel + gyro motion from t_s to now (None: no pose
        yet, or t_s outside the history). The further back, the more of the wheels' error it
        carries: meant for the last tick or two."""
        if self._last_update_s is None:
            return None
        d_t = self.fusion.dead_reckoning_at(t_s)
        d_now = self.fusion.dead_reckoning_at(self._last_update_s)
        if d_t is None or d_now is None:
            return None
        now = np.array([self.pose.x_m, self.pose.y_m, self.pose.yaw_rad])
        p = se2_compose(now, se2_between(d_now, d_t))
        return Pose2D(float(p[0]), float(p[1]), float(p[2]))

    def exclude_near(self, points_lidar: np.ndarray | None) -> None:
        """The points the next frames' ICP leaves out the neighbourhood of (None: none)."""
        self._exclude = None if points_lidar is None or not len(points_lidar) else points_lidar

    def exclude_movers(self, points_odom_xy: np.ndarray | None) -> None:
        """People walking, as odom-frame points (N, 2) (None: none): their columns are left out
        of the next frame's ICP (taken to the lidar frame with the pose at the frame's middle)."""
        self._exclude_xy = (None if points_odom_xy is None or not len(points_odom_xy)
                            else np.asarray(points_odom_xy, dtype=np.float64)[:, :2])

    def _movers_in_lidar(self, t_s: float) -> np.ndarray:
        """The movers' points (exclude_movers) in the lidar frame at time t_s, z zero: the pose
        then is the last tick's, carried by the wheels and gyro (turning at 1 rad/s, the last
        tick's pose alone put a person 4 m off 0.2 m astray)."""
        pose = _pose_vec(self.pose)
        d_t = self.fusion.dead_reckoning_at(t_s)
        if self._pose_dr is not None and d_t is not None:
            pose = se2_compose(pose, se2_between(self._pose_dr, d_t))
        c, s = math.cos(pose[2]), math.sin(pose[2])
        d = self._exclude_xy - pose[:2]
        base = np.column_stack([c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1],
                                np.full(len(d), self.mount[2, 3])])
        lidar = (base - self.mount[:3, 3]) @ self.mount[:3, :3]  # R^T (p - t), row-wise
        return np.column_stack([lidar[:, :2], np.zeros(len(lidar))])

    def _submit(self, scan: LidarScan) -> None:
        if self._exclude is not None:
            scan = self._without_movable(scan, self._exclude)
        if self._exclude_xy is not None:
            movers = self._movers_in_lidar(scan.stamp_s + 0.5 * scan.frame_duration_s)
            scan = self._without_movable(scan, movers, self.mover_radius_m, planar=True)
        offs = scan.point_time_offsets_s
        end = scan.stamp_s + (float(offs.max()) if len(offs) else scan.frame_duration_s)
        # The dead-reckoning pose at the frame's end: the engine takes the prior between the
        # frame it registered last and this one (a frame dropped on the way does not shorten it).
        d_end = self.fusion.dead_reckoning_at(end)
        motion = self.fusion.motion_samples(scan.stamp_s, end)  # a few rows: for a wheel/gyro deskew
        job = IcpJob(seq=self._seq, stamp_s=scan.stamp_s, end_s=end, points=scan.points_m, offsets_s=offs,
                     duration_s=scan.frame_duration_s, dead_reckoning_end=d_end, motion=motion,
                     ready_at_s=end + self.config.lockstep_latency_s)
        self._seq += 1
        if self._first_submit_s is None:
            self._first_submit_s = end
        self.frames_submitted += 1
        self.worker.submit(job)

    def _without_movable(self, scan: LidarScan, ref: np.ndarray, radius_m: float | None = None,
                         planar: bool = False) -> LidarScan:
        """scan less its points within radius_m (default exclude_radius_m) of ref (lidar frame;
        planar: in x, y only, ref's z zero; compiled grid search, only the points in ref's box
        grown by the radius are queried: spatial_grid.near_indices)."""
        from runtime.common.spatial_grid import near_indices

        r = self.exclude_radius_m if radius_m is None else radius_m
        p = scan.points_m
        ref = np.ascontiguousarray(ref, dtype=np.float64)
        near = near_indices(p, ref, float(r), bool(planar))
        if not near.size:
            return scan
        keep = np.ones(len(p), bool)
        keep[near] = False
        self.points_excluded += int(near.size)
        return dataclasses.replace(scan, points_m=p[keep], point_time_offsets_s=scan.point_time_offsets_s[keep])

    def _take(self, result, now_s: float) -> None:
        self.compute_ms.append(result.compute_s * 1e3)
        if not self.lockstep:  # real time: the frame's end -> the tick that uses its correction
            self.latency_ms.append((now_s - result.end_s) * 1e3)
        why = self.fusion.icp_update(result)
        if why is not None:
            self.last_refusal = why
        con = result.constraint
        degenerate = con is not None and con.degenerate
        if con is not None:
            self.last_degeneracy = con.describe()
        if degenerate != self._degenerate and self.events is not None:
            if degenerate:
                self.events.add(now_s, "icp_degenerate", f"{con.describe()}: wheels and gyro carry that direction")
            else:
                self.events.add(now_s, "icp_constrained", "the scan constrains the planar motion again")
        self._degenerate = degenerate
        self._count_gate(result, now_s)

    def _count_gate(self, result, now_s: float) -> None:
        """Sum the range gate's counts (a few integers per result); the settings the worker
        resolved; one `icp_range_gate` event when the gate has dropped more than a quarter."""
        if result.settings is not None:
            self.icp_settings = result.settings
        if result.iteration_cap is not None:
            self.iteration_caps = (min(self.iteration_caps[0], result.iteration_cap),
                                   max(self.iteration_caps[1], result.iteration_cap))
        if result.gate is None:
            return
        self.gate = self.gate + result.gate
        warning = None if self._gate_warned else self.gate.warning()
        if warning is not None:
            self._gate_warned = True
            if self.events is not None:
                self.events.add(now_s, "icp_range_gate", warning)

    def _watch_age(self, now_s: float) -> None:
        if self.worker is None:
            return
        t_f = self.fusion.last_fused_t  # refused and failed results do not count
        self.icp_age_s = now_s - t_f if t_f is not None else float("inf")
        # Before the first correction, the age counts from the first frame handed to ICP.
        since = self.icp_age_s if t_f is not None else (
            now_s - self._first_submit_s if self._first_submit_s is not None else 0.0)
        lost = since > self.config.max_icp_age_s
        failed = self.worker.failed
        if lost != self._icp_lost and self.events is not None:
            if lost:
                why = failed or self.last_refusal or "no ICP result"
                self.events.add(now_s, "icp_lost", f"no ICP correction for {self.icp_age_s:.2f} s ({why}): "
                                                   f"wheels and gyro carry the pose")
            else:
                self.events.add(now_s, "icp_restored", "ICP corrections again")
        self._icp_lost = lost

    # -- telemetry -----------------------------------------------------------------------------
    def describe(self) -> dict:
        """Counters and state (deterministic in lockstep: no wall-clock figure here; see wall_clock())."""
        s = self.fusion.stats
        out = {
            "source": self.config.source if self.icp_enabled else "wheels_imu",
            "icp_frames_submitted": self.frames_submitted,
            "icp_results": s.results,
            "icp_fused": s.fused,
            "icp_refused": s.refused,
            "icp_fused_wheels_blind": s.wheels_blind,
            "icp_degenerate_frames": s.degenerate,
            "icp_dropped": self._worker_stat("dropped"),
            "icp_too_old": s.too_old,
            "icp_last_degeneracy": self.last_degeneracy,
            "icp_last_refusal": self.last_refusal,
            "icp_worker_failed": self._worker_stat("failed"),
            "icp_age_s": None if not np.isfinite(self.icp_age_s) else round(float(self.icp_age_s), 4),
            "pose_sigma": [float(np.sqrt(max(self.covariance[i, i], 0.0))) for i in range(3)],
            "wheel_scale": self.wheels.wheel_scale,
            "effective_track_m": self.wheels.effective_track_m,
            "icp_range_gate": self.gate.to_dict(),
            "icp_iteration_cap": None if not self.iteration_caps[1] else list(self.iteration_caps),
            "icp_settings": self.icp_settings,
            "resume": self.resume_outcome,
            "gyro_bias": self.fusion.gyro_bias.describe(),
            "wheels_frozen_spells": self.frozen_wheel_spells,
            "wheels_frozen": self.frozen_wheels_since_s is not None,
        }
        return out


    def wall_clock(self) -> dict:
        """What ICP cost on this computer (a measurement, never in the deterministic metrics):
        the worker's time per frame, and in real time the send-to-result round trip."""
        ms = np.asarray(self.compute_ms) if self.compute_ms else np.zeros(0)
        rt = np.asarray(self._worker_stat("round_trip_s"), dtype=float) * 1e3
        lat = np.asarray(self.latency_ms)
        pct = lambda a, q: round(float(np.percentile(a, q)), 3) if len(a) else None  # noqa: E731
        return {
            "icp_compute_ms": {"p50": pct(ms, 50), "p99": pct(ms, 99), "max": pct(ms, 100), "frames": int(len(ms))},
            "icp_round_trip_ms": {"p50": pct(rt, 50), "p99": pct(rt, 99), "max": pct(rt, 100)},
            "pose_latency_ms": {"p50": pct(lat, 50), "p99": pct(lat, 99), "max": pct(lat, 100)},
        }


__all__ = ["OdometryConfig", "OdometryStage"]
