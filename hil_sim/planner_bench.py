"""`dct bench planner`: planner step time (distance net + OSQP QP), against the same problem
written in cvxpy and solved with ECOS or Clarabel (the way NeuPAN solves it).

For each horizon H and constraint-point count n, the MPC gets K = ceil(n / H) points per pose,
so each QP carries about n collision rows (K per pose x H poses) and the distance model runs on
H x K (point, pose) pairs per alternation. The robot drives a straight corridor between two
walls (plus clutter) at 1 m/s in closed loop (kinematic unicycle), planning every 50 ms with the
default caps of MpcConfig. The cvxpy run uses the identical planner (same point selection, same
net, same linearization, same cost and constraints) with the QP backend swapped for a cvxpy
problem built once with Parameters and re-solved each alternation (cvxpy is benchmark-only).
"""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from runtime.planning.mpc import MpcConfig, MpcLimits, MpcLinearization, MpcPlanner, OsqpMpcBackend, QpOutcome
from runtime.planning.point_selection import PointSelectionConfig

TICK_S = 0.05


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
        try:
            self.problem.solve(solver=self.solver, warm_start=True)
        except self.cp.error.SolverError as exc:
            return QpOutcome(False, False, f"solver error: {exc}", 0, None, 0.0)
        status = str(self.problem.status)
        ok = status in ("optimal", "optimal_inaccurate") and self.U.value is not None
        iters = int(getattr(self.problem.solver_stats, "num_iters", 0) or 0)
        inputs = np.array(self.U.value) if ok else None
        slack = float(max(0.0, np.max(self.E.value))) if ok else 0.0
        return QpOutcome(ok, False, status, iters, inputs, slack)


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


def corridor_scene(length_m: float, rng: np.random.Generator) -> np.ndarray:
    """Two walls at y = +-0.45 m (2 cm spacing) from x = -1 to length_m, plus clutter beyond them."""
    x = np.arange(-1.0, length_m, 0.02)
    walls = np.concatenate([np.stack([x, np.full_like(x, 0.45)], 1), np.stack([x, np.full_like(x, -0.45)], 1)])
    n_clutter = int(len(x) / 2)
    cx = rng.uniform(-1.0, length_m, n_clutter)
    cy = np.sign(rng.uniform(-1, 1, n_clutter)) * rng.uniform(0.5, 1.2, n_clutter)
    return np.concatenate([walls, np.stack([cx, cy], 1)])


def _straight_reference(x0: float, H: int, step_s: float) -> np.ndarray:
    ref = np.zeros((H + 1, 3))
    ref[:, 0] = x0 + np.arange(H + 1) * step_s * 1.0
    ref[:, 2] = 1.0
    return ref


def _run_closed_loop(planner: MpcPlanner, points: np.ndarray, ticks: int) -> tuple[list[dict], list]:
    H, dt = planner.config.horizon_steps, planner.config.step_s
    state = np.zeros(3)
    u = np.array([1.0, 0.0])
    rows, results = [], []
    for _ in range(ticks):
        res = planner.plan(state, u, _straight_reference(state[0], H, dt), points)
        rows.append(res.timings_ms)
        results.append(res)
        u = res.commands[0].copy()
        for _ in range(5):
            state = state + 0.01 * np.array([u[0] * math.cos(state[2]), u[0] * math.sin(state[2]), u[1]])
    return rows, results


def _pct(values: list[float], q: float) -> float:
    return float(np.percentile(np.asarray(values), q))


