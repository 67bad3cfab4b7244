"""`dct bench planner --neupan PATH`: NeuPAN's own planner against ours, on the benchmark corridor.

NeuPAN (github hanruihua/NeuPAN, GPL-3.0) is never part of this repository: it is imported from
the source folder the user names (the folder that holds its `neupan` package), with its
dependencies (cvxpylayers, gctl, ...) installed by the user (docs/decisions/bench-neupan-peer.md).

What runs: NeuPAN's class `neupan.neupan` built the way its examples build it (the keywords its
planner YAML files hold), stepped with `planner.forward(state, points)` as its examples step it:
its initial path, its DUNE network on the point flow, its NRMP problem solved by ECOS through
cvxpylayers, its PAN alternations; under torch.no_grad (a planning step needs no gradients; its
examples leave autograd on, which costs it about 15% more: `autograd=True`, `--neupan-autograd`).
Its settings: receding horizon = our H, step time = our
MpcConfig.step_s, reference speed 1 m/s (the corridor's reference), our robot's footprint (a
rectangle centred on base_link) and limits, PAN iterations = our alternations, dune_max_num = N
(it decimates the points to this number: every point in range is used), nrmp_max_num = our K
points per pose, and the cost weights of its corridor example (q_s 1, p_u 1, eta 15, d_min 0.1 m)
but for d_max: 0.3 m by default. NeuPAN rewards each distance up to d_max (eta per metre); the
corridor leaves 0.34 m each side of our footprint, so with its example's 1 m it chases clearance it
cannot have: it weaves, backs up and stops (its own collision stop), and its loop no longer drives the
corridor ours drives. Under 0.34 m the reward is saturated in the corridor's middle, as our rows are
met there (the argument d_max_m, `--neupan-d-max`, sets another).

Both planners drive the corridor of hil_sim.bench.planner (cluttered_corridor) in closed loop: each
tick, exactly N points in range (points_in_range), one step, then 50 ms of the kinematic unicycle
with the step's first command; ours through the benchmark's own loop (_run_closed_loop), NeuPAN's
through the same loop written for its call. One thread (torch.set_num_threads(1) and one BLAS
thread), the garbage collector outside the steps as in the controller's loop. Each step is timed
with time.perf_counter (wall) and time.thread_time (CPU) around the planner's call.

Warm: the steady state: after 10 steps and a reset (the planner forgets its previous plan, keeps
its solver set up), steps from the corridor's start; the percentiles of both are over the same
first min(repeats, neupan_repeats) steps (the same stretch of corridor, as many samples). Cold: the first `cold_steps` plans
with no previous plan of a freshly built planner, for `cold_runs` planners placed along the
corridor: each is built (ours: a new OSQP workspace; NeuPAN: a new CvxpyLayer, DUNE net and
nominal velocities, its initial path set at construction), started as the controller starts ours
(START_PLANS plans, MpcPlanner.warm_up's count, then a reset: the first calls of TorchScript's
profiling executor and OSQP's first allocations are start-up work, never a tick's), and timed
COLD_SHIFT_M further along, at a place it has no plan of. The plans before that start are kept
apart as `fresh` (first-call costs included). Building the planner is timed apart (build_ms).
The first use of the process (imports, allocator) is in neither: the warm run comes first.

Clearance: the exact distance of our footprint, at the pose of each warm step, to the scene's
points (all of them, not the N handed to the planner), over the first `neupan_repeats` steps of each
warm run (the same stretch of corridor for both); negative = the footprint overlaps a point.
"""
from __future__ import annotations

import contextlib
import importlib
import importlib.util
import io
import math
import sys
import time
import tomllib
import warnings
from pathlib import Path

import numpy as np

from hil_sim.bench.planner import (
    HORIZONS,
    TICK_S,
    _run_closed_loop,
    cluttered_corridor,
    load_distance_model,
    points_in_range,
)

