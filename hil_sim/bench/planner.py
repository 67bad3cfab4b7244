"""`dct bench planner`: the planner step's time against the points in range and the horizon,
against the same problem written in cvxpy and solved with ECOS or Clarabel (the way NeuPAN
solves it).

Work sizes: points in range N (P_fix within the obstacle range of the robot, 6 m: what the
partition hands the planner each tick) in 100 .. 10,000 and horizon H in 10, 20, 30, with the
controller's own MPC settings otherwise (K points per pose, thinning cells, reach, caps). The robot
drives a straight corridor (walls 0.9 m apart) through a cluttered room (boxes beyond the walls)
at 1 m/s in closed loop (kinematic unicycle), planning every 50 ms; each tick the planner gets
exactly N points drawn from the scene's points within range (a dense scene subsampled: the
density grows with N, the geometry stays).

Timing: the step (point selection + distance net + QP + bookkeeping, one thread), split into
select, net (the forward pass), rows (collision rows from the net's duals), build (the QP's
numbers written into OSQP) and solve. Caps: iteration counts only (lockstep caps), so a figure is
the cost of the work; a solve that hits its iteration cap is counted (`capped_fraction`), and a
figure with capped solves is flagged: it then describes the cap, not the planner.

The cvxpy run uses the identical planner (same point selection, same net, same linearization,
same cost and constraints) with the QP backend swapped for a cvxpy problem built once per H with
Parameters and re-solved each alternation (cvxpy is benchmark-only).
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from runtime.planning.mpc import MpcPlanner
from runtime.planning.mpc_config import MpcConfig, MpcLimits
from runtime.planning.mpc_qp import MpcLinearization, OsqpMpcBackend, QpOutcome

TICK_S = 0.05
#: The controller's obstacle range (runtime.config ObstaclePointsConfig.max_range_m).
RANGE_M = 6.0
HORIZONS = (10, 20, 30)
POINT_COUNTS = (100, 300, 1000, 3000, 10000)
#: The parts of a step, as MpcPlanner.plan times them.
PARTS = ("select", "net", "rows", "build", "solve")


class CvxpyMpcBackend:
    """The MPC QP of runtime.planning.mpc as a parametrized cvxpy problem (NeuPAN style)."""

    def __init__(self, config: MpcConfig, limits: MpcLimits, solver: str = "ECOS") -> None:
        import cvxpy as cp

        self.cp = cp
        self.solver = solver
        H, K, dt, w = config.horizon_steps, config.points.points_per_pose, config.step_s, config.weights
        self.H, self.K = H, K
        P = cp.Parameter
        self.p = {
            "state0": P(3), "u_prev": P(2), "a02": P(H), "a12": P(H), "b0": P(H), "b1": P(H),
            "off": P((H, 3)), "cx": P((H, K)), "cy": P((H, K)), "cth": P((H, K)), "rhs": P((H, K)),
            "ref_xy": P((H, 2)), "ref_yaw": P(H), "ref_v": P(H), "u_lo": P((H, 2)), "u_hi": P((H, 2)),
            "du": P((H, 2)), "slack_w": P((H, K), nonneg=True),
        }
        p = self.p
        S, U, E = cp.Variable((H + 1, 3)), cp.Variable((H, 2)), cp.Variable((H, K))
        self.U = U
        self.E = E
        ones = np.ones((1, K))
        U_prev = cp.vstack([cp.reshape(p["u_prev"], (1, 2), order="C"), U[:-1]])
        cons = [
            S[0] == p["state0"],
            S[1:, 0] == S[:-1, 0] + cp.multiply(p["a02"], S[:-1, 2]) + cp.multiply(p["b0"], U[:, 0]) + p["off"][:, 0],
            S[1:, 1] == S[:-1, 1] + cp.multiply(p["a12"], S[:-1, 2]) + cp.multiply(p["b1"], U[:, 0]) + p["off"][:, 1],
            S[1:, 2] == S[:-1, 2] + dt * U[:, 1] + p["off"][:, 2],
            U >= p["u_lo"], U <= p["u_hi"],
            U - U_prev <= p["du"], U - U_prev >= -p["du"],
            cp.multiply(p["cx"], cp.reshape(S[1:, 0], (H, 1), order="C") @ ones)
            + cp.multiply(p["cy"], cp.reshape(S[1:, 1], (H, 1), order="C") @ ones)
            + cp.multiply(p["cth"], cp.reshape(S[1:, 2], (H, 1), order="C") @ ones)
            + E >= p["rhs"],
            E >= 0,
        ]
        cost = (
            w.position * cp.sum_squares(S[1:H, :2] - p["ref_xy"][: H - 1])
            + w.terminal_position * cp.sum_squares(S[H, :2] - p["ref_xy"][H - 1])
            + w.heading * cp.sum_squares(S[1:, 2] - p["ref_yaw"])
            + w.speed * cp.sum_squares(U[:, 0] - p["ref_v"])
            + w.angular_speed * cp.sum_squares(U[:, 1])
            + w.speed_change * cp.sum_squares(U[:, 0] - U_prev[:, 0])
            + w.angular_speed_change * cp.sum_squares(U[:, 1] - U_prev[:, 1])
            + cp.sum(cp.multiply(p["slack_w"], E))  # per-row L1 weight (holding rows cost more)
            + (w.slack_quadratic + 5e-7) * cp.sum_squares(E)
        )
        self.problem = cp.Problem(cp.Minimize(cost), cons)
        if not self.problem.is_dpp():
            raise AssertionError("CvxpyMpcBackend: the problem is not DPP; parameters would recompile each solve")

    def solve(self, lin: MpcLinearization, time_limit_s: float | None = None) -> QpOutcome:
        t_build = time.perf_counter()
        p, H = self.p, self.H
        p["state0"].value = lin.state0
        p["u_prev"].value = lin.u_prev
        for name in ("a02", "a12", "b0", "b1", "ref_yaw", "ref_v"):
            p[name].value = getattr(lin, name)
        p["off"].value = lin.offset
        act = lin.coll_active
        p["cx"].value = np.where(act, lin.coll_coef[..., 0], 0.0)
        p["cy"].value = np.where(act, lin.coll_coef[..., 1], 0.0)
        p["cth"].value = np.where(act, lin.coll_coef[..., 2], 0.0)
        p["rhs"].value = np.where(act, lin.coll_rhs, -1.0e3)  # inactive rows: always satisfied
        p["ref_xy"].value = lin.ref_xy
        p["slack_w"].value = np.asarray(lin.coll_slack_weight, dtype=float)
        p["u_lo"].value = np.broadcast_to(lin.u_lo, (H, 2)).copy()
        p["u_hi"].value = np.broadcast_to(lin.u_hi, (H, 2)).copy()
        p["du"].value = np.broadcast_to(lin.du_max, (H, 2)).copy()
        t_solve = time.perf_counter()
        try:
            self.problem.solve(solver=self.solver, warm_start=True)
        except self.cp.error.SolverError as exc:
            return QpOutcome(False, False, f"solver error: {exc}", 0, None, 0.0)
        t_done = time.perf_counter()
        status = str(self.problem.status)
        ok = status in ("optimal", "optimal_inaccurate") and self.U.value is not None
        iters = int(getattr(self.problem.solver_stats, "num_iters", 0) or 0)
        inputs = np.array(self.U.value) if ok else None
        slack = float(max(0.0, np.max(self.E.value))) if ok else 0.0
        return QpOutcome(ok, False, status, iters, inputs, slack,
                         build_ms=(t_solve - t_build) * 1e3, solve_ms=(t_done - t_solve) * 1e3)


def load_distance_model(robot, path: str | Path | None = None):
    """The distance net at `path` (None: the shipped one); an untrained net of the same architecture when none is shipped
    (same inference cost, meaningless distances: reported as such)."""
    from models.distance_net import DistanceNet

    try:
        return DistanceNet.load(path, robot=robot), f"distance net ({path or 'shipped'})"
    except Exception as exc:  # noqa: BLE001 - any load failure falls back, and is reported
        import torch

        from models.distance_net import FoldedDualMLP

        G, g = robot.footprint.halfspaces()
        module = torch.jit.freeze(torch.jit.script(FoldedDualMLP(g[0], g[1]).eval()))
        torch.set_num_threads(1)
        return DistanceNet(module, G, g, {"untrained": True}, Path("<untrained>")), f"UNTRAINED net ({type(exc).__name__})"


def cluttered_corridor(length_m: float, rng: np.random.Generator, spacing_m: float = 0.005) -> np.ndarray:
    """A dense point scene (M, 2): walls at y = +-0.45 m from x = -RANGE_M to length_m + RANGE_M,
    and box outlines (0.2-0.6 m, yawed) in the room beyond them (|y| from 0.8 to 5 m), points
    every spacing_m (the benchmark subsamples it to N points in range per tick)."""
    x = np.arange(-RANGE_M, length_m + RANGE_M, spacing_m)
    walls = [np.stack([x, np.full_like(x, 0.45)], 1), np.stack([x, np.full_like(x, -0.45)], 1)]
    boxes = []
    n_boxes = int((length_m + 2 * RANGE_M) * 2.5)
    for _ in range(n_boxes):
        cx = rng.uniform(-RANGE_M, length_m + RANGE_M)
        cy = rng.choice([-1.0, 1.0]) * rng.uniform(0.8, 5.0)
        a, b = rng.uniform(0.1, 0.3, 2)
        yaw = rng.uniform(0.0, math.pi)
        t = np.arange(0.0, 4.0 * (a + b), spacing_m)  # arc length around the outline
        side = np.minimum(t, 4.0 * (a + b) - 1e-9)
        u = np.where(side < 2 * a, -a + side, np.where(side < 2 * a + 2 * b, a, np.where(side < 4 * a + 2 * b, a - (side - 2 * a - 2 * b), -a)))
        v = np.where(side < 2 * a, -b, np.where(side < 2 * a + 2 * b, -b + (side - 2 * a), np.where(side < 4 * a + 2 * b, b, b - (side - 4 * a - 2 * b))))
        c, s = math.cos(yaw), math.sin(yaw)
        boxes.append(np.stack([cx + c * u - s * v, cy + s * u + c * v], 1))
    return np.concatenate(walls + boxes)


def points_in_range(scene: np.ndarray, xy: np.ndarray, n: int, rng: np.random.Generator) -> np.ndarray:
    """Exactly n of the scene's points within RANGE_M of xy (all of them if fewer)."""
    d2 = (scene[:, 0] - xy[0]) ** 2 + (scene[:, 1] - xy[1]) ** 2
    near = np.flatnonzero(d2 <= RANGE_M * RANGE_M)
    if near.size > n:
        near = rng.choice(near, size=n, replace=False)
    return scene[near]


