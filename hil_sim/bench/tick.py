"""`dct bench tick`: the whole controller tick on the wall clock, at the lidar's real density.

Why lockstep episodes: they run the real tick (read, odometry, partition, planner, safety,
write) with the same code and config as `dct hil run`, on the simulator's Mid-360-class frames
(20k rays, 10 Hz; the controller ticks at 20 Hz, so every other tick gets a new frame). The
simulator steps *between* ticks, so the wall-clock stage times the loop records are the tick's
own; the ICP worker process (odometry) runs beside the tick as on the robot. With `--hog N`,
N busy processes (`python -c "while True: pass"`) run beside it all, as the robot's other
software would; they are killed at the end, also on error.

Figures (measurements, printed; no pass/fail), per scene and pooled over every scene:
- per stage and for the whole tick: p50, p90, p99, max (ms), the stage's budget
  (`loop.stage_budgets_s`) and its overruns;
- ticks over a quarter of the period (12.5 ms at 20 Hz: the whole tick's target);
- deadline misses measured on the wall clock (tick start -> command written later than
  `loop.command_deadline_s`); the loop's own verdict in lockstep is judged on simulated time
  and is never missed (README: lockstep verdicts do not depend on the machine's load);
- lidar returns per frame and P_fix points (after the voxel filter: what the planner gets);
- the share of QP solves that hit their iteration cap (lockstep caps are iterations, never the
  wall clock): when it is above 0 a WARNING says that the planner figures then describe the cap;
- where the planner stage's time goes on ACTIVE ticks (the only ticks that plan): the ticks
  with a reference-path search in the tick (none with the default `replan_in_slack`) against the
  others, and the MPC step's own split (select, net, rows, build, solve) as `MpcPlanner.plan`
  reports it;
- the work the loop runs in the slack after write() (reference searches, runtime.loop.fixed_rate
  `slack_work`): not part of the tick, but of its period, so tick + slack work is reported too.

All ticks count in the stage and tick figures (start-up and goal ticks are ticks the robot runs
too); the planner stage is also reported over ACTIVE ticks only, where it does work.

The odometry scaling table (`--odometry-scaling`, on by default): the same lockstep drive at
several lidar densities (rays per frame); every good frame the controller handed to ICP is kept
with the wheel/gyro prior it was given, then registered again in this process by one
`IcpEngine` (the controller's IcpConfig, 1 thread), timed per frame; beside it the odometry
stage's time in the tick (it only queues the frame for the worker).
"""
from __future__ import annotations

import contextlib
import os
import subprocess
import sys
import time
from dataclasses import dataclass, field
from typing import Callable, Iterator

import numpy as np

from hil_sim.world.scenario import Scenario, load_scenario
from runtime.loop.telemetry import STAGES

#: Library scenes, ordered by the clutter the planner sees (median P_fix points per frame,
#: measured with seed 0: corridor_boxes ~290, case1 ~710, case3 ~730, odom_loop_far ~750 with
#: up to 900); `dct bench tick` prints the measured figure of each.
DEFAULT_SCENES = ("corridor_boxes", "case1", "case3", "odom_loop_far")
#: Bench-only variants of library scenes: name -> (library scene, route waypoint the goal moves to).
#: odom_loop's own goal is 0.8 m from its start (its route is for `dct odom eval`); this one
#: drives 5.8 m through the furnished room (104 objects), the most cluttered scene there is.
SCENE_VARIANTS: dict[str, tuple[str, int]] = {"odom_loop_far": ("odom_loop", 2)}
#: Rays per frame of the odometry scaling table (the Mid-360 gives about 20k).
DEFAULT_SCALING_RAYS = (5_000, 10_000, 20_000, 40_000)
#: The scene and the simulated seconds per density of the odometry scaling table.
SCALING_SCENE = "odom_loop_far"
SCALING_SECONDS = 8.0
ACTIVE = 1  # runtime.controller.navigation.ControllerState.ACTIVE (the telemetry stores the code)
#: The MPC step's split as MpcPlanner.plan reports it in PlanResult.timings_ms.
MPC_PARTS = ("select", "net", "rows", "build", "solve", "check", "total")


