"""`dct odom eval --scenario`: the odometry streams of one HIL run against the simulator's truth.

The run: the robot stands still for `settle_s` (the gyro bias is learned, as at the controller's
start-up), then a scripted operator drives the scenario's `route` (hil_sim/scenarios/README.md).
The operator steers on the ground-truth pose, as a person with a remote control would: every
odometry stream sees the same drive, whatever its own errors, and the comparison is fair. Its
commands go to the emulated base over CAN (0x111) like the controller's; the sensors are the
simulated Mid-360-class lidar (20k points, 10 Hz) and IMU.

Three streams, side by side:
- `fused`: the controller's odometry stage itself (runtime.odometry.stage.OdometryStage, the
  controller's config), with ICP beside the tick at its fixed simulated latency;
- `wheels_imu`: that stage's dead reckoning alone (wheels 0x311 + gyro);
- `icp`: KISS-ICP alone, as its authors ship it: its own constant-velocity prediction and deskew,
  no wheels (a second pipeline, same voxel and ranges), evaluated at its frames' ends.

The gyro has a turn-on bias (removed by the standstill calibration) and a bias random walk
(`EVAL_IMU`), as a BMI088-class part; the simulator's default IMU has neither.
"""
from __future__ import annotations

import functools
import math
import time
from typing import Callable

import numpy as np

from calibration.errors import ConfigFileError
from calibration.robot_description import RobotDescription, load_robot_description
from firmware_bridge.base_driver import AgileXBaseDriver
from firmware_bridge.firmware_emulator import EmulatedBaseFirmware
from hil_sim.sensors.imu import ImuConfig
from hil_sim.episode.lockstep import LockstepClock, LockstepSimulation, virtual_bus_pair
from hil_sim.world.scenario import Scenario, load_scenario
from hil_sim.world.mujoco_world import World
from runtime.config import ControllerConfig, load_controller_config
from runtime.io.hardware import AgileXBaseHardware
from runtime.odometry.icp import IcpEngine, IcpJob
from runtime.odometry.se2 import wrap
from runtime.odometry.stage import OdometryStage
from runtime.odometry.worker import InlineIcpWorker
from runtime.io.sensor_inbox import SensorInbox

#: A BMI088-class gyro: turn-on bias (calibrated away at standstill) and bias instability.
EVAL_IMU = ImuConfig(gyro_bias_radps=(0.004, -0.003, 0.005), gyro_bias_walk_radps_per_sqrt_s=2e-5)


class RouteError(ConfigFileError):
    """The scenario has no route to drive."""


class RouteOperator:
    """Drives a polyline on the true pose: turn in place towards the next waypoint when the
    heading is off by more than `turn_in_place_rad`, else pure pursuit at the cruise speed."""

    def __init__(self, polyline: np.ndarray, speed_mps: float, lookahead_m: float = 0.35,
                 turn_in_place_rad: float = 0.35, max_turn_radps: float = 0.8, tolerance_m: float = 0.08) -> None:
        self.points = np.asarray(polyline, dtype=float)
        self.speed = speed_mps
        self.lookahead = lookahead_m
        self.turn_in_place = turn_in_place_rad
        self.max_turn = max_turn_radps
        self.tolerance = tolerance_m
        self.target = 1  # index of the waypoint being driven to
        self.done = False

    def command(self, x: float, y: float, yaw: float) -> tuple[float, float]:
        while self.target < len(self.points):
            tx, ty = self.points[self.target]
            if math.hypot(tx - x, ty - y) > self.tolerance:
                break
            self.target += 1
        if self.target >= len(self.points):
            self.done = True
            return 0.0, 0.0
        a, b = self.points[self.target - 1], self.points[self.target]
        seg = b - a
        L = float(np.hypot(*seg))
        s = float(np.clip(np.dot([x, y] - a, seg) / max(L * L, 1e-9), 0.0, 1.0)) * L
        look = min(s + self.lookahead, L)
        gx, gy = a + seg * (look / max(L, 1e-9))
        if look >= L - 1e-6:
            gx, gy = b
        heading_err = wrap(math.atan2(gy - y, gx - x) - yaw)
        if abs(heading_err) > self.turn_in_place:
            return 0.0, float(np.clip(2.0 * heading_err, -self.max_turn, self.max_turn))
        remaining = math.hypot(b[0] - x, b[1] - y)
        v = min(self.speed, max(0.1, 1.2 * remaining)) if self.target == len(self.points) - 1 else self.speed
        return v, float(np.clip(2.5 * heading_err, -self.max_turn, self.max_turn))


