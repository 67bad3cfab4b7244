"""`dct bench vpp`: the whole VPP stage (VppStage.update) per scan, against the stage's budget
(3 ms p99 for a 20k-point frame with up to 8 masks, one core); and the partition alone
(time_partition; `python -m hil_sim.bench.vpp` prints it).

The scene is synthetic_frame (a room, a floor and boxes in front of the
camera, with lens distortion), fixed in the odom frame. The stage runs as in the controller: a
tiny in-process backend behind a lockstep BackendRunner answers the first image with one movable
mask per box (the masks of synthetic_frame, capture pose = the start), so the memory holds
`masks` entries, each with a plane from the lidar points in it. The tracker follows the boxes
from that answer on; a second answer, asked 2 s later (t_thres), captures the masks again while
the tracker follows them: the steady state of an episode, where the stage knows whether each
object moved since its mask's capture and counts no warped area (VppStage._gates). With
`first_answer` the scans are timed right after the first answer instead (an episode's first
seconds, or a new object: the masks' warped areas are counted for the growth rule). Then the
robot sways (up to
0.25 m along x and y, 0.08 rad of yaw, so every warp is a real homography) and each timed call
is `update(now, pose, image=None, scan)` with the scan seen from that pose. No image is sent
during the timed scans, so no answer arrives: the figures are the steady-state tick. The answer
tick (Phase II) happens about once per second and is timed apart: its image work (planes, every
entry warped to the answer's capture pose, IoU) is done beside the tick, in the backend
runner's worker (`prepare`), and the tick only applies it (`apply`).

Split (wrapped methods, so the figures stay comparable across versions of the stage):
`masks` = the memory's Phase I per scan (propagate, or whatever the stage now calls to carry
the masks to the current pose), `partition` = PointPartitioner.partition (Phase III), `track`
= the object tracker (runtime/vpp/tracking/), `other` = the rest of update.

The garbage collector runs as in the loop (runtime.loop.fixed_rate.collector_outside_ticks): off
during the timed calls, its collections between them, so a collection pause, which the loop never
lets into a tick, is not counted as the stage's.

Single-threaded: numba and OpenCV set to one thread (the product budgets one core for the
stage); `--cpu N` also pins the process to core N. Figures are measurements on this machine, no
pass/fail.
"""
from __future__ import annotations

import functools
import math
import os
import time
from typing import Callable

import numpy as np

DEFAULT_MASK_COUNTS = (1, 4, 8)


def _single_thread(cpu: int | None) -> dict:
    """One thread for numba, OpenCV and BLAS (and one core when cpu is given)."""
    import cv2
    import numba

    numba.set_num_threads(1)
    cv2.setNumThreads(1)
    info = {"numba_threads": numba.get_num_threads(), "opencv_threads": cv2.getNumThreads(), "cpu": cpu}
    try:
        from threadpoolctl import threadpool_limits

        threadpool_limits(1)
    except ImportError:  # pragma: no cover - optional
        pass
    if cpu is not None:
        os.sched_setaffinity(0, {int(cpu)})
    return info


class _Timer:
    """Wall and CPU (this thread) time of calls to wrapped methods, summed per name between
    `reset`s. CPU time leaves out the time the scheduler gave other processes: on a shared
    machine it is the figure that says what the stage costs one core."""

    def __init__(self) -> None:
        self.acc: dict[str, list[float]] = {}

    def wrap(self, obj, attr: str, name: str) -> None:
        fn = getattr(obj, attr)

        @functools.wraps(fn)
        def timed(*args, **kwargs):
            t0, c0 = time.perf_counter(), time.thread_time()
            try:
                return fn(*args, **kwargs)
            finally:
                a = self.acc.setdefault(name, [0.0, 0.0])
                a[0] += time.perf_counter() - t0
                a[1] += time.thread_time() - c0

        setattr(obj, attr, timed)

    def reset(self) -> dict[str, list[float]]:
        out, self.acc = self.acc, {}
        return out


def _stats(ms: np.ndarray) -> dict:
    return {"p50_ms": float(np.percentile(ms, 50)), "p99_ms": float(np.percentile(ms, 99)), "max_ms": float(ms.max())}


