"""`dct bench odom-settings`: the odometry's default (auto) settings beside the best of a small hand grid.

For each input, KISS-ICP alone (runtime.odometry.sequence.evaluate_sequence, as `dct odom eval
--scans` runs it) is run with the defaults (every setting "auto": derived from the first frame,
runtime.odometry.icp_settings) and with each setting of a grid (voxel x max range x iteration
cap; the other settings auto), and measured against the reference poses. Inputs:

- a recorded sequence: a folder of scans and its KITTI poses file;
- a simulated scenario with a route (odom_loop, odom_corridor): its drive is recorded first, in
  lockstep (hil_sim.eval.odometry's scripted operator), as a temporary sequence: one binary PCD
  per lidar frame (x, y, z and the per-point time) and the true pose of the lidar at each
  frame's end.

The best grid setting is the one with the smallest relative pose error (RPE %, per metre of
travel over the sequence's segments; the end error when the run is too short for one), which a
loop's end error alone would flatter. Figures only, no pass/fail.
"""
from __future__ import annotations

import itertools
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np

#: The grid (voxel m, max range m, iteration cap) of the hand-tuned settings.
GRID_VOXELS_M = (0.3, 0.5, 1.0)
GRID_MAX_RANGES_M = (12.0, 60.0, 100.0)
GRID_ITERATIONS = (50, 500)


@dataclass(frozen=True)
class BenchInput:
    name: str
    scans: Path
    poses: Path


def _planar_pose(x: float, y: float, yaw: float) -> np.ndarray:
    c, s = np.cos(yaw), np.sin(yaw)
    T = np.eye(4)
    T[:2, :2] = [[c, -s], [s, c]]
    T[:2, 3] = x, y
    return T


def record_scenario_sequence(scenario, seed: int, folder: Path, progress=None) -> BenchInput:
    """Drive the scenario's route in lockstep and write its lidar frames and the lidar's true
    poses (at each frame's end) into folder as a sequence (module doc)."""
    from calibration.pointcloud_write import write_pcd
    from calibration.robot_description import load_robot_description
    from hil_sim.eval.odometry import evaluate_scenario
    from runtime.odometry.sequence import format_kitti_poses

    robot = load_robot_description()
    mount = robot.sensors.lidar.mount.transform()
    scans_dir = folder / "scans"
    scans_dir.mkdir(parents=True)
    ends: list[float] = []

    def on_tick(t, wheels, imu, scan):
        if scan is not None and scan.num_points:
            offs = np.asarray(scan.point_time_offsets_s, dtype=np.float64)
            xyz = np.asarray(scan.points_m, dtype=np.float32)
            write_pcd(scans_dir / f"{len(ends):06d}.pcd", {"x": xyz[:, 0], "y": xyz[:, 1], "z": xyz[:, 2],
                                                            "time": offs.astype(np.float32)})
            ends.append(scan.stamp_s + float(offs.max()))

    record: dict = {}
    evaluate_scenario(scenario, seed=seed, robot=robot, progress=progress, record=record, on_tick=on_tick)
    t, ref = np.asarray(record["t_s"]), np.asarray(record["ref_pose"])
    yaw = np.unwrap(ref[:, 2])
    # Before the drive the robot stands at the first pose (interp holds the ends).
    poses = np.array([_planar_pose(np.interp(e, t, ref[:, 0]), np.interp(e, t, ref[:, 1]), np.interp(e, t, yaw))
                      @ mount for e in ends])
    (folder / "poses.txt").write_text(format_kitti_poses(poses))
    name = scenario if isinstance(scenario, str) else scenario.name
    return BenchInput(f"{name} (seed {seed})", scans_dir, folder / "poses.txt")


def grid_configs(voxels=GRID_VOXELS_M, ranges=GRID_MAX_RANGES_M, iterations=GRID_ITERATIONS):
    """The grid's IcpConfigs (the settings not in the grid stay auto)."""
    from runtime.odometry.icp_config import IcpConfig

    return [IcpConfig(voxel_size_m=v, max_range_m=r, max_iterations=k)
            for v, r, k in itertools.product(voxels, ranges, iterations)]


def _score(report: dict) -> float:
    e = report["icp"]
    return e["rpe_percent"] if e.get("rpe_percent") is not None else e["end_error_m"]


