"""Lockstep simulation speed: simulated seconds per wall-clock second, robot driving."""
from __future__ import annotations

import math
import statistics
from dataclasses import dataclass
from typing import Callable

from hil_sim.episode.lockstep import run_episode
from hil_sim.world.scenario import load_scenario


def run_sim_speed_benchmark(scenario_name: str, seconds: float, repeats: int, echo: Callable[[str], None] = print) -> dict:
    scenario = load_scenario(scenario_name)
    # Run for a fixed simulated time with the controller driving towards the goal.
    scenario = scenario.model_copy(update={"time_limit_s": seconds})
    factors, steps_per_s, paths = [], [], []
    for i in range(repeats):
        result = run_episode(scenario, seed=i)
        factors.append(result.realtime_factor)
        steps_per_s.append(result.extra["physics_steps"] / result.wall_time_s)
        paths.append(result.metrics["path_length_m"])
        echo(
            f"run {i}: {result.sim_time_s:.1f} s simulated in {result.wall_time_s:.2f} s wall "
            f"= {result.realtime_factor:.1f}x real time (robot drove {result.metrics['path_length_m']:.2f} m)"
        )
    summary = {
        "scenario": scenario_name,
        "realtime_factor_median": statistics.median(factors),
        "realtime_factor_min": min(factors),
        "physics_steps_per_s_median": statistics.median(steps_per_s),
        "path_length_m_median": statistics.median(paths),
    }
    echo(
        f"sim-speed {scenario_name}: median {summary['realtime_factor_median']:.1f}x real time "
        f"(min {summary['realtime_factor_min']:.1f}x), {summary['physics_steps_per_s_median']:.0f} physics steps/s"
    )
    return summary


@dataclass(frozen=True)
class _Drive:
    """How run_sensor_sim_speed_benchmark drives: simulated seconds, the 0x111 period and command,
    the camera's rate."""

    seconds: float
    period_s: float
    linear_mps: float
    angular_radps: float
    camera_rate_hz: float


def run_sensor_sim_speed_benchmark(
    scenario_name: str = "case1",
    seconds: float = 10.0,
    repeats: int = 3,
    echo: Callable[[str], None] = print,
    linear_mps: float = 0.5,
    angular_radps: float = -2.5,
    camera_rate_hz: float = 2.0,
    baseline: bool = True,
) -> dict:
    """Lockstep speed (multiple of real time) with the robot's sensors running.

    Physics + emulated base firmware + a SensorRig device (lidar 10 Hz x 20k rays, IMU 200 Hz,
    camera `camera_rate_hz` RGB) stepped every physics step, the robot driven over the virtual
    CAN bus by AgileXBaseDriver sending 0x111 at 50 Hz (constant `linear_mps`, `angular_radps`:
    the skid-steer base turns at only about a third of the commanded yaw rate, so -2.5 rad/s
    gives a right-hand circle of about 0.6 m radius in case1, clear of every obstacle for any
    duration) and the inbox drained every tick
    like the controller's read(). No planner: this isolates the simulator's cost. With
    `baseline`, each repeat also runs the same loop without the rig, for the sensors' overhead.
    """
    from calibration.robot_description import load_robot_description

    if seconds <= 0 or repeats < 1:
        raise ValueError(f"run_sensor_sim_speed_benchmark: need seconds > 0 and repeats >= 1, got {seconds}, {repeats}")
    scenario = load_scenario(scenario_name)
    robot = load_robot_description()
    drive = _Drive(seconds, robot.can.command_period_s, linear_mps, angular_radps, camera_rate_hz)

    runs, bases = [], []
    for i in range(repeats):
        r = _sensor_run(scenario, robot, i, True, drive)
        runs.append(r)
        echo(f"run {i}: {r['sim_s']:.1f} s simulated in {r['wall_s']:.2f} s wall = {r['realtime_factor']:.2f}x real "
             f"time; {r['scans_produced']} scans ({r['lidar_ms_per_frame']:.1f} ms each), {r['imu_samples_produced']} "
             f"IMU samples, {r['images_produced']} images ({r['renders']} renders, "
             f"{r['camera_ms_per_image']:.1f} ms each); robot {r['driven_m']:.2f} m from start")
        if baseline:
            b = _sensor_run(scenario, robot, i, False, drive)
            bases.append(b)
            echo(f"run {i} without sensors: {b['realtime_factor']:.2f}x real time")
    summary = _sensor_summary(scenario_name, seconds, runs, bases)
    echo(f"sim-speed --sensors {scenario_name}: median {summary['realtime_factor_median']:.2f}x real time "
         f"(min {summary['realtime_factor_min']:.2f}x) with lidar 10 Hz, IMU 200 Hz, camera {camera_rate_hz:g} Hz; "
         f"{summary['lidar_ms_per_frame_median']:.1f} ms per lidar frame in the loop, "
         f"{summary['renders_total']} renders" + (
             f"; without sensors {summary['realtime_factor_without_sensors_median']:.2f}x" if bases else ""))
    return summary