def _straight_reference(x0: float, H: int, step_s: float) -> np.ndarray:
    ref = np.zeros((H + 1, 3))
    ref[:, 0] = x0 + np.arange(H + 1) * step_s * 1.0
    ref[:, 2] = 1.0
    return ref


def _run_closed_loop(planner: MpcPlanner, scene: np.ndarray, n_points: int, ticks: int, seed: int) -> dict:
    """Drive the corridor: per tick N points in range, one plan, 50 ms of the unicycle. The
    garbage collector runs as in the controller's loop: never inside a plan, its collections
    between them (runtime.loop.fixed_rate.collector_outside_ticks)."""
    from runtime.loop.fixed_rate import collector_outside_ticks

    with collector_outside_ticks():
        return _drive(planner, scene, n_points, ticks, seed)


def _drive(planner: MpcPlanner, scene: np.ndarray, n_points: int, ticks: int, seed: int) -> dict:
    from runtime.loop.fixed_rate import FULL_COLLECTION_EVERY_TICKS, collect_between_ticks

    H, dt = planner.config.horizon_steps, planner.config.step_s
    rng = np.random.default_rng(seed)
    state = np.zeros(3)
    u = np.array([1.0, 0.0])
    out: dict[str, list] = {k: [] for k in ("total", *PARTS, "rows_used", "reach", "cells", "expanded", "points",
                                            "iterations", "cpu")}
    for tick in range(ticks):
        collect_between_ticks(tick + 1, FULL_COLLECTION_EVERY_TICKS)
        pts = points_in_range(scene, state[:2], n_points, rng)
        reference = _straight_reference(state[0], H, dt)
        c0 = time.thread_time()
        res = planner.plan(state, u, reference, pts)
        out["cpu"].append(1e3 * (time.thread_time() - c0))
        for k in ("total", *PARTS):
            out[k].append(res.timings_ms[k])
        out["rows_used"].append(res.constraint_points)
        sel = planner.last_selection
        out["reach"].append(0 if sel is None else sel.points_in_reach)
        out["cells"].append(0 if sel is None else sel.cells)
        out["expanded"].append(0 if sel is None else sel.pairs_expanded)
        out["points"].append(pts.shape[0])
        out["iterations"].append(res.iterations)
        u = res.commands[0].copy()
        for _ in range(5):
            state = state + 0.01 * np.array([u[0] * math.cos(state[2]), u[0] * math.sin(state[2]), u[1]])
    return {k: np.asarray(v, dtype=float) for k, v in out.items()}