def _row(report: dict) -> dict:
    e, c = report["icp"], report["config"]
    return {"voxel_size_m": c["voxel_size_m"], "min_range_m": c["min_range_m"], "max_range_m": c["max_range_m"],
            "max_iterations": c["max_iterations"], "end_error_m": e["end_error_m"],
            "drift_percent": e["drift_percent"], "rpe_percent": e["rpe_percent"],
            "frame_ms_p50": report["stage_ms"]["p50"], "frame_ms_p99": report["stage_ms"]["p99"],
            "range_gate_dropped": report["range_gate"]["dropped_fraction"] if report.get("range_gate") else None}


def bench_input(item: BenchInput, configs, echo: Callable[[str], None]) -> dict:
    """The defaults and every grid setting on one input; the rows and the best."""
    from runtime.odometry.icp_config import IcpConfig
    from runtime.odometry.sequence import evaluate_sequence, load_sequence

    seq = load_sequence(item.scans, item.poses)
    report, _ = evaluate_sequence(seq, IcpConfig())
    default = {**_row(report), "derivation": report.get("settings_derivation"),
               "range_gate": report.get("range_gate"), "length_m": report["icp"]["length_m"], "frames": report["frames"]}
    echo(f"{item.name}: auto {_settings(default)}: {_errors(default)}")
    rows = []
    for config in configs:
        r, _ = evaluate_sequence(seq, config)
        rows.append((_score(r), _row(r)))
        echo(f"  grid {_settings(rows[-1][1])}: {_errors(rows[-1][1])}")
    best = min(rows, key=lambda sr: sr[0])[1] if rows else None
    return {"input": item.name, "scans": str(item.scans), "poses": str(item.poses), "default": default,
            "best": best, "grid": [row for _, row in rows]}


def _settings(row: dict) -> str:
    return (f"voxel {row['voxel_size_m']:g} m, range {row['min_range_m']:g}-{row['max_range_m']:g} m, "
            f"cap {row['max_iterations']}")


def _errors(row: dict) -> str:
    rpe = "n/a" if row["rpe_percent"] is None else f"{row['rpe_percent']:.2f}%"
    return (f"end error {row['end_error_m']:.3f} m, RPE {rpe}, {row['frame_ms_p50']:.1f}/{row['frame_ms_p99']:.1f} ms "
            f"per frame (p50/p99)")


def format_table(results: list[dict]) -> list[str]:
    """The summary: per input, the defaults beside the best grid setting."""
    head = (f"{'input':<28} {'auto settings':<40} {'end err m':>9} {'RPE %':>6} {'ms p50/p99':>12}  "
            f"{'best grid setting':<40} {'end err m':>9} {'RPE %':>6} {'ms p50/p99':>12}")
    lines = [head, "-" * len(head)]
    for res in results:
        d, b = res["default"], res["best"]
        left = (f"{res['input'][:28]:<28} {_settings(d):<40} {d['end_error_m']:>9.3f} {_pct(d['rpe_percent']):>6} "
                f"{d['frame_ms_p50']:>5.1f}/{d['frame_ms_p99']:<6.1f}")
        right = "" if b is None else (f"  {_settings(b):<40} {b['end_error_m']:>9.3f} {_pct(b['rpe_percent']):>6} "
                                      f"{b['frame_ms_p50']:>5.1f}/{b['frame_ms_p99']:<6.1f}")
        lines.append(left + right)
    return lines


def _pct(v) -> str:
    return "n/a" if v is None else f"{v:.2f}"


def run_odom_settings_bench(sequences: list[BenchInput], scenarios: list[str], seed: int, configs,
                            echo: Callable[[str], None]) -> dict:
    """Every sequence, then every scenario (recorded to a temporary folder, removed after)."""
    results = []
    for item in sequences:
        results.append(bench_input(item, configs, echo))
    for name in scenarios:
        with tempfile.TemporaryDirectory(prefix="dct-bench-odom-") as tmp:
            echo(f"recording {name} (seed {seed}, lockstep) ...")
            item = record_scenario_sequence(name, seed, Path(tmp))
            results.append(bench_input(item, configs, echo))
    for line in format_table(results):
        echo(line)
    return {"results": results, "grid": {"voxel_size_m": sorted({c.voxel_size_m for c in configs}),
                                         "max_range_m": sorted({c.max_range_m for c in configs}),
                                         "max_iterations": sorted({c.max_iterations for c in configs})}}


__all__ = ["BenchInput", "GRID_ITERATIONS", "GRID_MAX_RANGES_M", "GRID_VOXELS_M", "format_table", "grid_configs",
           "record_scenario_sequence", "run_odom_settings_bench"]
