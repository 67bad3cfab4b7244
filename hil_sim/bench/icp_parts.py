"""`dct bench icp-parts`: where one ICP frame's time goes, by part, at several lidar densities.

The drive is the one of `dct bench tick`'s odometry scaling table (hil_sim.bench.tick: the scene
odom_loop_far in lockstep, the controller's config, `rays` rays per frame): every good frame the
controller handed to its ICP worker is kept with its wheel/gyro prior, then registered again in
this process by one `IcpEngine` (the controller's settings, 1 thread), `repeats` times from a
fresh engine. The registrations are deterministic, so each frame does the same work in every
repeat: its figure is the fastest repeat, which takes out most of what other processes on a
shared machine add. The first frame (it only seeds the map) is not counted.

Figures per density (ms): the median of each part (`IcpResult.parts_ms`: prepare, preprocess,
downsample, inspect = the degeneracy analysis, registration, map update), the whole frame's p50
and p99 on the wall clock and in the thread's CPU time, and what the job costs to cross to the
worker process (pickle protocol 5, the arrays out of band, as runtime.odometry.worker sends it;
and unpickled) with its size.
"""
from __future__ import annotations

import pickle
import time
from typing import Callable

import numpy as np

from runtime.odometry.kiss_pipeline import TIMED_PARTS

#: The parts of a frame in the table's order.
PARTS = ("prepare", *TIMED_PARTS)
DEFAULT_RAYS = (5_000, 10_000, 20_000, 40_000)
DEFAULT_REPEATS = 3


def record_jobs(rays: int, seconds: float, seed: int) -> list:
    """The IcpJobs of the scaling drive at `rays` rays per frame (module doc)."""
    from hil_sim.bench.tick import SCALING_SCENE, capped_scene, resolve_scene, run_ticks
    from hil_sim.sensors.lidar import LidarConfig
    from hil_sim.world.sensor_rig import SensorRigConfig
    from runtime.config import load_controller_config

    base = load_controller_config()
    lidar = base.inputs.lidar.model_copy(update={"expected_points_per_frame": rays})
    config = base.model_copy(update={"inputs": base.inputs.model_copy(update={"lidar": lidar})})
    sensors = SensorRigConfig(seed=seed, lidar=LidarConfig(points_per_frame=rays, slices_per_frame=min(50, rays)))
    return run_ticks(capped_scene(resolve_scene(SCALING_SCENE), seconds), seed, config=config, sensors=sensors,
                     keep_jobs=True).jobs


def time_parts(jobs: list, repeats: int = DEFAULT_REPEATS) -> dict:
    """Each frame's fastest repeat by part (module doc); the figures of one density."""
    from calibration.robot_description import load_robot_description
    from runtime.config import load_controller_config
    from runtime.odometry.icp import IcpEngine

    c = load_controller_config().odometry
    mount = load_robot_description().sensors.lidar.mount.transform()
    n = len(jobs)
    parts = np.full((n, len(PARTS)), np.inf)
    wall, cpu = np.full(n, np.inf), np.full(n, np.inf)
    results = []
    for _ in range(max(1, repeats)):
        engine = IcpEngine(c.icp, c.degeneracy, mount, c.icp_prior == "odometry")
        results = []
        for i, job in enumerate(jobs):
            w0, c0 = time.perf_counter(), time.thread_time()
            r = engine.process(job)
            wall[i], cpu[i] = min(wall[i], time.perf_counter() - w0), min(cpu[i], time.thread_time() - c0)
            parts[i] = np.minimum(parts[i], [r.parts_ms.get(p, np.nan) for p in PARTS])
            results.append(r)
    counted = slice(1, None)
    pickle_ms, size = _job_transfer(jobs[1:])
    pct = lambda a, q: round(float(np.percentile(a, q)), 3) if len(a) else None  # noqa: E731
    return {
        "frames": max(0, n - 1),
        "returns_p50": pct([r.points_in for r in results[counted]], 50),
        "source_points_p50": pct([r.points_registered for r in results[counted]], 50),
        "iteration_cap_p50": pct([r.iteration_cap for r in results[counted]], 50),
        "parts_ms_p50": {p: pct(parts[counted, k], 50) for k, p in enumerate(PARTS)},
        "wall_ms": {"p50": pct(wall[counted] * 1e3, 50), "p99": pct(wall[counted] * 1e3, 99)},
        "cpu_ms": {"p50": pct(cpu[counted] * 1e3, 50), "p99": pct(cpu[counted] * 1e3, 99)},
        "job_pickle_ms_p50": pct(pickle_ms, 50),
        "job_bytes_p50": pct(size, 50),
    }


def _job_transfer(jobs: list) -> tuple[list[float], list[int]]:
    """ms to pickle a job as the worker's sender does and to unpickle it; its bytes."""
    from runtime.odometry.worker import _job_message

    ms, size = [], []
    for job in jobs:
        t0 = time.perf_counter()
        parts = _job_message(job)
        pickle.loads(parts[0][4:], buffers=[bytes(b) for b in parts[1:]])
        ms.append((time.perf_counter() - t0) * 1e3)
        size.append(sum(len(memoryview(p).cast("B")) for p in parts))
    return ms, size


def run_icp_parts(rays: tuple[int, ...], seconds: float, seed: int, repeats: int,
                  echo: Callable[[str], None]) -> dict:
    """Record and time every density; print the table; the figures."""
    head = (f"{'rays':>6s} {'returns':>7s} {'source':>6s} {'cap':>4s} | "
            + " ".join(f"{p:>12s}" for p in PARTS) + f" | {'wall p50':>8s} {'p99':>6s} | {'cpu p50':>7s} {'p99':>6s}"
            + f" | {'job pickle':>10s}")
    echo(f"ICP time per frame by part (ms; per frame the fastest of {repeats} repeats, then the median over frames)")
    echo(head)
    rows = []
    for n in rays:
        row = {"rays_per_frame": n, **time_parts(record_jobs(n, seconds, seed), repeats)}
        rows.append(row)
        p, w, c = row["parts_ms_p50"], row["wall_ms"], row["cpu_ms"]
        echo(f"{n:6d} {_f(row['returns_p50'], 0):>7s} {_f(row['source_points_p50'], 0):>6s} "
             f"{_f(row['iteration_cap_p50'], 0):>4s} | " + " ".join(f"{_f(p[k]):>12s}" for k in PARTS)
             + f" | {_f(w['p50']):>8s} {_f(w['p99']):>6s} | {_f(c['p50']):>7s} {_f(c['p99']):>6s}"
             + f" | {_f(row['job_pickle_ms_p50']):>10s}")
    echo("(inspect: the degeneracy analysis; job pickle: pickled as the worker's sender does, and unpickled)")
    return {"repeats": repeats, "seconds": seconds, "seed": seed, "rows": rows}


def _f(x, digits: int = 2) -> str:
    return "-" if x is None else f"{x:.{digits}f}"


__all__ = ["DEFAULT_RAYS", "PARTS", "record_jobs", "run_icp_parts", "time_parts"]