#: Modules NeuPAN 1.3's package imports that are not part of Python (and threadpoolctl, which this
#: comparison uses), and what pip installs them.
NEUPAN_DEPENDENCIES: tuple[tuple[str, str], ...] = (
    ("cvxpylayers", "cvxpylayers"),
    ("gctl", "gctl==1.2"),
    ("cvxpy", "cvxpy"),
    ("ecos", "ecos"),
    ("torch", "torch"),
    ("yaml", "pyyaml"),
    ("rich", "rich"),
    ("colorama", "colorama"),
    ("threadpoolctl", "threadpoolctl"),  # ours: one BLAS thread (diffcp, under cvxpylayers, installs it)
)
#: NeuPAN's shipped DUNE model for its example diff robot (a 1.6 m x 2.0 m rectangle, not ours).
SHIPPED_MODEL = Path("example/model/diff_robot_default/model_5000.pth")
#: The cost weights of NeuPAN's corridor example (example/corridor/diff/planner.yaml); d_max is
#: set per run (DEFAULT_D_MAX_M, module docstring).
NEUPAN_ADJUST = {"q_s": 1.0, "p_u": 1.0, "eta": 15.0, "d_max": 1.0, "d_min": 0.1}
DEFAULT_D_MAX_M = 0.3
REFERENCE_SPEED_MPS = 1.0
WARMUP_STEPS = 10
#: Cold planners start this far apart along the corridor (metres).
COLD_SPACING_M = 0.5
#: Plans a fresh planner makes before its cold steps, as the controller's start-up makes them
#: (MpcPlanner.warm_up: TorchScript's profiling executor and OSQP's first allocations).
START_PLANS = 4
#: The cold steps start this much further along than the start-up plans (a new place: no plan of it).
COLD_SHIFT_M = 0.25


class NeupanUnavailable(Exception):
    """NeuPAN cannot be imported from the given folder; the message is one line naming the fix."""


def import_neupan(path: str | Path):
    """NeuPAN's `neupan` package from the folder `path` (the folder that holds `neupan/`), its
    dependencies checked first; NeupanUnavailable (one line) when anything is missing."""
    root = Path(path).expanduser().resolve()
    where = f"NeuPAN is not importable from {path}"
    if not (root / "neupan" / "__init__.py").is_file():
        raise NeupanUnavailable(
            f"{where}: no neupan/ package there (extract github hanruihua/NeuPAN 1.3 there: "
            f"git archive HEAD | tar -x -C {path})")
    missing = [pip for module, pip in NEUPAN_DEPENDENCIES if importlib.util.find_spec(module) is None]
    if missing:
        raise NeupanUnavailable(f"{where}: pip install {' '.join(missing)}")
    loaded = sys.modules.get("neupan")
    if loaded is not None:
        if Path(getattr(loaded, "__file__", "") or "").resolve().parent.parent != root:
            raise NeupanUnavailable(f"{where}: another neupan is already imported ({loaded.__file__})")
        return loaded
    sys.path.insert(0, str(root))
    try:
        with contextlib.redirect_stdout(io.StringIO()):
            module = importlib.import_module("neupan")
    except ImportError as exc:
        sys.path.remove(str(root))
        for name in list(sys.modules):
            if name == "neupan" or name.startswith("neupan."):
                del sys.modules[name]
        what = getattr(exc, "name", None) or str(exc)
        raise NeupanUnavailable(f"{where}: import failed on {what} (pip install it; {exc})") from exc
    return module


def neupan_version(path: str | Path) -> str:
    """The version in NeuPAN's pyproject.toml ('unknown' when it has none)."""
    try:
        with open(Path(path) / "pyproject.toml", "rb") as f:
            return str(tomllib.load(f)["project"]["version"])
    except (OSError, KeyError, tomllib.TOMLDecodeError):
        return "unknown"