def _pct(values, q: float) -> float:
    return float(np.percentile(np.asarray(values), q))


@dataclass(frozen=True)
class _Bench:
    """What every (H, N) cell of the planner benchmark shares."""

    robot: object
    model: object
    model_name: str
    scene: np.ndarray
    repeats: int
    cvxpy_repeats: int
    cvxpy_solvers: tuple[str, ...]
    seed: int


def run_planner_benchmark(
    *,
    horizons: tuple[int, ...] = HORIZONS,
    point_counts: tuple[int, ...] = POINT_COUNTS,
    repeats: int = 300,
    cvxpy_repeats: int = 20,
    cvxpy_solvers: tuple[str, ...] = ("ECOS", "CLARABEL"),
    seed: int = 0,
    distance_net_path: str | Path | None = None,
    config: MpcConfig | None = None,
    progress=None,
) -> list[dict]:
    """Planner step time per (H, N) and the cvxpy formulation's; one dict (row) each.

    config: the MPC settings (default: the controller's, from its default config file); only
    the horizon is varied."""
    import torch

    from calibration.robot_description import load_robot_description
    from runtime.config import load_controller_config

    torch.set_num_threads(1)
    robot = load_robot_description()
    model, model_name = load_distance_model(robot, distance_net_path)
    base = config or load_controller_config().planner.mpc
    length = 2.0 + (repeats + 40) * TICK_S * 1.0 + 4.0
    scene = cluttered_corridor(length, np.random.default_rng(seed))
    bench = _Bench(robot, model, model_name, scene, repeats, cvxpy_repeats, cvxpy_solvers, seed)
    out = []
    for H in horizons:
        cfg = base.model_copy(update={"horizon_steps": H, "tick_period_s": TICK_S})
        cfg = MpcConfig.model_validate(cfg.model_dump())
        cv_backends: dict[str, CvxpyMpcBackend] = {}
        for n in point_counts:
            if progress is not None:
                progress(f"H={H} points={n}")
            row, planner = _osqp_row(bench, cfg, n)
            row.update(_two_qps_columns(bench, cfg, n))
            row.update(_cvxpy_columns(bench, cfg, n, planner, cv_backends, row["p50_ms"]))
            out.append(row)
    return out