# -- scenes ---------------------------------------------------------------------------------------
def resolve_scene(name: str) -> Scenario:
    """A library scene, a scenario YAML path, or one of SCENE_VARIANTS (ConfigFileError if none)."""
    if name in SCENE_VARIANTS:
        base_name, waypoint = SCENE_VARIANTS[name]
        base = load_scenario(base_name)
        x, y = base.route.waypoints[waypoint]
        goal = base.goal.model_copy(update={"pose": base.goal.pose.model_copy(update={"x_m": x, "y_m": y})})
        return base.model_copy(update={"name": name, "goal": goal, "time_limit_s": 30.0})
    return load_scenario(name)


def capped_scene(scene: Scenario, seconds: float | None) -> Scenario:
    if seconds is None or seconds >= scene.time_limit_s:
        return scene
    return scene.model_copy(update={"time_limit_s": float(seconds)})


# -- busy processes ----------------------------------------------------------------------------------
@contextlib.contextmanager
def busy_processes(n: int) -> Iterator[list[subprocess.Popen]]:
    """N processes that spin a core each, killed (and reaped) on the way out, also on error."""
    procs: list[subprocess.Popen] = []
    try:
        for _ in range(n):
            procs.append(subprocess.Popen([sys.executable, "-c", "while True: pass"],
                                          stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
                                          stderr=subprocess.DEVNULL))
        yield procs
    finally:
        for p in procs:
            p.kill()
        for p in procs:
            p.wait(timeout=10.0)


# -- one episode's ticks --------------------------------------------------------------------------------
@dataclass
class TickProbe:
    """Reads the controller after every tick (runner.run_episode's `observe`, outside the tick):
    the frame's point counts and the planner's counters and split, one row per tick."""

    returns: list[int] = field(default_factory=list)  # lidar returns of this tick's good frame (0: none)
    p_fix: list[int] = field(default_factory=list)  # P_fix points after the tick
    replans: list[int] = field(default_factory=list)  # cumulative reference-path replans
    slack_replans: list[int] = field(default_factory=list)  # ... of them in the slack after a tick
    plans: list[int] = field(default_factory=list)  # cumulative MPC plans
    mpc_ms: list[tuple[float, ...]] = field(default_factory=list)  # MPC_PARTS of a fresh plan (NaN: none)
    keep_jobs: bool = False
    after: Callable[[], None] | None = None  # called last, after each tick (the regression gate's reference)
    jobs: list = field(default_factory=list)  # IcpJob per good frame (odometry scaling)
    _last_plan: object = None

    def __call__(self, controller) -> None:
        scan = controller.monitor.good_scan
        self.returns.append(int(scan.num_points) if scan is not None else 0)
        self.p_fix.append(int(len(controller.points_fix)))
        counters = controller.modes.counters()
        plans = int(counters.get("mpc_plans", 0))
        self.replans.append(int(counters.get("reference_replans", 0)))
        self.slack_replans.append(int(counters.get("reference_replans_in_slack", 0)))
        fresh = plans > (self.plans[-1] if self.plans else 0)
        self.plans.append(plans)
        # The normal mode's newest plan (a backoff plans with the same MPC but keeps its own).
        last = getattr(getattr(controller.modes, "normal", None), "last_plan", None)
        if fresh and last is not None and last is not self._last_plan:
            self._last_plan = last
            t = last.timings_ms
            self.mpc_ms.append(tuple(float(t.get(k, np.nan)) for k in MPC_PARTS))
        else:
            self.mpc_ms.append((np.nan,) * len(MPC_PARTS))
        if self.keep_jobs and scan is not None:
            self.jobs.append(icp_job_of(controller.odometry, scan, len(self.jobs)))
        if self.after is not None:
            self.after()