def build_neupan(neupan_module, cfg, limits, robot, n_points: int, model_path: str | Path,
                 goal_x_m: float, start: np.ndarray, d_max_m: float = DEFAULT_D_MAX_M):
    """NeuPAN's planner for our robot and MPC settings (module docstring), its initial path a line
    from `start` (3,) to (goal_x_m, 0) along the corridor, set with its own API."""
    planner = neupan_module.neupan(
        receding=cfg.horizon_steps,
        step_time=cfg.step_s,
        ref_speed=REFERENCE_SPEED_MPS,
        device="cpu",
        robot_kwargs={
            "kinematics": "diff",
            "length": robot.footprint.length_m,
            "width": robot.footprint.width_m,  # no wheelbase: the rectangle is centred on the state
            "max_speed": [limits.v_max_mps, limits.omega_max_radps],
            "max_acce": [limits.accel_mps2, limits.angular_accel_radps2],
        },
        ipath_kwargs={"waypoints": [[goal_x_m, 0.0, 0.0]], "curve_style": "line"},
        pan_kwargs={
            "iter_num": cfg.alternations,
            "dune_max_num": n_points,
            "nrmp_max_num": cfg.points.points_per_pose,
            "dune_checkpoint": str(model_path),
        },
        adjust_kwargs={**NEUPAN_ADJUST, "d_max": float(d_max_m)},
        train_kwargs={},
    )
    with contextlib.redirect_stdout(io.StringIO()):  # it prints that it sets the path
        planner.set_initial_path_from_state(np.asarray(start, dtype=float).reshape(3, 1))
    return planner


def dune_distance_error_mm(planner, robot, seed: int = 0) -> float:
    """p99 of |DUNE's distance - the exact one| (mm) for points 0-1 m from our footprint: how well
    the DUNE model fits our robot (a model trained for another footprint is far off)."""
    import torch

    hl, hw = robot.footprint.length_m / 2, robot.footprint.width_m / 2
    p = np.random.default_rng(seed).uniform([-hl - 1.0, -hw - 1.0], [hl + 1.0, hw + 1.0], (20000, 2))
    exact = np.hypot(np.maximum(np.abs(p[:, 0]) - hl, 0.0), np.maximum(np.abs(p[:, 1]) - hw, 0.0))
    p, exact = p[(exact > 0.0) & (exact <= 1.0)], exact[(exact > 0.0) & (exact <= 1.0)]
    dune = planner.pan.dune_layer
    with torch.no_grad():
        pts = torch.as_tensor(p.T, dtype=torch.float32)
        mu = dune.model(pts.T).T
        est = dune.cal_objective_distance(mu, pts).numpy()
    return float(np.percentile(np.abs(est - exact), 99) * 1e3)


def footprint_clearance_m(poses: np.ndarray, scene: np.ndarray, half_length_m: float, half_width_m: float) -> float:
    """Smallest exact distance of the footprint (a rectangle centred on each pose) to the scene's
    points over the poses (K, 3); negative: a point inside the footprint (minus its depth)."""
    best = math.inf
    reach = math.hypot(half_length_m, half_width_m) + 1.0
    for x, y, th in poses:
        near = scene[(np.abs(scene[:, 0] - x) <= reach) & (np.abs(scene[:, 1] - y) <= reach)]
        if near.size == 0:
            continue
        c, s = math.cos(th), math.sin(th)
        dx, dy = near[:, 0] - x, near[:, 1] - y
        bx, by = np.abs(c * dx + s * dy) - half_length_m, np.abs(-s * dx + c * dy) - half_width_m
        outside = np.hypot(np.maximum(bx, 0.0), np.maximum(by, 0.0))
        inside = np.minimum(np.maximum(bx, by), 0.0)
        best = min(best, float(np.min(outside + inside)))
    return best


class _TimedPlanner:
    """Our planner as _run_closed_loop drives it, each plan() timed from outside (perf_counter and
    thread_time, as NeuPAN's step is) and the pose it planned from recorded."""

    def __init__(self, planner) -> None:
        self.planner = planner
        self.config = planner.config
        self.wall_ms: list[float] = []
        self.cpu_ms: list[float] = []
        self.poses: list[np.ndarray] = []

    @property
    def last_selection(self):
        return self.planner.last_selection

    def plan(self, state, current_input, reference, points):
        self.poses.append(np.array(state, dtype=float))
        c0, t0 = time.thread_time(), time.perf_counter()
        res = self.planner.plan(state, current_input, reference, points)
        t1, c1 = time.perf_counter(), time.thread_time()
        self.wall_ms.append(1e3 * (t1 - t0))
        self.cpu_ms.append(1e3 * (c1 - c0))
        return res