def synthetic_frame(n_points: int = 20000, n_masks: int = 8, width: int = 640, height: int = 480, seed: int = 0):
    """A LIMO-like scan: a room (walls 4-6 m away), a floor, and n_masks boxes in front of the
    camera, each with a rectangular mask a little larger than its silhouette (so the mask's
    edge sees the wall behind). Returns (points float32, T_cam_lidar, camera, masks, ids, costs,
    T_base_lidar)."""
    from calibration.camera_model import CameraModel, transform_points

    rng = np.random.default_rng(seed)
    K = np.array([[520.0, 0, (width - 1) / 2], [0, 520.0, (height - 1) / 2], [0, 0, 1]])
    cam = CameraModel(K, np.array([-0.05, 0.01, 0.0005, -0.0003, 0.0]), width, height)
    T = np.eye(4)  # lidar x fwd, y left, z up -> optical x right, y down, z fwd; camera 5 cm above
    T[:3, :3] = np.array([[0, -1, 0], [0, 0, -1], [1, 0, 0]], float)
    T[:3, 3] = T[:3, :3] @ np.array([0.0, 0.0, -0.05])
    T_base = np.eye(4)
    T_base[2, 3] = 0.25  # lidar 25 cm above the floor
    n_box = n_points // 4
    n_floor = n_points // 4
    n_wall = n_points - n_box - n_floor
    az = rng.uniform(-np.pi, np.pi, n_wall)
    r = 5.0 + 0.5 * np.sin(3 * az)
    walls = np.column_stack([r * np.cos(az), r * np.sin(az), rng.uniform(-0.25, 1.0, n_wall)])
    rr = np.sqrt(rng.uniform(0.04, 25.0, n_floor))
    fa = rng.uniform(-np.pi, np.pi, n_floor)
    floor = np.column_stack([rr * np.cos(fa), rr * np.sin(fa), np.full(n_floor, -0.25) + rng.normal(0, 0.005, n_floor)])
    boxes, masks = [], np.zeros((n_masks, height, width), bool)
    per = n_box // max(n_masks, 1)
    for k in range(n_masks):
        y0 = -0.75 + 1.5 * (k + 0.5) / max(n_masks, 1)
        x0 = 1.5 + 0.3 * (k % 3)
        b = np.column_stack([np.full(per, x0) + rng.normal(0, 0.005, per), rng.uniform(y0 - 0.06, y0 + 0.06, per),
                             rng.uniform(-0.2, 0.2, per)])
        boxes.append(b)
        uv, ok = cam.project(transform_points(T, b))
        u0, v0 = np.floor(uv[ok].min(0)).astype(int) - 4
        u1, v1 = np.ceil(uv[ok].max(0)).astype(int) + 4
        masks[k, max(v0, 0):v1 + 1, max(u0, 0):u1 + 1] = True
    extra = n_points - n_wall - n_floor - per * n_masks
    pts = np.vstack([walls, floor] + boxes + [walls[:extra]]).astype(np.float32)
    return pts, T, cam, masks, np.arange(n_masks), np.linspace(1.0, 8.0, n_masks), T_base


def time_partition(n_points: int = 20000, n_masks: int = 8, width: int = 640, height: int = 480,
                   repeats: int = 300, with_memory: bool = True, seed: int = 0,
                   config=None) -> dict:
    """Wall time of PointPartitioner.partition alone on synthetic_frame (after a warm-up call that
    compiles the kernels; config: a PartitionConfig, None for the defaults). Returns ms figures:
    p50, p99, max, and the frame's counts. A figure to print, not a test: run it on an idle core
    (OMP_NUM_THREADS=1); `python -m hil_sim.bench.vpp` prints it with and without the memory."""
    from runtime.vpp.partition.partitioner import PointPartitioner

    pts, T, cam, masks, ids, costs, T_base = synthetic_frame(n_points, n_masks, width, height, seed)
    part = PointPartitioner(config)
    T_odom = np.eye(4)
    res = None
    times = []
    for r in range(repeats + 3):
        T_odom[0, 3] = 0.01 * r
        kw = dict(T_odom_lidar=T_odom, stamp_s=0.1 * r) if with_memory else {}
        t0 = time.perf_counter()
        res = part.partition(pts, T, cam, masks, ids, costs, T_base_lidar=T_base, **kw)
        if r >= 3:
            times.append(time.perf_counter() - t0)
    ms = np.array(times) * 1e3
    return {"p50_ms": float(np.percentile(ms, 50)), "p99_ms": float(np.percentile(ms, 99)),
            "max_ms": float(ms.max()), "n_points": n_points, "n_masks": n_masks, "n_in_view": int(res.in_view.sum()),
            "n_movable": int(res.movable.sum()), "n_outliers_removed": res.n_outliers_removed,
            "n_completed": res.n_completed, "repeats": repeats}