def icp_job_of(stage, scan, seq: int):
    """The IcpJob the odometry stage handed to its worker for this frame (same prior, same deskew
    motion; runtime.odometry.stage.OdometryStage._submit), to register it again in this process."""
    from runtime.odometry.icp import IcpJob

    offs = scan.point_time_offsets_s
    end = scan.stamp_s + (float(offs.max()) if len(offs) else scan.frame_duration_s)
    return IcpJob(seq=seq, stamp_s=scan.stamp_s, end_s=end, points=scan.points_m, offsets_s=offs,
                  duration_s=scan.frame_duration_s, dead_reckoning_end=stage.fusion.dead_reckoning_at(end),
                  motion=stage.fusion.motion_samples(scan.stamp_s, end))


@dataclass
class EpisodeTicks:
    """Per-tick arrays of one episode (all of equal length) and its episode-level counters."""

    scene: str
    seed: int
    stage_ms: np.ndarray  # (T, len(STAGES))
    tick_ms: np.ndarray
    overrun_mask: np.ndarray
    wall_missed: np.ndarray
    loop_missed: np.ndarray
    state: np.ndarray
    returns: np.ndarray
    p_fix: np.ndarray
    replanned: np.ndarray  # a reference search ran in the tick
    slack_ms: np.ndarray  # work in the slack after the tick (runtime.loop.fixed_rate: slack_work_s)
    slack_replanned: np.ndarray  # a reference search ran in the slack after the tick
    mpc_ms: np.ndarray  # (T, len(MPC_PARTS)), NaN where no fresh plan
    qp_solves: int
    qp_capped: int
    success: bool
    sim_s: float
    wall_s: float
    odometry_wall_clock: dict
    jobs: list

    @staticmethod
    def concat(parts: list["EpisodeTicks"], scene: str) -> "EpisodeTicks":
        cat = lambda name: np.concatenate([getattr(p, name) for p in parts])  # noqa: E731
        return EpisodeTicks(
            scene=scene, seed=-1, stage_ms=cat("stage_ms"), tick_ms=cat("tick_ms"), overrun_mask=cat("overrun_mask"),
            wall_missed=cat("wall_missed"), loop_missed=cat("loop_missed"), state=cat("state"),
            returns=cat("returns"), p_fix=cat("p_fix"), replanned=cat("replanned"), slack_ms=cat("slack_ms"),
            slack_replanned=cat("slack_replanned"), mpc_ms=cat("mpc_ms"),
            qp_solves=sum(p.qp_solves for p in parts), qp_capped=sum(p.qp_capped for p in parts),
            success=all(p.success for p in parts), sim_s=sum(p.sim_s for p in parts),
            wall_s=sum(p.wall_s for p in parts), odometry_wall_clock={}, jobs=[],
        )


def inline_sensors(sensors):
    """The rig config with the lockstep camera's latency, rendered inline, and the lidar cast
    inline: the same images and frames at the same instants as in `dct hil run` (the episode sets
    the camera's rate when the planner uses one), with the simulator's own work between the ticks,
    never beside them."""
    from hil_sim.episode.lockstep import CAMERA_LATENCY_S

    return sensors.model_copy(update={"camera_async": False, "camera_latency_s": CAMERA_LATENCY_S,
                                      "lidar_process": False})