def _drive_neupan(planner, scene: np.ndarray, n_points: int, ticks: int, seed: int, autograd: bool = False) -> dict:
    """NeuPAN's closed loop, as _run_closed_loop drives ours: per tick N points in range, one
    `planner.forward(state, points)`, 50 ms of the unicycle with its first command; the collector
    between steps. Its prints (initial path, arrival) are dropped. Under torch.no_grad unless
    `autograd` (its examples leave autograd on: its step then also records what a backward pass
    would need, about 15% more at H = 10)."""
    import torch

    from runtime.loop.fixed_rate import FULL_COLLECTION_EVERY_TICKS, collect_between_ticks, collector_outside_ticks

    rng = np.random.default_rng(seed)
    state = np.zeros((3, 1))
    out: dict[str, list] = {"wall": [], "cpu": [], "poses": [], "stops": [], "arrived": []}
    grad = contextlib.nullcontext() if autograd else torch.no_grad()
    with collector_outside_ticks(), contextlib.redirect_stdout(io.StringIO()), warnings.catch_warnings(), grad:
        warnings.simplefilter("ignore")  # its tensor-to-scalar and path-direction warnings, once each
        for tick in range(ticks):
            collect_between_ticks(tick + 1, FULL_COLLECTION_EVERY_TICKS)
            pts = np.ascontiguousarray(points_in_range(scene, state[:2, 0], n_points, rng).T)  # (2, N) as it takes them
            out["poses"].append(state[:, 0].copy())
            c0, t0 = time.thread_time(), time.perf_counter()
            action, info = planner.forward(state, pts)
            t1, c1 = time.perf_counter(), time.thread_time()
            out["wall"].append(1e3 * (t1 - t0))
            out["cpu"].append(1e3 * (c1 - c0))
            out["stops"].append(bool(info.get("stop")))
            out["arrived"].append(bool(info.get("arrive")))
            v, w = float(action[0, 0]), float(action[1, 0])
            for _ in range(5):
                th = state[2, 0]
                state = state + 0.01 * np.array([[v * math.cos(th)], [v * math.sin(th)], [w]])
    return {k: np.asarray(v) for k, v in out.items()}


def _pct(values, q: float) -> float:
    return float(np.percentile(np.asarray(values, dtype=float), q))