def _build(n_points: int, n_masks: int, seed: int, first_answer: bool = False):
    """(stage, scan_at, masks, costs, the time of the last untimed scan) with the memory filled
    through the stage's own request -> answer -> reconcile path (module docstring)."""
    from calibration.camera_model import transform_points
    from models.vlm.interface import DetectedObject, VlmAnswer, VlmRequest
    from models.vlm.runner import BackendRunner, BackendRunnerConfig
    from runtime.common.sensor_data import CameraImage, LidarScan
    from runtime.vpp.config import VppConfig
    from runtime.vpp.stage import VppStage, pose_matrix

    pts, T_cam_lidar, cam, masks, _, _, T_base_lidar = synthetic_frame(n_points, n_masks, seed=seed)
    T_base_cam = T_base_lidar @ np.linalg.inv(T_cam_lidar)
    world = transform_points(T_base_lidar, pts.astype(np.float64))  # odom frame = base frame at the start
    costs = np.linspace(1.0, 7.0, n_masks)  # all below never_touch_cost: every mask gates

    class Backend:
        name = "bench"

        def query(self, request: VlmRequest) -> VlmAnswer:
            objs = tuple(DetectedObject(masks[k], f"box{k}", True, float(costs[k]), 0.9) for k in range(n_masks))
            return VlmAnswer(request.stamp_s, request.camera_pose_odom, objs, self.name, 0.0)

    runner = BackendRunner(Backend(), BackendRunnerConfig(clock="lockstep", latency_s=0.05))
    stage = VppStage(VppConfig(), cam, T_base_cam, T_base_lidar, runner)

    def scan_at(t: float, pose: tuple[float, float, float]) -> LidarScan:
        T_odom_lidar = pose_matrix(*pose) @ T_base_lidar
        p = transform_points(np.linalg.inv(T_odom_lidar), world).astype(np.float32)
        return LidarScan(stamp_s=t, points_m=p, point_time_offsets_s=np.zeros(len(p), np.float32),
                         frame_duration_s=0.1)

    def image_at(t: float) -> CameraImage:
        return CameraImage(stamp_s=t, pixels=np.zeros((cam.height_px, cam.width_px, 3), np.uint8), K=cam.K,
                           distortion=cam.dist)

    start = (0.0, 0.0, 0.0)
    stage.update(0.0, start, image_at(0.0), scan_at(0.0, start))
    stage.settle(0.06)
    t = 0.06
    stage.update(t, start, None, scan_at(t, start))
    if not first_answer:  # scans until t_thres asks again, the second answer captured while tracked
        ask = stage.config.memory.t_thres_s + 0.05
        while t < ask:
            t += 0.1
            stage.update(t, start, image_at(t) if t >= ask else None, scan_at(t, start))
        stage.settle(t + 0.06)
        t += 0.06
        stage.update(t, start, None, scan_at(t, start))
        if stage.answers != 2:
            raise RuntimeError(f"bench set-up: the second answer did not arrive ({stage.answers} answers)")
    entries = stage.memory.entries
    if len(entries) != n_masks or any(e.plane is None for e in entries):
        raise RuntimeError(f"bench set-up: expected {n_masks} entries with planes, got "
                           f"{[(e.object_id, e.plane is not None) for e in entries]}")
    followed = [stage.tracker.moved_since(e.object_id, e.stamp_s) is not None for e in entries]
    if (any(followed) if first_answer else not all(followed)):
        raise RuntimeError(f"bench set-up: the tracker followed {sum(followed)} of {n_masks} objects since their "
                           f"masks' capture; expected {'none' if first_answer else 'all'}")
    return stage, scan_at, masks, costs, t


