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
    from hil_sim.world.sensor_rig import SensorRig, SensorRigConfig

    if isinstance(scenario, str):
        scenario = load_scenario(scenario)
    if scenario.route is None:
        raise RouteError(f"scenario {scenario.name} has no route: odometry evaluation drives a route "
                         f"(add `route:` to the scenario, hil_sim/scenarios/README.md)")
    robot = robot or load_robot_description()
    config = config or load_controller_config()
    oc = config.odometry

    world = World(scenario, robot, ground_clearance_m=config.planner.obstacle_points.ground_clearance_m)
    world.reset(seed)
    controller_bus, sim_bus = virtual_bus_pair()
    firmware = EmulatedBaseFirmware(sim_bus, robot)
    inbox = SensorInbox()
    rig = SensorRig(world, robot, inbox, SensorRigConfig(seed=seed, imu=EVAL_IMU))
    sim = LockstepSimulation(world, firmware, None, [rig])
    clock = LockstepClock(sim)
    driver = AgileXBaseDriver(controller_bus, clock=clock.now, feedback_timeout_s=robot.can.feedback_timeout_s)
    hardware = AgileXBaseHardware(driver, robot.drive.skid_steer_yaw_factor)
    mount = robot.sensors.lidar.mount.transform()
    stage = OdometryStage(oc.model_copy(update={"source": "fused"}), robot.drive.track_m,
                          robot.drive.skid_steer_yaw_factor, mount, lockstep=True)
    # KISS-ICP alone: its own prediction and deskew (no wheel prior), same map settings.
    icp_alone = InlineIcpWorker(functools.partial(
        IcpEngine, oc.icp.model_copy(update={"deskew": "kiss"}), oc.degeneracy, mount, False))
    clock.barriers += [stage, icp_alone]

    start = np.array([scenario.robot_start.x_m, scenario.robot_start.y_m])
    polyline = scenario.route.polyline(tuple(start))
    operator = RouteOperator(polyline, scenario.route.speed_mps)
    period = config.loop.period_s
    t0 = sim.time_s
    limit = t0 + scenario.time_limit_s
    ticks: list[tuple] = []
    icp_rows: list[tuple] = []
    stage_wall: list[float] = []
    seq = 0
    gyro_rows: list[float] = []
    wall0 = time.perf_counter()
    try:
        stage.start()
        hardware.configure()
        hardware.activate()
        k = 0
        while True:
            now = t0 + k * period
            clock.sleep_until(now)
            inputs = hardware.read(now)
            snap = inbox.take()
            standing = now - t0 < settle_s
            imu = snap.imu
            if on_tick is not None:
                on_tick(now, inputs.odometry, tuple(imu), snap.scan)
            w0 = time.perf_counter()
            if standing:
                stage.calibrate_bias(imu)
                imu = ()
            limits = config.inputs  # the controller's freshness rule for 0x311 and 0x221
            wheels = inputs.odometry if inputs.odometry_age_s <= limits.odometry_timeout_s else None
            speed = inputs.linear_mps if inputs.motion_state_age_s <= limits.motion_state_timeout_s else None
            pose = stage.update(now, wheels, imu, snap.scan, speed)
            stage_wall.append(time.perf_counter() - w0)
            if snap.scan is not None and snap.scan.num_points:
                offs = snap.scan.point_time_offsets_s
                end = snap.scan.stamp_s + float(offs.max())
                icp_alone.submit(IcpJob(seq=seq, stamp_s=snap.scan.stamp_s, end_s=end, points=snap.scan.points_m,
                                        offsets_s=offs, duration_s=snap.scan.frame_duration_s,
                                        ready_at_s=end + oc.lockstep_latency_s))
                seq += 1
            for r in icp_alone.poll(now):
                if r.error is None:
                    icp_rows.append((r.end_s, *r.pose_base))
            gx, gy, gyaw = world.robot_pose()
            wp = stage.wheels.pose
            gz = float(np.mean([s.gyro_radps[2] for s in snap.imu])) if snap.imu else float("nan")
            gyro_rows.append(gz)
            odo = inputs.odometry or (float("nan"), float("nan"))
            ticks.append((now, gx, gy, gyaw, pose.x_m, pose.y_m, pose.yaw_rad, wp.x_m, wp.y_m, wp.yaw_rad,
                          odo[0], odo[1]))
            if progress is not None:
                progress(now - t0, scenario.time_limit_s)
            if now >= limit or (operator.done and abs(inputs.linear_mps) < 1e-3):
                break
            v, w = (0.0, 0.0) if standing else operator.command(gx, gy, gyaw)
            hardware.write(v, w)
            k += 1
        # Let ICP deliver the last frames (a barrier: the results due by then).
        clock.sleep_until(sim.time_s + oc.lockstep_latency_s + 0.05)
        for r in icp_alone.poll(sim.time_s):
            if r.error is None:
                icp_rows.append((r.end_s, *r.pose_base))
    finally:
        hardware.deactivate()
        stage.close()
        icp_alone.close()
        controller_bus.shutdown()
        sim_bus.shutdown()
    wall = time.perf_counter() - wall0

    arr = np.array(ticks)
    t = arr[:, 0]
    moving_from = t0 + settle_s
    sel = t >= moving_from - 1e-9
    gt = arr[sel, 1:4]
    fused = arr[sel, 4:7]
    wheels = arr[sel, 7:10]
    out: dict = {"scenario": scenario.name, "seed": seed}
    out["fused"] = _stream_errors(fused, gt)
    out["wheels_imu"] = _stream_errors(wheels, gt)
    icp = np.array(icp_rows) if icp_rows else np.zeros((0, 4))
    icp = icp[(icp[:, 0] >= moving_from) & (icp[:, 0] <= t[-1])] if len(icp) else icp
    if len(icp) >= 2:
        # ICP's frame 0 is its origin: compare from the first frame after the start of the drive.
        from runtime.odometry.metrics import interpolate_poses, planar_to_se3, trajectory_errors

        gt_at = interpolate_poses(t, planar_to_se3(arr[:, 1:4]), icp[:, 0])
        out["icp"] = trajectory_errors(planar_to_se3(icp[:, 1:4]), gt_at)
        out["icp"]["frames"] = int(len(icp))
    else:
        out["icp"] = None
    ms = np.asarray(stage_wall) * 1e3
    desc = stage.describe()
    wc = stage.wall_clock()
    out["stage_ms"] = {"p50": float(np.percentile(ms, 50)), "p99": float(np.percentile(ms, 99)),
                       "max": float(ms.max()), "budget": config.loop.stage_budgets_s.get("odometry", 0.0) * 1e3}
    out["pose_latency_ms"] = {
        "lockstep_fixed": oc.lockstep_latency_s * 1e3,
        "icp_compute_p50": wc["icp_compute_ms"]["p50"],
        "icp_compute_p99": wc["icp_compute_ms"]["p99"],
        "note": "lockstep: ICP results are delivered at end of frame + the fixed latency; the compute "
                "time is what the worker spent per frame on this machine (real-time latency: dct bench odometry)",
    }
    out["odometry"] = desc
    out["degenerate_fraction"] = (desc["icp_degenerate_frames"] / desc["icp_results"]) if desc["icp_results"] else None
    out["route_length_m"] = float(scenario.route.length_m(tuple(start)))
    out["route_completed"] = bool(operator.done)
    out["sim_time_s"] = float(t[-1] - t0)
    out["wall_time_s"] = wall
    out["config"] = {"icp": oc.icp.model_dump(), "fusion": oc.fusion.model_dump(),
                     "lockstep_latency_s": oc.lockstep_latency_s, "imu": EVAL_IMU.model_dump()}
    if record is not None:
        record.update(t_s=t[sel], left_wheel_m=arr[sel, 10], right_wheel_m=arr[sel, 11],
                      gyro_z_radps=np.asarray(gyro_rows)[sel], ref_pose=gt,
                      source=f"{scenario.name} seed {seed}", robot=robot.name)
    return out


__all__ = ["evaluate_scenario", "RouteOperator", "RouteError", "EVAL_IMU"]