def run_ticks(scene: Scenario, seed: int, config=None, sensors=None, keep_jobs: bool = False,
              after_tick: Callable[[], None] | None = None) -> EpisodeTicks:
    """One lockstep episode (hil_sim.episode.lockstep.run_episode, as `dct hil run`) with the tick
    probe. The camera renders between ticks (inline), its images handed over after the same
    latency as in `dct hil run` (the same run): on the robot the camera driver is another process,
    and a render thread in the controller's process would take Python's GIL from its ticks. The
    lidar's rays are cast between ticks too: a cast process (`dct hil run`'s) would take the
    second core from the ticks and the ICP worker, for work the robot's lidar does in its own
    hardware."""
    from hil_sim.episode.lockstep import run_episode
    from hil_sim.world.sensor_rig import SensorRigConfig
    from runtime.config.loading import load_controller_config

    if sensors is None:  # as run_episode decides
        sensors = (config or load_controller_config()).uses_lidar
    if sensors is True:
        sensors = SensorRigConfig(seed=seed)
    if sensors is not False:
        sensors = inline_sensors(sensors)
    probe = TickProbe(keep_jobs=keep_jobs, after=after_tick)
    result = run_episode(scene, config=config, seed=seed, sensors=sensors, observe=probe)
    rec = result.tick_records
    n = len(rec)
    if len(probe.returns) < n:
        raise RuntimeError(f"tick probe saw {len(probe.returns)} ticks, the telemetry has {n}")
    tail = slice(len(probe.returns) - n, None)  # the telemetry ring keeps the newest ticks
    # Observed after each tick and the slack work that followed it: searches in the tick are
    # all searches less those in the slack.
    def increased(counts: list[int]) -> np.ndarray:
        c = np.asarray(counts[tail])
        return np.diff(c, prepend=counts[tail.start - 1] if tail.start else 0) > 0

    in_tick = [a - b for a, b in zip(probe.replans, probe.slack_replans)]
    replanned, slack_replanned = increased(in_tick), increased(probe.slack_replans)
    c = result.controller
    return EpisodeTicks(
        scene=scene.name, seed=seed,
        stage_ms=rec["stage_s"] * 1e3, tick_ms=rec["tick_s"] * 1e3, overrun_mask=rec["overrun_mask"].copy(),
        wall_missed=rec["wall_deadline_missed"].copy(), loop_missed=rec["deadline_missed"].copy(),
        state=rec["state"].copy(), returns=np.asarray(probe.returns[tail]), p_fix=np.asarray(probe.p_fix[tail]),
        replanned=replanned, slack_ms=rec["slack_work_s"] * 1e3, slack_replanned=slack_replanned, mpc_ms=np.asarray(probe.mpc_ms[tail], dtype=float).reshape(n, len(MPC_PARTS)),
        qp_solves=int(c.get("mpc_qp_solves", 0)), qp_capped=int(c.get("mpc_qp_capped", 0)),
        success=bool(result.metrics["success"]), sim_s=result.sim_time_s, wall_s=result.wall_time_s,
        odometry_wall_clock=result.extra.get("odometry_wall_clock") or {}, jobs=probe.jobs,
    )


# -- figures ------------------------------------------------------------------------------------------------
def percentiles(ms: np.ndarray) -> dict:
    ms = np.asarray(ms, dtype=float)
    ms = ms[np.isfinite(ms)]
    if not len(ms):
        return {"p50_ms": None, "p90_ms": None, "p99_ms": None, "max_ms": None, "count": 0}
    p50, p90, p99 = np.percentile(ms, [50, 90, 99])
    return {"p50_ms": round(float(p50), 3), "p90_ms": round(float(p90), 3), "p99_ms": round(float(p99), 3),
            "max_ms": round(float(ms.max()), 3), "count": int(len(ms))}