def run_planner_benchmark(
    horizons: tuple[int, ...] = (10, 20),
    point_counts: tuple[int, ...] = (100, 1000),
    repeats: int = 300,
    cvxpy_repeats: int = 40,
    cvxpy_solvers: tuple[str, ...] = ("ECOS", "CLARABEL"),
    seed: int = 0,
    distance_net_path: str | Path | None = None,
) -> list[dict]:
    """Planner step time (select + net + QP) and the cvxpy formulation's, per (H, n); one dict each."""
    import torch

    from calibration.robot_description import load_robot_description

    torch.set_num_threads(1)
    robot = load_robot_description()
    model, model_name = load_distance_model(robot, distance_net_path)
    rng = np.random.default_rng(seed)
    out = []
    for H in horizons:
        for n in point_counts:
            K = max(1, math.ceil(n / H))
            cfg = MpcConfig(
                horizon_steps=H,
                tick_period_s=TICK_S,
                points=PointSelectionConfig(points_per_pose=K, voxel_size_m=0.0),
            )
            length = 2.0 + (repeats + 20) * TICK_S * 1.0 + H * cfg.step_s
            points = corridor_scene(length, rng)
            planner = MpcPlanner(cfg, robot, model)
            _run_closed_loop(planner, points, 10)  # warm-up (allocations, first solves)
            planner.plans = planner.capped_solves = planner.fallbacks = 0
            timings, results = _run_closed_loop(planner, points, repeats)
            step = [t["total"] for t in timings]
            row = {
                "horizon": H,
                "constraint_points": n,
                "points_per_pose": K,
                "rows_used_median": float(np.median([r.constraint_points for r in results])),
                "distance_model": model_name,
                "repeats": repeats,
                "step_median_ms": float(np.median(step)),
                "step_p99_ms": _pct(step, 99),
                "net_median_ms": float(np.median([t["net"] for t in timings])),
                "net_qp_median_ms": float(np.median([t["net"] + t["qp"] for t in timings])),
                "net_qp_p99_ms": _pct([t["net"] + t["qp"] for t in timings], 99),
                "qp_median_ms": float(np.median([t["qp"] for t in timings])),
                "qp_p99_ms": _pct([t["qp"] for t in timings], 99),
                "select_median_ms": float(np.median([t["select"] for t in timings])),
                "iterations_median": float(np.median([r.iterations for r in results])),
                "capped": planner.capped_solves,
                "fallbacks": planner.fallbacks,
            }
            lin_snapshot = planner.lin  # the last QP, for the cross-check below
            osqp_inputs = OsqpMpcBackend(cfg, planner.limits).solve(lin_snapshot, 1.0).inputs
            for solver in cvxpy_solvers:
                backend = CvxpyMpcBackend(cfg, planner.limits, solver)
                check = backend.solve(lin_snapshot)
                cv_planner = MpcPlanner(cfg, robot, model, qp_backend=backend)
                _run_closed_loop(cv_planner, points, 2)
                cv_timings, _ = _run_closed_loop(cv_planner, points, cvxpy_repeats)
                cv_step = [t["total"] for t in cv_timings]
                key = solver.lower()
                row[f"cvxpy_{key}_step_median_ms"] = float(np.median(cv_step))
                row[f"cvxpy_{key}_step_p99_ms"] = _pct(cv_step, 99)
                row[f"cvxpy_{key}_qp_median_ms"] = float(np.median([t["qp"] for t in cv_timings]))
                row[f"cvxpy_{key}_net_qp_median_ms"] = float(np.median([t["net"] + t["qp"] for t in cv_timings]))
                row[f"net_qp_speedup_vs_{key}"] = row[f"cvxpy_{key}_net_qp_median_ms"] / row["net_qp_median_ms"]
                row[f"speedup_vs_{key}"] = row[f"cvxpy_{key}_step_median_ms"] / row["step_median_ms"]
                row[f"qp_speedup_vs_{key}"] = row[f"cvxpy_{key}_qp_median_ms"] / row["qp_median_ms"]
                row[f"max_input_diff_vs_{key}"] = (
                    float(np.abs(check.inputs - osqp_inputs).max())
                    if check.ok and osqp_inputs is not None else float("nan")
                )
            out.append(row)
    return out


def format_planner_table(rows: list[dict]) -> str:
    """A plain-text table of run_planner_benchmark's rows.

    step: the whole planning step (select + net + QP + bookkeeping); net+qp: the issue's "planner
    step (net + QP)"; per cvxpy solver: its whole-step median and the speed-ups (x step, x net+qp,
    x qp) of ours over it, and |du| the largest input difference between the two solutions of
    the last QP (small weights on omega leave the optimum flat in omega: a few 1e-2 rad/s).
    """
    solvers = sorted({k[len("speedup_vs_"):] for r in rows for k in r if k.startswith("speedup_vs_")})
    head = (f"{'H':>3} {'pts':>5} {'K':>4} {'step med':>9} {'step p99':>9} {'net+qp':>7} {'n+q p99':>8}"
            f" {'net':>6} {'qp':>6} {'it':>4} {'cap':>4}")
    for s in solvers:
        head += f" | {s + ' step':>13} {'x step':>7} {'x n+q':>6} {'x qp':>6} {'|du|':>7}"
    lines = [f"distance model: {rows[0]['distance_model'] if rows else '-'}; times in ms", head]
    for r in rows:
        line = (
            f"{r['horizon']:>3} {r['constraint_points']:>5} {r['points_per_pose']:>4} {r['step_median_ms']:>9.2f} "
            f"{r['step_p99_ms']:>9.2f} {r['net_qp_median_ms']:>7.2f} {r['net_qp_p99_ms']:>8.2f} "
            f"{r['net_median_ms']:>6.2f} {r['qp_median_ms']:>6.2f} {r['iterations_median']:>4.0f} {r['capped']:>4}"
        )
        for s in solvers:
            line += (
                f" | {r[f'cvxpy_{s}_step_median_ms']:>13.2f} {r[f'speedup_vs_{s}']:>7.1f}"
                f" {r[f'net_qp_speedup_vs_{s}']:>6.1f} {r[f'qp_speedup_vs_{s}']:>6.1f}"
                f" {r[f'max_input_diff_vs_{s}']:>7.1e}"
            )
        lines.append(line)
    return "\n".join(lines)


def print_planner_benchmark(**kwargs) -> list[dict]:
    """Run the benchmark and print its table; returns the rows."""
    rows = run_planner_benchmark(**kwargs)
    print(format_planner_table(rows))
    return rows


if __name__ == "__main__":
    print_planner_benchmark()