def _stream_errors(estimate: np.ndarray, reference: np.ndarray) -> dict:
    """Errors of planar poses (N, 3) against the reference (both taken relative to their first)."""
    from runtime.odometry.metrics import planar_to_se3, trajectory_errors

    return trajectory_errors(planar_to_se3(estimate), planar_to_se3(reference))


def evaluate_scenario(
    scenario: Scenario | str,
    seed: int = 0,
    config: ControllerConfig | None = None,
    robot: RobotDescription | None = None,
    progress: Callable[[float, float], None] | None = None,
    settle_s: float = 1.0,
    record: dict | None = None,
    on_tick: Callable[[float, tuple[float, float] | None, tuple, object], None] | None = None,
) -> dict:
    """Run the route of `scenario` and return the JSON-ready comparison (module docstring).

    record: if a dict, filled with the per-tick arrays of the run (for `--record`: wheels, gyro,
    ground truth and the fused pose).
    on_tick: called every tick with what the odometry stage reads (time, wheel distances, IMU
    samples, lidar frame or None): `dct bench odometry` records the run with it.
    """
    if isinstance(scenario, str):
        scenario = load_scenario(scenario)
    if scenario.route is None:
        raise RouteError(f"scenario {scenario.name} has no route: odometry evaluation drives a route "
                         f"(add `route:` to the scenario, hil_sim/scenarios/README.md)")
    robot = robot or load_robot_description()
    config = config or load_controller_config()
    drive = _RouteDrive(scenario, seed, config, robot)
    wall = drive.run(settle_s, progress, on_tick)
    return drive.report(settle_s, wall, record)