def figures(t: EpisodeTicks, budgets_s: dict, period_s: float, deadline_s: float) -> dict:
    """The JSON figures of a set of ticks (one scene, or every scene pooled)."""
    quarter_ms = period_s * 1e3 / 4.0
    stages = {}
    for i, name in enumerate(STAGES):
        stages[name] = {**percentiles(t.stage_ms[:, i]),
                        "budget_ms": round(budgets_s.get(name, period_s) * 1e3, 3),
                        "overruns": int(np.count_nonzero(t.overrun_mask & np.uint32(1 << i)))}
    active = t.state == ACTIVE
    planner = t.stage_ms[:, STAGES.index("planner")]
    frames = t.returns > 0
    slow = t.tick_ms > quarter_ms
    fresh = np.isfinite(t.mpc_ms[:, MPC_PARTS.index("total")])
    # The planner stage less the MPC step: the reference path (grid, search, smoothing on a
    # replan; projection and resampling otherwise) and the mode's glue.
    outside_mpc = planner[active & fresh] - t.mpc_ms[active & fresh, MPC_PARTS.index("total")]
    return {
        "ticks": int(len(t.tick_ms)),
        "active_ticks": int(np.count_nonzero(active)),
        "stages": stages,
        "tick": {**percentiles(t.tick_ms), "over_quarter_period": int(np.count_nonzero(slow)),
                 "quarter_period_ms": quarter_ms},
        "deadline_misses": int(np.count_nonzero(t.wall_missed)),
        "deadline_misses_loop_clock": int(np.count_nonzero(t.loop_missed)),
        "command_deadline_ms": round(deadline_s * 1e3, 3),
        "points_per_frame": _counts(t.returns[frames]),
        "frames": int(np.count_nonzero(frames)),
        "p_fix_points": _counts(t.p_fix[frames]),
        "qp_solves": t.qp_solves,
        "qp_capped": t.qp_capped,
        "capped_fraction": round(t.qp_capped / t.qp_solves, 6) if t.qp_solves else 0.0,
        "planner_active": {
            "all": percentiles(planner[active]),
            "reference_replan_ticks": percentiles(planner[active & t.replanned]),
            "other_ticks": percentiles(planner[active & ~t.replanned]),
            "outside_mpc": percentiles(outside_mpc),
            "mpc_step": {k: percentiles(t.mpc_ms[active & fresh, j]) for j, k in enumerate(MPC_PARTS)},
        },
        "slow_ticks": {  # what the ticks over a quarter period had in common
            "count": int(np.count_nonzero(slow)),
            "with_reference_replan": int(np.count_nonzero(slow & t.replanned)),
            "with_new_frame": int(np.count_nonzero(slow & frames)),
            "active": int(np.count_nonzero(slow & active)),
        },
        "replan_ticks": int(np.count_nonzero(t.replanned)),
        # Work the loop ran after write(), before the next tick (reference searches): not in the
        # tick, but in its period: tick + slack work must leave the loop time to sleep.
        "slack_work": {**percentiles(t.slack_ms[t.slack_replanned]), "searches": int(np.count_nonzero(t.slack_replanned))},
        "tick_plus_slack": percentiles(t.tick_ms + t.slack_ms),
    }


def _counts(x: np.ndarray) -> dict:
    if not len(x):
        return {"p50": None, "min": None, "max": None}
    return {"p50": float(np.median(x)), "min": int(x.min()), "max": int(x.max())}


# -- odometry scaling ---------------------------------------------------------------------------------------------
def time_icp(jobs: list, config) -> np.ndarray:
    """ms per frame of one in-process IcpEngine (the controller's IcpConfig) over the frames in
    order; the first frame only seeds the map and is not counted."""
    from calibration.robot_description import load_robot_description
    from runtime.odometry.icp import IcpEngine

    c = config.odometry
    mount = load_robot_description().sensors.lidar.mount.transform()
    engine = IcpEngine(c.icp, c.degeneracy, mount, c.icp_prior == "odometry")
    ms = []
    for job in jobs:
        t0 = time.perf_counter()
        engine.process(job)
        ms.append((time.perf_counter() - t0) * 1e3)
    return np.asarray(ms[1:])