def _pose(k: int) -> tuple[float, float, float]:
    """The sway: within 0.25 m and 0.08 rad of the capture pose (below d_thres, so the trigger
    rule would not re-ask; no image is given anyway)."""
    return (0.25 * math.sin(0.11 * k), 0.15 * math.sin(0.07 * k + 1.0), 0.08 * math.sin(0.05 * k))


def _time_answers(stage, scan_at, masks, costs, t: float, dt: float, n: int) -> tuple[list, list]:
    """Phase II, n times: a fresh answer (the same objects, at the start pose's capture), prepared
    beside the tick (the runner's worker: planes, warps, IoU) and applied in the tick
    (MaskMemory.apply). Returns the CPU seconds of each (prepare, apply)."""
    from models.vlm.interface import DetectedObject, VlmAnswer
    from runtime.vpp.stage import pose_matrix

    mem = stage.memory
    prep, app = [], []
    T_cam = pose_matrix(*_pose(0)) @ stage.T_base_cam
    points_cam = np.asarray(scan_at(t, _pose(0)).points_m, np.float64)
    points_cam = points_cam @ stage.T_cam_lidar[:3, :3].T + stage.T_cam_lidar[:3, 3]
    for _ in range(n):
        objs = tuple(DetectedObject(masks[j], f"box{j}", True, float(costs[j]), 0.9) for j in range(len(masks)))
        t += dt
        ans = VlmAnswer(t, T_cam, objs, "bench", 0.0)
        t0 = time.thread_time()
        prepared = stage._preparer.prepare(ans, tuple(mem.entries), prompt=stage.config.prompt, points_cam=points_cam)
        t1 = time.thread_time()
        mem.apply(prepared, now_s=t)
        app.append(time.thread_time() - t1)
        prep.append(t1 - t0)
    return prep, app


def time_stage(n_masks: int, repeats: int = 300, n_points: int = 20000, seed: int = 0, warmup: int = 5,
               first_answer: bool = False) -> dict:
    """Times `repeats` VppStage.update calls with n_masks entries in memory (module docstring)."""
    from runtime.loop.fixed_rate import collector_outside_ticks

    stage, scan_at, masks, costs, t0 = _build(n_points, n_masks, seed, first_answer)
    with collector_outside_ticks():
        out = _time_updates(stage, scan_at, masks, costs, n_masks, repeats, n_points, warmup, t0)
    out["first_answer"] = bool(first_answer)
    return out