class _RouteDrive:
    """One drive of a scenario's route in lockstep: the world, the emulated base over CAN, the
    odometry stage beside KISS-ICP alone, and what every tick recorded (module docstring)."""

    def __init__(self, scenario: Scenario, seed: int, config: ControllerConfig, robot: RobotDescription) -> None:
        from hil_sim.world.sensor_rig import SensorRig, SensorRigConfig

        self.scenario, self.seed, self.config, self.robot = scenario, seed, config, robot
        oc = self.oc = config.odometry
        self.world = World(scenario, robot, ground_clearance_m=config.planner.obstacle_points.ground_clearance_m)
        self.world.reset(seed)
        self.controller_bus, self.sim_bus = virtual_bus_pair()
        firmware = EmulatedBaseFirmware(self.sim_bus, robot)
        self.inbox = SensorInbox()
        rig = SensorRig(self.world, robot, self.inbox, SensorRigConfig(seed=seed, imu=EVAL_IMU))
        self.sim = LockstepSimulation(self.world, firmware, None, [rig])
        self.clock = LockstepClock(self.sim)
        driver = AgileXBaseDriver(self.controller_bus, clock=self.clock.now,
                                  feedback_timeout_s=robot.can.feedback_timeout_s)
        self.hardware = AgileXBaseHardware(driver, robot.drive.skid_steer_yaw_factor)
        mount = robot.sensors.lidar.mount.transform()
        self.stage = OdometryStage(oc.model_copy(update={"source": "fused"}), robot.drive.track_m,
                                   robot.drive.skid_steer_yaw_factor, mount, lockstep=True)
        # KISS-ICP alone: its own prediction and deskew (no wheel prior), same map settings.
        self.icp_alone = InlineIcpWorker(functools.partial(
            IcpEngine, oc.icp.model_copy(update={"deskew": "kiss"}), oc.degeneracy, mount, False))
        self.clock.barriers += [self.stage, self.icp_alone]

        self.start = np.array([scenario.robot_start.x_m, scenario.robot_start.y_m])
        polyline = scenario.route.polyline(tuple(self.start))
        self.operator = RouteOperator(polyline, scenario.route.speed_mps)
        self.t0 = self.sim.time_s
        self.ticks: list[tuple] = []
        self.icp_rows: list[tuple] = []
        self.stage_wall: list[float] = []
        self.seq = 0
        self.gyro_rows: list[float] = []

    def run(self, settle_s: float, progress, on_tick) -> float:
        """Stand for settle_s, then drive the route until it is done or the time limit; the wall seconds."""
        period = self.config.loop.period_s
        limit = self.t0 + self.scenario.time_limit_s
        wall0 = time.perf_counter()
        try:
            self.stage.start()
            self.hardware.configure()
            self.hardware.activate()
            k = 0
            while True:
                now = self.t0 + k * period
                self.clock.sleep_until(now)
                inputs, standing, (gx, gy, gyaw) = self._tick(now, settle_s, on_tick)
                if progress is not None:
                    progress(now - self.t0, self.scenario.time_limit_s)
                if now >= limit or (self.operator.done and abs(inputs.linear_mps) < 1e-3):
                    break
                v, w = (0.0, 0.0) if standing else self.operator.command(gx, gy, gyaw)
                self.hardware.write(v, w)
                k += 1
            # Let ICP deliver the last frames (a barrier: the results due by then).
            self.clock.sleep_until(self.sim.time_s + self.oc.lockstep_latency_s + 0.05)
            self._collect_icp(self.sim.time_s)
        finally:
            self.hardware.deactivate()
            self.stage.close()
            self.icp_alone.close()
            self.controller_bus.shutdown()
            self.sim_bus.shutdown()
        return time.perf_counter() - wall0

    def _tick(self, now: float, settle_s: float, on_tick):
        """Read the base and the sensors, update the odometry stage and ICP alone, record the tick;
        returns (the base's inputs, standing still, the true pose)."""
        inputs = self.hardware.read(now)
        snap = self.inbox.take()
        standing = now - self.t0 < settle_s
        imu = snap.imu
        if on_tick is not None:
            on_tick(now, inputs.odometry, tuple(imu), snap.scan)
        w0 = time.perf_counter()
        if standing:
            self.stage.calibrate_bias(imu)
            imu = ()
        limits = self.config.inputs  # the controller's freshness rule for 0x311 and 0x221
        wheels = inputs.odometry if inputs.odometry_age_s <= limits.odometry_timeout_s else None
        speed = inputs.linear_mps if inputs.motion_state_age_s <= limits.motion_state_timeout_s else None
        pose = self.stage.update(now, wheels, imu, snap.scan, speed)
        self.stage_wall.append(time.perf_counter() - w0)
        if snap.scan is not None and snap.scan.num_points:
            self._submit_icp(snap.scan)
        self._collect_icp(now)
        gx, gy, gyaw = self.world.robot_pose()
        wp = self.stage.wheels.pose
        gz = float(np.mean([s.gyro_radps[2] for s in snap.imu])) if snap.imu else float("nan")
        self.gyro_rows.append(gz)
        odo = inputs.odometry or (float("nan"), float("nan"))
        self.ticks.append((now, gx, gy, gyaw, pose.x_m, pose.y_m, pose.yaw_rad, wp.x_m, wp.y_m, wp.yaw_rad,
                           odo[0], odo[1]))
        return inputs, standing, (gx, gy, gyaw)

    def _submit_icp(self, scan) -> None:
        offs = scan.point_time_offsets_s
        end = scan.stamp_s + float(offs.max())
        self.icp_alone.submit(IcpJob(seq=self.seq, stamp_s=scan.stamp_s, end_s=end, points=scan.points_m,
                                     offsets_s=offs, duration_s=scan.frame_duration_s,
                                     ready_at_s=end + self.oc.lockstep_latency_s))
        self.seq += 1

    def _collect_icp(self, t_s: float) -> None:
        for r in self.icp_alone.poll(t_s):
            if r.error is None:
                self.icp_rows.append((r.end_s, *r.pose_base))

    def report(self, settle_s: float, wall: float, record: dict | None) -> dict:
        """The comparison of the three streams with the truth, and the stage's figures (module docstring)."""
        scenario, oc = self.scenario, self.oc
        arr = np.array(self.ticks)
        t = arr[:, 0]
        moving_from = self.t0 + settle_s
        sel = t >= moving_from - 1e-9
        gt = arr[sel, 1:4]
        fused = arr[sel, 4:7]
        wheels = arr[sel, 7:10]
        out: dict = {"scenario": scenario.name, "seed": self.seed}
        out["fused"] = _stream_errors(fused, gt)
        out["wheels_imu"] = _stream_errors(wheels, gt)
        out["icp"] = _icp_errors(self.icp_rows, arr, moving_from)
        ms = np.asarray(self.stage_wall) * 1e3
        desc = self.stage.describe()
        wc = self.stage.wall_clock()
        out["stage_ms"] = {"p50": float(np.percentile(ms, 50)), "p99": float(np.percentile(ms, 99)),
                           "max": float(ms.max()), "budget": self.config.loop.stage_budgets_s.get("odometry", 0.0) * 1e3}
        out["pose_latency_ms"] = {
            "lockstep_fixed": oc.lockstep_latency_s * 1e3,
            "icp_compute_p50": wc["icp_compute_ms"]["p50"],
            "icp_compute_p99": wc["icp_compute_ms"]["p99"],
            "note": "lockstep: ICP results are delivered at end of frame + the fixed latency; the compute "
                    "time is what the worker spent per frame on this machine (real-time latency: dct bench odometry)",
        }
        out["odometry"] = desc
        out["degenerate_fraction"] = (desc["icp_degenerate_frames"] / desc["icp_results"]) if desc["icp_results"] else None
        out["route_length_m"] = float(scenario.route.length_m(tuple(self.start)))
        out["route_completed"] = bool(self.operator.done)
        out["sim_time_s"] = float(t[-1] - self.t0)
        out["wall_time_s"] = wall
        out["config"] = {"icp": oc.icp.model_dump(), "fusion": oc.fusion.model_dump(),
                         "lockstep_latency_s": oc.lockstep_latency_s, "imu": EVAL_IMU.model_dump()}
        if record is not None:
            record.update(t_s=t[sel], left_wheel_m=arr[sel, 10], right_wheel_m=arr[sel, 11],
                          gyro_z_radps=np.asarray(self.gyro_rows)[sel], ref_pose=gt,
                          source=f"{scenario.name} seed {self.seed}", robot=self.robot.name)
        return out


def _icp_errors(icp_rows: list[tuple], arr: np.ndarray, moving_from: float) -> dict | None:
    """KISS-ICP alone against the truth at its frames' ends during the drive (None: under 2 frames)."""
    t = arr[:, 0]
    icp = np.array(icp_rows) if icp_rows else np.zeros((0, 4))
    icp = icp[(icp[:, 0] >= moving_from) & (icp[:, 0] <= t[-1])] if len(icp) else icp
    if len(icp) < 2:
        return None
    # ICP's frame 0 is its origin: compare from the first frame after the start of the drive.
    from runtime.odometry.metrics import interpolate_poses, planar_to_se3, trajectory_errors

    gt_at = interpolate_poses(t, planar_to_se3(arr[:, 1:4]), icp[:, 0])
    out = trajectory_errors(planar_to_se3(icp[:, 1:4]), gt_at)
    out["frames"] = int(len(icp))
    return out


__all__ = ["evaluate_scenario", "RouteOperator", "RouteError", "EVAL_IMU"]