def odometry_scaling(rays: tuple[int, ...], seconds: float, seed: int, echo: Callable[[str], None]) -> dict:
    from hil_sim.sensors.lidar import LidarConfig
    from hil_sim.world.sensor_rig import SensorRigConfig
    from runtime.config import load_controller_config

    base = load_controller_config()
    scene = capped_scene(resolve_scene(SCALING_SCENE), seconds)
    odo = STAGES.index("odometry")
    rows = []
    echo(f"\nodometry scaling: {scene.name}, seed {seed}, {scene.time_limit_s:g} s per density; ICP timed again "
         f"in this process (IcpEngine, voxel {base.odometry.icp.voxel_size_m}"
         f"{' m' if base.odometry.icp.voxel_size_m != 'auto' else ' (from the first frame)'}, "
         f"{base.odometry.icp.threads} thread)")
    echo(f"{'rays':>7s} {'returns':>8s} {'frames':>6s} | {'ICP ms/frame p50':>16s} {'p99':>6s} {'max':>6s} | "
         f"{'worker p50':>10s} {'p99':>6s} | {'in-tick stage p50':>17s} {'p99':>6s} {'max':>6s}")
    for n in rays:
        lidar = base.inputs.lidar.model_copy(update={"expected_points_per_frame": n})
        config = base.model_copy(update={"inputs": base.inputs.model_copy(update={"lidar": lidar})})
        sensors = SensorRigConfig(seed=seed, lidar=LidarConfig(points_per_frame=n, slices_per_frame=min(50, n)))
        ep = run_ticks(scene, seed, config=config, sensors=sensors, keep_jobs=True)
        icp = percentiles(time_icp(ep.jobs, base))
        stage = percentiles(ep.stage_ms[:, odo])
        worker = ep.odometry_wall_clock.get("icp_compute_ms") or {}
        frames = ep.returns[ep.returns > 0]
        row = {"rays_per_frame": n, "points_per_frame": float(np.median(frames)) if len(frames) else 0.0,
               "frames": int(len(ep.jobs)), "icp_ms": icp,
               "worker_ms": {"p50_ms": worker.get("p50"), "p99_ms": worker.get("p99"), "max_ms": worker.get("max")},
               "stage_ms": stage}
        rows.append(row)
        echo(f"{n:7d} {row['points_per_frame']:8.0f} {row['frames']:6d} | {_f(icp['p50_ms']):>16s} "
             f"{_f(icp['p99_ms']):>6s} {_f(icp['max_ms']):>6s} | {_f(worker.get('p50')):>10s} "
             f"{_f(worker.get('p99')):>6s} | {_f(stage['p50_ms']):>17s} {_f(stage['p99_ms']):>6s} "
             f"{_f(stage['max_ms']):>6s}")
        del ep
    echo("(ICP: the frames the controller handed to its worker, registered again here one by one, the first "
         "frame not counted; worker: the same frames in the worker process during the episode, beside the "
         "simulator; in-tick stage: the odometry stage in the tick, which only queues the frame)")
    return {"scenario": scene.name, "seed": seed, "seconds": scene.time_limit_s, "rows": rows}


# -- the benchmark ---------------------------------------------------------------------------------------------------
def _f(x, digits: int = 2) -> str:
    return "-" if x is None else f"{x:.{digits}f}"


def print_table(fig: dict, echo: Callable[[str], None]) -> None:
    echo(f"{'stage':10s} {'p50':>7s} {'p90':>7s} {'p99':>7s} {'max':>7s} {'budget':>7s} {'overruns':>8s}   (ms)")
    for name, s in fig["stages"].items():
        echo(f"{name:10s} {_f(s['p50_ms']):>7s} {_f(s['p90_ms']):>7s} {_f(s['p99_ms']):>7s} {_f(s['max_ms']):>7s} "
             f"{_f(s['budget_ms'], 1):>7s} {s['overruns']:8d}")
    t = fig["tick"]
    echo(f"{'tick':10s} {_f(t['p50_ms']):>7s} {_f(t['p90_ms']):>7s} {_f(t['p99_ms']):>7s} {_f(t['max_ms']):>7s} "
         f"{_f(t['quarter_period_ms'], 1):>7s} {t['over_quarter_period']:8d}   (budget: a quarter period)")