def _sensor_run(scenario, robot, seed: int, with_sensors: bool, drive: _Drive) -> dict:
    """One timed drive: the wall and simulated seconds, what the inbox got, and (with the sensors)
    the rig's figures per frame."""
    import time

    from firmware_bridge.base_driver import AgileXBaseDriver
    from firmware_bridge.firmware_emulator import EmulatedBaseFirmware
    from hil_sim.episode.lockstep import LockstepSimulation, virtual_bus_pair
    from hil_sim.world.mujoco_world import World
    from hil_sim.world.sensor_rig import SensorRig, SensorRigConfig
    from runtime.io.sensor_inbox import SensorInbox

    world = World(scenario, robot, seed=seed)
    controller_bus, sim_bus = virtual_bus_pair()
    firmware = EmulatedBaseFirmware(sim_bus, robot)
    inbox = SensorInbox()
    rig = None
    if with_sensors:
        rig = SensorRig(world, robot, inbox, SensorRigConfig(camera_rate_hz=drive.camera_rate_hz, seed=seed))
    sim = LockstepSimulation(world, firmware, devices=[rig] if rig is not None else [])
    driver = AgileXBaseDriver(controller_bus, clock=lambda: sim.time_s,
                              feedback_timeout_s=robot.can.feedback_timeout_s)
    scans = images = imu = 0
    try:
        wall0 = time.perf_counter()
        driver.enable()
        t0 = sim.time_s
        tick = 0
        while sim.time_s < t0 + drive.seconds - 0.5 * world.timestep_s:
            driver.poll()
            snap = inbox.take()
            scans += snap.scan is not None
            images += snap.image is not None
            imu += len(snap.imu)
            driver.send_motion(drive.linear_mps, drive.angular_radps)
            tick += 1
            sim.advance_to(t0 + tick * drive.period_s)
        wall = time.perf_counter() - wall0
        x, y, _ = world.robot_pose()
        st = rig.stats() if rig is not None else None
    finally:
        if rig is not None:
            rig.close()
        controller_bus.shutdown()
        sim_bus.shutdown()
    out = {"wall_s": wall, "sim_s": sim.time_s - t0, "realtime_factor": (sim.time_s - t0) / wall,
           "scans_taken": scans, "images_taken": images, "imu_taken": imu,
           "driven_m": math.hypot(x - scenario.robot_start.x_m, y - scenario.robot_start.y_m)}
    if st is not None:
        out.update(st)
        out["lidar_ms_per_frame"] = 1e3 * st["time_spent_s"]["lidar"] / max(1, st["scans_produced"])
        out["camera_ms_per_image"] = 1e3 * st["time_spent_s"]["camera"] / max(1, st["images_produced"])
        out["imu_ms_per_sim_s"] = 1e3 * st["time_spent_s"]["imu"] / out["sim_s"]
    return out


def _sensor_summary(scenario_name: str, seconds: float, runs: list[dict], bases: list[dict]) -> dict:
    """Medians and totals over the runs (and the runs without sensors)."""
    summary = {
        "scenario": scenario_name,
        "seconds": seconds,
        "realtime_factor_median": statistics.median(r["realtime_factor"] for r in runs),
        "realtime_factor_min": min(r["realtime_factor"] for r in runs),
        "lidar_ms_per_frame_median": statistics.median(r["lidar_ms_per_frame"] for r in runs),
        "camera_ms_per_image_median": statistics.median(r["camera_ms_per_image"] for r in runs),
        "imu_ms_per_sim_s_median": statistics.median(r["imu_ms_per_sim_s"] for r in runs),
        "renders_total": sum(r["renders"] for r in runs),
        "scans_total": sum(r["scans_produced"] for r in runs),
        "images_total": sum(r["images_produced"] for r in runs),
        "imu_samples_total": sum(r["imu_samples_produced"] for r in runs),
    }
    if bases:
        summary["realtime_factor_without_sensors_median"] = statistics.median(b["realtime_factor"] for b in bases)
    return summary