def _osqp_row(bench: _Bench, cfg: MpcConfig, n: int) -> tuple[dict, MpcPlanner]:
    """The planner's step with N points in range at horizon cfg.horizon_steps: the row's figures,
    and the planner (its last QP is the cvxpy cross-check's)."""
    planner = MpcPlanner(cfg, bench.robot, bench.model, wall_clock_caps=False)
    _run_closed_loop(planner, bench.scene, n, 10, bench.seed)  # warm-up (allocations, first solves)
    planner.reset()
    solves0, capped0, fallbacks0 = planner.qp_solves, planner.qp_capped, planner.fallbacks
    skipped0 = planner.alternations_skipped
    t = _run_closed_loop(planner, bench.scene, n, bench.repeats, bench.seed + 1)
    solves = planner.qp_solves - solves0
    total_mean = float(t["total"].mean())
    row = {
        "horizon": cfg.horizon_steps,
        "points": n,
        "points_in_range_median": float(np.median(t["points"])),
        "points_per_pose": cfg.points.points_per_pose,
        "points_in_reach_median": float(np.median(t["reach"])),
        "cells_median": float(np.median(t["cells"])),
        "pairs_expanded_median": float(np.median(t["expanded"])),
        "constraint_rows_median": float(np.median(t["rows_used"])),
        "constraint_rows_max": int(t["rows_used"].max()),
        "distance_model": bench.model_name,
        "repeats": bench.repeats,
        "p50_ms": _pct(t["total"], 50),
        "p90_ms": _pct(t["total"], 90),
        "p99_ms": _pct(t["total"], 99),
        "max_ms": float(t["total"].max()),
        "cpu_p50_ms": _pct(t["cpu"], 50),
        "cpu_p99_ms": _pct(t["cpu"], 99),
        **{f"{k}_p50_ms": _pct(t[k], 50) for k in PARTS},
        "share": {k: float(t[k].mean()) / total_mean for k in PARTS},
        "iterations_median": float(np.median(t["iterations"])),
        "qp_solves": solves,
        "capped_solves": planner.qp_capped - capped0,
        "capped_fraction": (planner.qp_capped - capped0) / max(solves, 1),
        "fallbacks": planner.fallbacks - fallbacks0,
        "alternations_skipped": planner.alternations_skipped - skipped0,
    }
    return row, planner