def print_details(fig: dict, echo: Callable[[str], None]) -> None:
    pa = fig["planner_active"]
    sl = fig["slow_ticks"]
    echo(f"deadline misses (wall clock: tick start -> command written > {fig['command_deadline_ms']:g} ms): "
         f"{fig['deadline_misses']} of {fig['ticks']} ticks (the loop's lockstep verdict, on simulated time: "
         f"{fig['deadline_misses_loop_clock']})")
    ppf, pf = fig["points_per_frame"], fig["p_fix_points"]
    echo(f"lidar returns per frame p50 {_f(ppf['p50'], 0)} (min {ppf['min']}, max {ppf['max']}) over "
         f"{fig['frames']} frames; P_fix points p50 {_f(pf['p50'], 0)} (max {pf['max']})")
    echo(f"QP solves {fig['qp_solves']}, {fig['qp_capped']} hit their iteration cap "
         f"(capped fraction {fig['capped_fraction']:.4f})")
    r, o, x = pa["reference_replan_ticks"], pa["other_ticks"], pa["outside_mpc"]
    echo(f"planner on ACTIVE ticks ({fig['active_ticks']}): p50 {_f(pa['all']['p50_ms'])} p99 "
         f"{_f(pa['all']['p99_ms'])} ms; with a reference search in the tick ({r['count']} ticks) p50 {_f(r['p50_ms'])} "
         f"p99 {_f(r['p99_ms'])} max {_f(r['max_ms'])}; without ({o['count']}) p50 {_f(o['p50_ms'])} "
         f"p99 {_f(o['p99_ms'])} max {_f(o['max_ms'])}")
    parts = " ".join(f"{k} {_f(v['p50_ms'])}/{_f(v['p99_ms'])}" for k, v in pa["mpc_step"].items())
    echo(f"MPC step p50/p99 ms: {parts}; planner stage outside the MPC (reference path, glue) "
         f"{_f(x['p50_ms'])}/{_f(x['p99_ms'])}")
    sw, tp = fig["slack_work"], fig["tick_plus_slack"]
    echo(f"slack work after write() (reference searches, not in the tick): {sw['searches']} searches, p50 "
         f"{_f(sw['p50_ms'])} p99 {_f(sw['p99_ms'])} max {_f(sw['max_ms'])} ms; tick + slack work per period p50 "
         f"{_f(tp['p50_ms'])} p99 {_f(tp['p99_ms'])} max {_f(tp['max_ms'])} ms of {4 * fig['tick']['quarter_period_ms']:g}")
    echo(f"ticks over a quarter period ({fig['tick']['quarter_period_ms']:g} ms): {sl['count']}, of which "
         f"{sl['with_reference_replan']} with a reference replan, {sl['with_new_frame']} with a new frame "
         f"(partition), {sl['active']} ACTIVE")


def cap_warning(fig: dict) -> str | None:
    if fig["qp_capped"]:
        return (f"WARNING: {fig['qp_capped']} of {fig['qp_solves']} QP solves "
                f"({100 * fig['capped_fraction']:.2f}%) hit their iteration cap: the planner figures of those "
                f"ticks describe the cap, not the planner")
    return None