def run_neupan_comparison(
    *,
    neupan_path: str | Path,
    model_path: str | Path | None = None,
    horizons: tuple[int, ...] = HORIZONS,
    point_counts: tuple[int, ...] = (100, 300, 1000, 3000),
    repeats: int = 300,
    neupan_repeats: int = 100,
    cold_runs: int = 20,
    cold_steps: int = 3,
    d_max_m: float = DEFAULT_D_MAX_M,
    autograd: bool = False,
    seed: int = 0,
    distance_net_path: str | Path | None = None,
    config=None,
    progress=None,
) -> list[dict]:
    """Per (H, N): our step and NeuPAN's, warm and cold (module docstring), and their ratios
    (NeuPAN / ours); one dict (row) each. NeupanUnavailable when NeuPAN cannot be imported."""
    import torch

    from calibration.robot_description import load_robot_description
    from runtime.config import load_controller_config
    from runtime.planning.mpc import MpcPlanner
    from runtime.planning.mpc_config import MpcConfig, MpcLimits

    nm = import_neupan(neupan_path)
    from threadpoolctl import threadpool_limits  # checked by import_neupan

    model = Path(model_path) if model_path is not None else Path(neupan_path) / SHIPPED_MODEL
    if not model.is_file():
        raise NeupanUnavailable(f"NeuPAN's DUNE model {model} is not a file (--neupan-model PATH)")
    torch.set_num_threads(1)
    robot = load_robot_description()
    net, net_name = load_distance_model(robot, distance_net_path)
    base = config or load_controller_config().planner.mpc
    hl, hw = robot.footprint.length_m / 2, robot.footprint.width_m / 2
    cold_starts = [COLD_SPACING_M * (1 + c) for c in range(cold_runs)]
    length = 2.0 + (max(repeats, neupan_repeats) + WARMUP_STEPS + 40) * TICK_S * 1.0 + 4.0 + max(cold_starts, default=0.0)
    scene = cluttered_corridor(length, np.random.default_rng(seed))
    goal_x = length - 1.0  # NeuPAN's path ends here: it never arrives within the runs
    version = neupan_version(neupan_path)
    dune_err: float | None = None
    rows = []
    with threadpool_limits(limits=1):
        for H in horizons:
            cfg = base.model_copy(update={"horizon_steps": H, "tick_period_s": TICK_S})
            cfg = MpcConfig.model_validate(cfg.model_dump())
            limits = MpcLimits.from_robot(robot, cfg.max_reverse_speed_mps)
            for n in point_counts:
                if progress is not None:
                    progress(f"NeuPAN comparison H={H} points={n}")

                # Ours, warm.
                planner = MpcPlanner(cfg, robot, net, wall_clock_caps=False)
                _run_closed_loop(planner, scene, n, WARMUP_STEPS, seed)
                planner.reset()
                ours = _TimedPlanner(planner)
                _run_closed_loop(ours, scene, n, repeats, seed + 1)

                # NeuPAN, warm.
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore")
                    np_planner = build_neupan(nm, cfg, limits, robot, n, model, goal_x, np.zeros(3), d_max_m)
                if dune_err is None:
                    dune_err = dune_distance_error_mm(np_planner, robot)
                _drive_neupan(np_planner, scene, n, WARMUP_STEPS, seed, autograd)
                np_planner.reset()
                theirs = _drive_neupan(np_planner, scene, n, neupan_repeats, seed + 1, autograd)

                # Cold: fresh planners along the corridor (the scene moved, the robot starts at 0),
                # each started as the controller starts ours (START_PLANS plans, then a reset), then
                # timed 0.25 m further on; their first plans, before that start, are kept as "fresh".
                ours_cold, ours_fresh, ours_build, np_cold, np_fresh, np_build = [], [], [], [], [], []
                for c, x0 in enumerate(cold_starts):
                    shifted = scene - np.array([x0, 0.0])
                    further = scene - np.array([x0 + COLD_SHIFT_M, 0.0])
                    t0 = time.perf_counter()
                    fresh = _TimedPlanner(MpcPlanner(cfg, robot, net, wall_clock_caps=False))
                    ours_build.append(1e3 * (time.perf_counter() - t0))
                    _run_closed_loop(fresh, shifted, n, START_PLANS, seed + 100 + c)
                    ours_fresh.extend(fresh.wall_ms[:cold_steps])
                    fresh.planner.reset()
                    fresh.wall_ms.clear()
                    _run_closed_loop(fresh, further, n, cold_steps, seed + 200 + c)
                    ours_cold.extend(fresh.wall_ms)
                    with warnings.catch_warnings():
                        warnings.simplefilter("ignore")  # the path generator's direction warning
                        t0 = time.perf_counter()
                        fresh_np = build_neupan(nm, cfg, limits, robot, n, model, goal_x - x0, np.zeros(3), d_max_m)
                        np_build.append(1e3 * (time.perf_counter() - t0))
                    np_fresh.extend(_drive_neupan(fresh_np, shifted, n, START_PLANS, seed + 100 + c,
                                                  autograd)["wall"][:cold_steps])
                    fresh_np.reset()
                    np_cold.extend(_drive_neupan(fresh_np, further, n, cold_steps, seed + 200 + c, autograd)["wall"])

                k = min(repeats, neupan_repeats)  # the same stretch of corridor, and as many steps, for both
                ours_poses = np.asarray(ours.poses)[:k]
                np_poses = theirs["poses"][:k]
                row = {
                    "horizon": H,
                    "points": n,
                    "points_per_pose": cfg.points.points_per_pose,
                    "step_s": cfg.step_s,
                    "distance_model": net_name,
                    "neupan_version": version,
                    "neupan_model": str(model),
                    "neupan_dune_error_p99_mm": dune_err,
                    "neupan_d_max_m": float(d_max_m),
                    "neupan_autograd": bool(autograd),
                    "repeats": repeats,
                    "neupan_repeats": neupan_repeats,
                    "cold_runs": cold_runs,
                    "cold_steps": cold_steps,
                    "ours_warm_p50_ms": _pct(ours.wall_ms[:k], 50),
                    "ours_warm_p99_ms": _pct(ours.wall_ms[:k], 99),
                    "ours_warm_cpu_p50_ms": _pct(ours.cpu_ms[:k], 50),
                    "ours_cold_p50_ms": _pct(ours_cold, 50),
                    "ours_cold_p99_ms": _pct(ours_cold, 99),
                    "ours_build_p50_ms": _pct(ours_build, 50),
                    "neupan_warm_p50_ms": _pct(theirs["wall"], 50),
                    "neupan_warm_p99_ms": _pct(theirs["wall"], 99),
                    "neupan_warm_cpu_p50_ms": _pct(theirs["cpu"], 50),
                    "neupan_cold_p50_ms": _pct(np_cold, 50),
                    "neupan_cold_p99_ms": _pct(np_cold, 99),
                    "ours_fresh_p50_ms": _pct(ours_fresh, 50),
                    "ours_fresh_p99_ms": _pct(ours_fresh, 99),
                    "neupan_fresh_p50_ms": _pct(np_fresh, 50),
                    "neupan_fresh_p99_ms": _pct(np_fresh, 99),
                    "neupan_build_p50_ms": _pct(np_build, 50),
                    "neupan_stops": int(theirs["stops"].sum()),
                    "neupan_arrived": int(theirs["arrived"].sum()),
                    "clearance_ticks": k,
                    "ours_min_clearance_m": footprint_clearance_m(ours_poses, scene, hl, hw),
                    "neupan_min_clearance_m": footprint_clearance_m(np_poses, scene, hl, hw),
                    "ours_travel_m": float(ours_poses[-1, 0] - ours_poses[0, 0]) if k > 1 else 0.0,
                    "neupan_travel_m": float(np_poses[-1, 0] - np_poses[0, 0]) if k > 1 else 0.0,
                }
                for kind in ("warm", "cold"):
                    for q in ("p50", "p99"):
                        row[f"{kind}_ratio_{q}"] = row[f"neupan_{kind}_{q}_ms"] / row[f"ours_{kind}_{q}_ms"]
                rows.append(row)
    return rows