def _two_qps_columns(bench: _Bench, cfg: MpcConfig, n: int) -> dict:
    """The same with both net/QP alternations always run (alternation_tolerance 0): what a tick
    pays when the first solution moves (always, in the HIL scenes)."""
    cfg2 = cfg.model_copy(update={"alternation_tolerance_m": 0.0, "alternation_tolerance_rad": 0.0})
    planner2 = MpcPlanner(cfg2, bench.robot, bench.model, wall_clock_caps=False)
    _run_closed_loop(planner2, bench.scene, n, 10, bench.seed)
    planner2.reset()
    t2 = _run_closed_loop(planner2, bench.scene, n, bench.repeats, bench.seed + 1)
    return {"two_qps_p50_ms": _pct(t2["total"], 50), "two_qps_p99_ms": _pct(t2["total"], 99),
            "two_qps_capped_solves": planner2.qp_capped}


def _cvxpy_columns(bench: _Bench, cfg: MpcConfig, n: int, planner: MpcPlanner,
                   cv_backends: dict[str, CvxpyMpcBackend], p50_ms: float) -> dict:
    """Per cvxpy solver: its step p50, its solve p50, its ratio to ours (p50_ms) and the largest
    input difference on the planner's last QP; and `cvxpy_ratio`, the fastest solver's."""
    row: dict = {}
    lin_snapshot = planner.lin  # the last QP, for the cross-check below
    osqp_inputs = OsqpMpcBackend(cfg, planner.limits, wall_clock_caps=False).solve(lin_snapshot).inputs
    ratios = []
    for solver in bench.cvxpy_solvers:
        if bench.cvxpy_repeats <= 0:
            break
        if solver not in cv_backends:  # the cvxpy problem depends on H and K only
            cv_backends[solver] = CvxpyMpcBackend(cfg, planner.limits, solver)
        backend = cv_backends[solver]
        check = backend.solve(lin_snapshot)
        cv_planner = MpcPlanner(cfg, bench.robot, bench.model, qp_backend=backend, wall_clock_caps=False)
        _run_closed_loop(cv_planner, bench.scene, n, 2, bench.seed)
        cv_planner.reset()
        cv = _run_closed_loop(cv_planner, bench.scene, n, bench.cvxpy_repeats, bench.seed + 1)
        key = solver.lower()
        row[f"cvxpy_{key}_p50_ms"] = _pct(cv["total"], 50)
        row[f"cvxpy_{key}_solve_p50_ms"] = _pct(cv["build"] + cv["solve"], 50)
        row[f"cvxpy_{key}_ratio"] = row[f"cvxpy_{key}_p50_ms"] / p50_ms
        row[f"cvxpy_{key}_max_input_diff"] = (  # None: a solver failed the check (JSON has no NaN)
            float(np.abs(check.inputs - osqp_inputs).max())
            if check.ok and osqp_inputs is not None else None
        )
        ratios.append(row[f"cvxpy_{key}_ratio"])
    # The cvxpy ratio: the fastest cvxpy solver's step p50 over ours (how much faster we are).
    row["cvxpy_ratio"] = min(ratios) if ratios else None
    return row


def cap_warnings(rows: list[dict]) -> list[str]:
    """One warning per row whose figures are bounded by a cap (then they are not timings)."""
    return [
        f"WARNING: H={r['horizon']} points={r['points']}: {r['capped_solves']} of {r['qp_solves']} QP solves "
        f"({100 * r['capped_fraction']:.1f}%) hit the iteration cap: these figures describe the cap, not the planner"
        for r in rows if r["capped_solves"]
    ] + [
        f"WARNING: H={r['horizon']} points={r['points']}: {r['two_qps_capped_solves']} QP solves of the two-QP "
        f"run hit the iteration cap: its figures describe the cap, not the planner"
        for r in rows if r.get("two_qps_capped_solves")
    ]


