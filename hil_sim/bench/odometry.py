"""`dct bench odometry`: the odometry stage in real time, as on the robot.

1. Record: a lockstep drive along a scenario's route (hil_sim.eval.odometry's scripted operator),
   keeping per tick what the controller's odometry stage reads: the wheel distances, the IMU
   samples and the lidar frame (20k rays, 10 Hz, Mid-360 class).
2. Replay on the wall clock: a 20 Hz loop calls `OdometryStage.update` (real time: KISS-ICP in
   its worker process, results used when they arrive) with the recorded data re-stamped to the
   wall clock, optionally with N busy processes beside it (`--hog N`, the robot's other software).

Figures (measurements, printed; no pass/fail): the stage's time in the tick (p50, p90, p99, max
and overruns of its budget), the worker's time per frame, the pose latency (a frame's end ->
the tick whose pose includes its ICP correction), frames dropped while the worker was busy, and
missed tick starts.
"""
from __future__ import annotations

import dataclasses
import subprocess
import sys
import time
from dataclasses import dataclass

import numpy as np

from runtime.common.sensor_data import ImuSample, LidarScan


@dataclass
class RecordedTick:
    t_s: float
    wheels: tuple[float, float] | None
    imu: tuple[ImuSample, ...]
    scan: LidarScan | None


def record_ticks(scenario: str, seconds: float, seed: int = 0) -> tuple[list[RecordedTick], float]:
    """Drive the route for `seconds` (lockstep) and keep the stage's inputs per tick."""
    from hil_sim.eval.odometry import evaluate_scenario
    from hil_sim.world.scenario import load_scenario

    ticks: list[RecordedTick] = []
    sc = load_scenario(scenario)
    sc = sc.model_copy(update={"time_limit_s": min(sc.time_limit_s, seconds)})
    evaluate_scenario(sc, seed=seed, on_tick=lambda t, w, imu, scan: ticks.append(RecordedTick(t, w, imu, scan)))
    points = [len(t.scan.points_m) for t in ticks if t.scan is not None]
    return ticks, float(np.mean(points)) if points else 0.0


def _restamp(item, shift_s: float):
    """A scan or an IMU sample moved in time by shift_s (recorded time -> wall clock)."""
    return dataclasses.replace(item, stamp_s=item.stamp_s + shift_s)


def replay(ticks: list[RecordedTick], hogs: int = 0, config=None, robot=None, settle_s: float = 1.0) -> dict:
    """Replay on the wall clock at the recorded tick times (the first settle_s standing still:
    the gyro bias is learned, as at the controller's start); returns the figures."""
    from calibration.robot_description import load_robot_description
    from runtime.config import load_controller_config
    from runtime.odometry.stage import OdometryStage

    config = config or load_controller_config()
    robot = robot or load_robot_description()
    stage = OdometryStage(config.odometry, robot.drive.track_m, robot.drive.skid_steer_yaw_factor,
                          robot.sensors.lidar.mount.transform(), lockstep=False)
    budget_ms = config.loop.stage_budgets_s.get("odometry", 0.01) * 1e3
    hog_procs: list[subprocess.Popen] = []
    try:
        hog_procs += [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(hogs)]
        stage.start()
        # Wait for the worker to be up (its start is part of activation, not of a tick).
        time.sleep(1.5)
        stage_ms, late_starts = _replay_ticks(stage, ticks, settle_s)
    finally:
        stage.close()
        for p in hog_procs:
            p.kill()
            p.wait(timeout=5.0)
    ms = np.asarray(stage_ms)
    wc = stage.wall_clock()
    return {
        "hogs": hogs,
        "ticks": len(ms),
        "stage_ms": {"p50": float(np.percentile(ms, 50)), "p90": float(np.percentile(ms, 90)),
                     "p99": float(np.percentile(ms, 99)), "max": float(ms.max()), "budget_ms": budget_ms,
                     "overruns": int((ms > budget_ms).sum())},
        "icp_compute_ms": wc["icp_compute_ms"],
        "pose_latency_ms": wc["pose_latency_ms"],
        "frames_submitted": stage.frames_submitted,
        "frames_dropped": stage.describe()["icp_dropped"],
        "icp_fused": stage.describe()["icp_fused"],
        "late_tick_starts": late_starts,
    }


def _replay_ticks(stage, ticks: list[RecordedTick], settle_s: float) -> tuple[list[float], int]:
    """Feed the stage each tick at its recorded time moved onto the wall clock; (ms in the stage per
    tick, ticks started more than 50 ms late)."""
    stage_ms: list[float] = []
    late_starts = 0
    t_rec0 = ticks[0].t_s
    wall0 = time.perf_counter() + 0.05
    shift = wall0 - t_rec0
    for tick in ticks:
        due = tick.t_s + shift
        now = time.perf_counter()
        if now < due:
            time.sleep(due - now)
        elif now - due > 0.05:
            late_starts += 1
        now = time.perf_counter()
        scan = _restamp(tick.scan, shift) if tick.scan is not None else None
        imu = tuple(_restamp(s, shift) for s in tick.imu)
        w0 = time.perf_counter()
        if tick.t_s - t_rec0 < settle_s:
            stage.calibrate_bias(imu)
            imu = ()
        stage.update(now, tick.wheels, imu, scan)
        stage_ms.append((time.perf_counter() - w0) * 1e3)
    time.sleep(0.5)  # the last results
    stage.update(time.perf_counter(), ticks[-1].wheels, (), None)
    return stage_ms, late_starts


def print_odometry_benchmark(scenario: str, seconds: float, hogs: tuple[int, ...], echo) -> dict:
    echo(f"recording {seconds:g} s of {scenario} (lockstep) ...")
    ticks, points = record_ticks(scenario, seconds)
    frames = sum(t.scan is not None for t in ticks)
    echo(f"{len(ticks)} ticks, {frames} lidar frames, {points:.0f} points per frame on average")
    rows = []
    for n in hogs:
        r = replay(ticks, hogs=n)
        r["points_per_frame"] = points
        rows.append(r)
        s, c, lat = r["stage_ms"], r["icp_compute_ms"], r["pose_latency_ms"]
        echo(f"hog {n}: stage in tick p50 {s['p50']:.2f} p90 {s['p90']:.2f} p99 {s['p99']:.2f} max {s['max']:.2f} ms "
             f"(budget {s['budget_ms']:.0f} ms, {s['overruns']} overruns) | ICP worker per frame p50 {c['p50']} "
             f"p99 {c['p99']} ms | pose latency p50 {lat['p50']} p99 {lat['p99']} max {lat['max']} ms | "
             f"{r['frames_dropped']} of {r['frames_submitted']} frames dropped, {r['late_tick_starts']} late ticks")
    return {"scenario": scenario, "seconds": seconds, "points_per_frame": points, "rows": rows}


__all__ = ["record_ticks", "replay", "print_odometry_benchmark"]