def format_neupan_table(rows: list[dict], target_ratio: float = 10.0) -> str:
    """Plain-text table of run_neupan_comparison's rows, and whether ours is `target_ratio` times
    faster (NeuPAN / ours) at every size, warm and cold, at p50 and p99."""
    if not rows:
        return "(no NeuPAN rows)"
    r0 = rows[0]
    lines = [
        "",
        f"NeuPAN {r0['neupan_version']} (its own planner: neupan.forward; DUNE + NRMP by ECOS through cvxpylayers) "
        f"against ours, same process, one thread, same closed-loop corridor; step time in ms (wall, perf_counter); "
        f"x = NeuPAN / ours",
        f"NeuPAN DUNE model: {r0['neupan_model']} (distance error 0-1 m from our footprint: p99 "
        f"{r0['neupan_dune_error_p99_mm']:.1f} mm); ours: {r0['distance_model']}; K = {r0['points_per_pose']} "
        f"points per pose (NeuPAN's nrmp_max_num), dune_max_num = N; NeuPAN d_max {r0['neupan_d_max_m']:g} m; "
        f"NeuPAN {'with autograd on, as its examples' if r0.get('neupan_autograd') else 'under torch.no_grad'}",
        f"warm: steady state, the first {r0['clearance_ticks']} steps of each; cold: the first "
        f"{r0['cold_steps']} plans with no previous plan of {r0['cold_runs']} fresh planners, each started as the "
        f"controller starts ours ({START_PLANS} plans, then a reset; build time apart: build p50); "
        f"clearance: min footprint distance to the scene over the first {r0['clearance_ticks']} warm steps "
        f"(ours/NeuPAN, m); travel: x driven in them (m)",
        f"{'H':>3} {'points':>6} | {'ours p50':>8} {'p99':>6} | {'NeuPAN p50':>10} {'p99':>7} | {'x p50':>6} {'x p99':>6} "
        f"| {'cold ours p50':>13} {'p99':>6} | {'NeuPAN p50':>10} {'p99':>7} | {'x p50':>6} {'x p99':>6} "
        f"| {'build ours/NeuPAN':>17} | {'clearance':>11} | {'travel':>9} | {'stops':>5}",
    ]
    for r in rows:
        lines.append(
            f"{r['horizon']:>3} {r['points']:>6} | {r['ours_warm_p50_ms']:>8.2f} {r['ours_warm_p99_ms']:>6.2f} | "
            f"{r['neupan_warm_p50_ms']:>10.2f} {r['neupan_warm_p99_ms']:>7.2f} | {r['warm_ratio_p50']:>6.1f} "
            f"{r['warm_ratio_p99']:>6.1f} | {r['ours_cold_p50_ms']:>13.2f} {r['ours_cold_p99_ms']:>6.2f} | "
            f"{r['neupan_cold_p50_ms']:>10.2f} {r['neupan_cold_p99_ms']:>7.2f} | {r['cold_ratio_p50']:>6.1f} "
            f"{r['cold_ratio_p99']:>6.1f} | {r['ours_build_p50_ms']:>7.2f}/{r['neupan_build_p50_ms']:<9.1f} | "
            f"{r['ours_min_clearance_m']:>5.3f}/{r['neupan_min_clearance_m']:<5.3f} | "
            f"{r['ours_travel_m']:>4.1f}/{r['neupan_travel_m']:<4.1f} | {r['neupan_stops']:>5}"
        )
    ratios = {(r["horizon"], r["points"], kind, q): r[f"{kind}_ratio_{q}"]
              for r in rows for kind in ("warm", "cold") for q in ("p50", "p99")}
    worst = min(ratios, key=ratios.get)
    below = sorted({(h, n) for (h, n, _, _), x in ratios.items() if x < target_ratio})
    verdict = "yes" if not below else f"NO (below at H, N = {', '.join(f'{h}/{n}' for h, n in below)})"
    lines.append(
        f"ours >= {target_ratio:g}x faster than NeuPAN at every size (warm and cold, p50 and p99): {verdict}; "
        f"smallest ratio x{ratios[worst]:.1f} ({worst[2]} {worst[3]}, H={worst[0]}, N={worst[1]}); "
        f"warm p50 ratios from x{min(r['warm_ratio_p50'] for r in rows):.1f} to "
        f"x{max(r['warm_ratio_p50'] for r in rows):.1f}"
    )
    lines.append("fresh (a new planner's first plans, before its start-up: first-call costs included), p50/p99 ms: "
                 + "; ".join(f"H={r['horizon']} N={r['points']} ours {r['ours_fresh_p50_ms']:.2f}/"
                             f"{r['ours_fresh_p99_ms']:.2f} NeuPAN {r['neupan_fresh_p50_ms']:.1f}/"
                             f"{r['neupan_fresh_p99_ms']:.1f}" for r in rows))
    if any(r["neupan_stops"] for r in rows):
        lines.append("NOTE: NeuPAN stopped (its min distance under its collision threshold) in some steps: "
                     "its robot stood still there; its steps were still timed in full")
    if r0["neupan_dune_error_p99_mm"] > 50.0:
        lines.append("WARNING: NeuPAN's DUNE model does not fit our footprint (error above): its distances, "
                     "clearance and path are meaningless; its step time barely depends on the weights")
    return "\n".join(lines)


__all__ = [
    "NEUPAN_DEPENDENCIES",
    "NeupanUnavailable",
    "build_neupan",
    "format_neupan_table",
    "import_neupan",
    "run_neupan_comparison",
]