def format_planner_table(rows: list[dict]) -> str:
    """Plain-text tables of run_planner_benchmark's rows: per (H, N) the step's percentiles,
    the constraint set and the share of each part; then the scaling pivot (p99 by N and H)."""
    if not rows:
        return "(no rows)"
    solvers = sorted({k[len("cvxpy_"):-len("_ratio")] for r in rows for k in r
                      if k.startswith("cvxpy_") and k.endswith("_ratio") and k != "cvxpy_ratio"})
    lines = [
        f"distance model: {rows[0]['distance_model']}; one thread; caps: iterations only; times in ms; "
        f"K = {rows[0]['points_per_pose']} points per pose",
        "step = select + net + rows + build + solve (+ bookkeeping); share = mean part / mean step; reach: points "
        "within reach of the horizon, cells: their occupied cells, rows: constraint rows (at most H x K), "
        "QPs: solves per step (net/QP alternations; the second is skipped when the first converged), "
        "it: OSQP iterations per step; 2QP: the step with both alternations always run (as in the HIL scenes); "
        "per cvxpy solver: its step "
        "p50, x = its p50 over ours, |du| = largest input difference of the two solutions of the last QP "
        "(OSQP stops at eps 1e-3 and the cost is flat in omega: up to ~0.1 rad/s there); "
        "cpu: the step's CPU time, p50/p99 (the wall-clock percentiles add the time other processes took the core)",
    ]
    head = (f"{'H':>3} {'points':>6} {'reach':>5} {'cells':>5} {'rows':>5} {'p50':>6} {'p90':>6} {'p99':>6} {'max':>6} "
            f"{'sel%':>5} {'net%':>5} {'row%':>5} {'bld%':>5} {'slv%':>5} {'QPs':>4} {'it':>4} {'capped':>7} "
            f"{'2QP p50':>7} {'p99':>6} {'cpu p50/p99':>11}")
    for sv in solvers:
        head += f" | {sv + ' p50':>13} {'x':>6} {'|du|':>7}"
    lines.append(head)
    for r in rows:
        sh = r["share"]
        line = (
            f"{r['horizon']:>3} {r['points']:>6} {r['points_in_reach_median']:>5.0f} {r['cells_median']:>5.0f} "
            f"{r['constraint_rows_median']:>5.0f} "
            f"{r['p50_ms']:>6.2f} {r['p90_ms']:>6.2f} {r['p99_ms']:>6.2f} {r['max_ms']:>6.2f} "
            f"{100 * sh['select']:>5.0f} {100 * sh['net']:>5.0f} {100 * sh['rows']:>5.0f} "
            f"{100 * sh['build']:>5.0f} {100 * sh['solve']:>5.0f} {r['qp_solves'] / r['repeats']:>4.2f} "
            f"{r['iterations_median']:>4.0f} "
            f"{100 * r['capped_fraction']:>6.1f}% {r['two_qps_p50_ms']:>7.2f} {r['two_qps_p99_ms']:>6.2f} "
            f"{r['cpu_p50_ms']:>5.2f}/{r['cpu_p99_ms']:<5.2f}"
        )
        for sv in solvers:
            if f"cvxpy_{sv}_p50_ms" in r:
                du = r[f"cvxpy_{sv}_max_input_diff"]
                du_text = "failed" if du is None else f"{du:.1e}"
                line += f" | {r[f'cvxpy_{sv}_p50_ms']:>13.2f} {r[f'cvxpy_{sv}_ratio']:>6.1f} {du_text:>7}"
        lines.append(line)
    horizons = sorted({r["horizon"] for r in rows})
    counts = sorted({r["points"] for r in rows})
    by = {(r["horizon"], r["points"]): r for r in rows}
    lines.append("")
    lines.append("scaling: step p50 / p99 (ms) against points in range (rows) and horizon (columns)")
    lines.append(f"{'points':>6} " + " ".join(f"{'H=' + str(h):>13}" for h in horizons))
    for n in counts:
        cells = [f"{by[(h, n)]['p50_ms']:>6.2f}/{by[(h, n)]['p99_ms']:<6.2f}" if (h, n) in by else f"{'-':>13}"
                 for h in horizons]
        lines.append(f"{n:>6} " + " ".join(cells))
    for h in horizons:
        if (h, 1000) in by and (h, 10000) in by:
            g50 = by[(h, 10000)]["p50_ms"] / by[(h, 1000)]["p50_ms"]
            g99 = by[(h, 10000)]["p99_ms"] / by[(h, 1000)]["p99_ms"]
            lines.append(f"H={h}: 1,000 -> 10,000 points: step p50 x{g50:.2f}, p99 x{g99:.2f}")
    lines.extend(cap_warnings(rows))
    return "\n".join(lines)


def print_planner_benchmark(echo=print, **kwargs) -> list[dict]:
    """Run the benchmark and print its tables; returns the rows."""
    rows = run_planner_benchmark(**kwargs)
    echo(format_planner_table(rows))
    return rows


if __name__ == "__main__":
    print_planner_benchmark()