def run_tick_benchmark(scene_names: tuple[str, ...], seed: int, runs: int, hogs: int, seconds: float | None,
                       scaling_rays: tuple[int, ...], echo: Callable[[str], None] = print,
                       gate=None) -> dict:
    """The whole benchmark (module docstring); returns the JSON figures. `gate` (the regression gate,
    hil_sim.bench.tick_gate.GateProbe): gate.episode(None) before the first episode, gate.episode(ticks)
    after each, gate.tick() after each tick (outside it); all beside the busy processes."""
    episode_done = gate.episode if gate is not None else (lambda ep: None)
    after_tick = gate.tick if gate is not None else None
    from runtime.config import load_controller_config

    scenes = [capped_scene(resolve_scene(n), seconds) for n in scene_names]
    config = load_controller_config()
    loop = config.loop
    budgets = dict(loop.stage_budgets_s)
    args = (budgets, loop.period_s, loop.command_deadline_s)
    out: dict = {
        "hogs": hogs, "seed": seed, "runs_per_scene": runs, "seconds_cap": seconds,
        "cpu_count": os.cpu_count(), "load_average_before": [round(x, 2) for x in os.getloadavg()],
        "period_ms": loop.period_s * 1e3, "lidar_rays_per_frame": 20_000, "scenes": {},
    }
    with busy_processes(hogs):
        echo(f"dct bench tick: {len(scenes)} scenes x {runs} runs (seeds {seed}..{seed + runs - 1}), {hogs} busy "
             f"processes beside it, {os.cpu_count()} cores; lockstep episodes as `dct hil run`, 20k-ray frames at "
             f"10 Hz, ticks at {1 / loop.period_s:g} Hz; times on the wall clock")
        per_scene: list[EpisodeTicks] = []
        episode_done(None)
        for sc in scenes:
            eps = []
            for k in range(runs):
                eps.append(run_ticks(sc, seed + k, after_tick=after_tick))
                episode_done(eps[-1])
            ticks = EpisodeTicks.concat(eps, sc.name)
            per_scene.append(ticks)
            fig = figures(ticks, *args)
            fig["success"] = [e.success for e in eps]
            fig["realtime_factor"] = round(ticks.sim_s / ticks.wall_s, 2) if ticks.wall_s else None
            out["scenes"][sc.name] = fig
            s, t = fig["stages"], fig["tick"]
            echo(f"{sc.name:15s} {fig['ticks']:5d} ticks, returns/frame {_f(fig['points_per_frame']['p50'], 0)}, "
                 f"P_fix {_f(fig['p_fix_points']['p50'], 0)} | tick p50 {_f(t['p50_ms'])} p99 {_f(t['p99_ms'])} max "
                 f"{_f(t['max_ms'])} ms, {t['over_quarter_period']} over {t['quarter_period_ms']:g} ms | p99 odometry "
                 f"{_f(s['odometry']['p99_ms'])} partition {_f(s['partition']['p99_ms'])} planner "
                 f"{_f(s['planner']['p99_ms'])} | misses {fig['deadline_misses']} | capped "
                 f"{fig['qp_capped']}/{fig['qp_solves']}")
        pooled = figures(EpisodeTicks.concat(per_scene, "all"), *args)
        echo(f"\nall scenes pooled: {pooled['ticks']} ticks ({pooled['active_ticks']} ACTIVE), hogs {hogs}")
        print_table(pooled, echo)
        print_details(pooled, echo)
        stage_p99 = {k: v["p99_ms"] or 0.0 for k, v in pooled["stages"].items()}
        dominant = max(stage_p99, key=stage_p99.get)
        echo(f"stage with the largest p99: {dominant} ({stage_p99[dominant]:.2f} ms of the tick's "
             f"{_f(pooled['tick']['p99_ms'])} ms)")
        warning = cap_warning(pooled)
        if warning:
            echo(warning)
        out.update(pooled)
        out["dominant_stage_p99"] = dominant
        out["warnings"] = [warning] if warning else []
        if scaling_rays:
            out["odometry_scaling"] = odometry_scaling(scaling_rays, SCALING_SECONDS if seconds is None
                                                       else min(seconds, SCALING_SECONDS), seed, echo)
    # The machine is shared: what else ran shows in the load average (1 minute) around the run.
    out["load_average_after"] = [round(x, 2) for x in os.getloadavg()]
    echo(f"load average before {out['load_average_before'][0]:.2f}, after {out['load_average_after'][0]:.2f} "
         f"(1 min; with {hogs} busy processes of this run)")
    return out


__all__ = ["DEFAULT_SCENES", "SCENE_VARIANTS", "busy_processes", "resolve_scene", "run_tick_benchmark",
           "figures", "run_ticks"]