def _time_updates(stage, scan_at, masks, costs, n_masks: int, repeats: int, n_points: int, warmup: int,
                  t: float) -> dict:
    from runtime.loop.fixed_rate import FULL_COLLECTION_EVERY_TICKS, collect_between_ticks

    timer = _Timer()
    mem = stage.memory
    for attr in ("propagate", "lookup", "prepare"):  # Phase I, whichever this version of the stage calls
        if hasattr(mem, attr):
            timer.wrap(mem, attr, "masks")
    timer.wrap(stage.partitioner, "partition", "partition")
    timer.wrap(stage.tracker, "update", "track")
    # time advances slowly, so the entries never age out (max_age_s) over the timed scans
    dt = min(0.05, 0.5 * stage.config.memory.max_age_s / (repeats + warmup + 1))
    names = ("masks", "partition", "track", "other")
    total = {"wall": [], "cpu": []}
    parts = {clock: {k: [] for k in names} for clock in ("wall", "cpu")}
    movable, used = [], []
    for k in range(repeats + warmup):
        t += dt
        pose = _pose(k + 1)
        scan = scan_at(t, pose)
        timer.reset()
        t0, c0 = time.perf_counter(), time.thread_time()
        frame = stage.update(t, pose, None, scan)
        el = (time.perf_counter() - t0, time.thread_time() - c0)
        acc = timer.reset()
        collect_between_ticks(k + 1, FULL_COLLECTION_EVERY_TICKS)
        if k < warmup:
            continue
        for i, clock in enumerate(("wall", "cpu")):
            total[clock].append(el[i])
            for name in names[:3]:
                parts[clock][name].append(acc.get(name, (0.0, 0.0))[i])
            parts[clock]["other"].append(el[i] - sum(a[i] for a in acc.values()))
        movable.append(frame.movable_count)
        used.append(frame.masks_used)
    prep, app = _time_answers(stage, scan_at, masks, costs, t, dt, max(3, min(30, repeats // 10)))
    stage.close()
    out = {"n_masks": n_masks, "n_points": n_points, "repeats": repeats}
    for clock in ("wall", "cpu"):
        out[clock] = {"update": _stats(np.array(total[clock]) * 1e3),
                      "split": {k: _stats(np.array(v) * 1e3) for k, v in parts[clock].items()}}
    out.update({
        "answer_apply_cpu": _stats(np.array(app) * 1e3), "answer_prepare_cpu": _stats(np.array(prep) * 1e3),
        "masks_used_min": int(min(used)), "movable_points_median": float(np.median(movable)),
        "masks_distrusted": int(stage.masks_distrusted),
    })
    return out


def run_vpp_benchmark(mask_counts=DEFAULT_MASK_COUNTS, repeats: int = 300, n_points: int = 20000, seed: int = 0,
                      cpu: int | None = None, echo: Callable[[str], None] = print, first_answer: bool = False) -> dict:
    """Prints and returns the figures per mask count."""
    threads = _single_thread(cpu)
    when = ("right after the first answer (masks captured before the tracker followed the objects)" if first_answer
            else "steady state (masks captured while the tracker follows the objects)")
    echo(f"VppStage.update, {n_points} points, {repeats} scans per row, camera moving, {when}, single thread "
         f"(numba {threads['numba_threads']}, OpenCV {threads['opencv_threads']}"
         + (f", cpu {cpu}" if cpu is not None else "") + "); budget 3 ms p99 at 8 masks")
    head = (f"{'masks':>5} {'clock':>5} {'p50':>6} {'p99':>6} {'max':>6} | {'Phase I':>11} {'partition':>11} "
            f"{'track':>11} {'other':>11} | {'used':>4} {'movable':>7} {'apply':>11} {'prepare':>7}")
    echo(head)
    rows = []
    for m in mask_counts:
        r = time_stage(int(m), repeats, n_points, seed, first_answer=first_answer)
        rows.append(r)
        for clock in ("cpu", "wall"):
            u, s = r[clock]["update"], r[clock]["split"]
            pp = " ".join(f"{s[k]['p50_ms']:>5.2f}/{s[k]['p99_ms']:<5.2f}" for k in ("masks", "partition", "track", "other"))
            ap, pr = r["answer_apply_cpu"], r["answer_prepare_cpu"]
            tail = (f" | {r['masks_used_min']:>4} {r['movable_points_median']:>7.0f} "
                    f"{ap['p50_ms']:>5.2f}/{ap['max_ms']:<5.2f} {pr['p50_ms']:>7.2f}" if clock == "cpu" else "")
            echo(f"{m:>5} {clock:>5} {u['p50_ms']:>6.2f} {u['p99_ms']:>6.2f} {u['max_ms']:>6.2f} | {pp}{tail}")
    echo("ms; split columns p50/p99; cpu = this thread's CPU time (what the stage costs one core; wall adds the "
         "time other processes took the core); used = fewest masks a scan was gated against; movable = median "
         "movable points per scan; an answer (Phase II, about once a second): apply = CPU p50/max of its part in "
         "the tick (add it to that tick's update), prepare = CPU p50 of its image work beside the tick (the "
         "backend runner's worker)")
    return {"threads": threads, "first_answer": bool(first_answer), "rows": rows}


__all__ = ["DEFAULT_MASK_COUNTS", "run_vpp_benchmark", "synthetic_frame", "time_partition", "time_stage"]


if __name__ == "__main__":  # pragma: no cover
    import json

    print(json.dumps(time_partition(), indent=1))
    print(json.dumps(time_partition(with_memory=False), indent=1))
