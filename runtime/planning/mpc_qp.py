"""The MPC's QP: the numbers of one QP (MpcLinearization), what a solve returns (QpOutcome),
the backend interface (QpBackend), and the OSQP backend: set up once on the fixed pattern of
runtime.planning.mpc_qp_layout, then each solve only `update(q, l, u, Ax)` + `warm_start` +
`solve()`.

Each solve is capped in iterations (`max_iterations`) and, in real time only, by the wall clock
(the time limit the planner passes); in lockstep (`wall_clock_caps=False`) only the iteration cap
applies, so the same inputs give the same solution under any machine load.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np
import osqp

from runtime.planning.mpc_config import MpcConfig, MpcLimits
from runtime.planning.mpc_qp_layout import QpLayout


@dataclass
class MpcLinearization:
    """The numbers of one QP: everything that changes from solve to solve (preallocated)."""

    horizon: int
    points_per_pose: int
    state0: np.ndarray = field(init=False)  # (3,)
    u_prev: np.ndarray = field(init=False)  # (2,) input applied now (start of the rate limit)
    a02: np.ndarray = field(init=False)  # (H,) d x_{h+1} / d theta_h = -dt v sin(theta)
    a12: np.ndarray = field(init=False)  # (H,) d y_{h+1} / d theta_h =  dt v cos(theta)
    b0: np.ndarray = field(init=False)  # (H,) dt cos(theta)
    b1: np.ndarray = field(init=False)  # (H,) dt sin(theta)
    offset: np.ndarray = field(init=False)  # (H, 3) c_h in s_{h+1} = A s_h + B u_h + c_h
    coll_coef: np.ndarray = field(init=False)  # (H, K, 3) row coefficients on (x_h, y_h, theta_h)
    coll_rhs: np.ndarray = field(init=False)  # (H, K) lower bound of the row
    coll_active: np.ndarray = field(init=False)  # (H, K) bool
    coll_slack_weight: np.ndarray = field(init=False)  # (H, K) L1 weight of each row's slack
    ref_xy: np.ndarray = field(init=False)  # (H, 2) targets for poses 1..H
    ref_yaw: np.ndarray = field(init=False)  # (H,)
    ref_v: np.ndarray = field(init=False)  # (H,) target speed of inputs 0..H-1
    u_lo: np.ndarray = field(init=False)  # (2,)
    u_hi: np.ndarray = field(init=False)  # (2,)
    du_max: np.ndarray = field(init=False)  # (2,) per step
    nominal_states: np.ndarray = field(init=False)  # (H+1, 3)
    nominal_inputs: np.ndarray = field(init=False)  # (H, 2)

    def __post_init__(self) -> None:
        h, k = self.horizon, self.points_per_pose
        self.state0 = np.zeros(3)
        self.u_prev = np.zeros(2)
        for name in ("a02", "a12", "b0", "b1", "ref_yaw", "ref_v"):
            setattr(self, name, np.zeros(h))
        self.offset = np.zeros((h, 3))
        self.coll_coef = np.zeros((h, k, 3))
        self.coll_rhs = np.zeros((h, k))
        self.coll_active = np.zeros((h, k), dtype=bool)
        self.coll_slack_weight = np.zeros((h, k))
        self.ref_xy = np.zeros((h, 2))
        self.u_lo = np.zeros(2)
        self.u_hi = np.zeros(2)
        self.du_max = np.zeros(2)
        self.nominal_states = np.zeros((h + 1, 3))
        self.nominal_inputs = np.zeros((h, 2))

    def set_dynamics(self, nominal_states: np.ndarray, nominal_inputs: np.ndarray, step_s: float) -> None:
        """The unicycle (12b) linearized along the nominal trajectory (states (H+1, 3), inputs (H, 2))."""
        dt = step_s
        th = nominal_states[:-1, 2]
        v = nominal_inputs[:, 0]
        c, s = np.cos(th), np.sin(th)
        self.a02[:] = -dt * v * s
        self.a12[:] = dt * v * c
        self.b0[:] = dt * c
        self.b1[:] = dt * s
        self.offset[:, 0] = dt * v * s * th
        self.offset[:, 1] = -dt * v * c * th
        self.offset[:, 2] = 0.0
        self.nominal_states[:] = nominal_states
        self.nominal_inputs[:] = nominal_inputs


@dataclass
class QpOutcome:
    ok: bool
    capped: bool
    status: str
    iterations: int
    inputs: np.ndarray | None  # (H, 2)
    max_slack_m: float
    build_ms: float = 0.0  # writing the QP's numbers into the solver (update)
    solve_ms: float = 0.0  # the solver's own run


class QpBackend(Protocol):
    """Solves the QP described by an MpcLinearization (OSQP here; cvxpy in the benchmark)."""

    def solve(self, lin: MpcLinearization, time_limit_s: float | None) -> QpOutcome: ...


class OsqpMpcBackend:
    """The QP in OSQP form with a fixed sparsity pattern (QpLayout); set up once, then update + solve."""

    #: OSQP's own default time limit (1e10 s): in effect, none.
    NO_TIME_LIMIT_S = 1.0e10

    def __init__(self, config: MpcConfig, limits: MpcLimits, wall_clock_caps: bool = True) -> None:
        """wall_clock_caps: cap each solve at qp_time_budget_s / alternations of wall-clock time
        (real time). False: iterations only (lockstep: deterministic under any load)."""
        self.config = config
        self.limits = limits
        self.wall_clock_caps = wall_clock_caps
        layout = QpLayout(config)
        self.layout = layout
        H = config.horizon_steps
        self.H, self.K = layout.H, layout.K
        self.n_s, self.n_u, self.n_e, self.n, self.m = layout.n_s, layout.n_u, layout.n_e, layout.n, layout.m
        self.r_box, self.r_rate, self.r_coll, self.r_slack = layout.r_box, layout.r_rate, layout.r_coll, layout.r_slack
        self._slices = layout.slices
        self._perm = layout.perm
        self._values = layout.values
        self._Ax = np.empty(layout.nnz)

        self._P = layout.cost_matrix(config)
        self._q = np.zeros(self.n)
        self._q[self.n_s + self.n_u :] = config.weights.slack_linear
        self._neg2_pos_w = np.full(H, -2.0 * config.weights.position)
        self._neg2_pos_w[-1] = -2.0 * config.weights.terminal_position
        self._l = np.zeros(self.m)
        self._u = np.zeros(self.m)
        # Constant bounds.
        self._u[self.r_coll : self.r_slack] = np.inf
        self._l[self.r_slack :] = 0.0
        self._u[self.r_slack :] = np.inf
        self._z_guess = np.zeros(self.n)
        self._solver = osqp.OSQP()
        self._solver.setup(
            self._P, self._q, layout.A, self._l, self._u,
            verbose=False, polishing=False, warm_starting=True,
            max_iter=config.max_iterations, eps_abs=config.eps_abs, eps_rel=config.eps_rel,
            time_limit=self._default_time_limit_s(),
            # Termination checked every 5 iterations, rho adapted when it is off by 2x (OSQP's
            # default 5x): see docs/decisions/planning-osqp-settings.md.
            check_termination=5,
            adaptive_rho_interval=25,  # fixed, not time-based: the same inputs give the same plan
            adaptive_rho_tolerance=2.0,
        )
        self._time_limit_s = self._default_time_limit_s()

    def _default_time_limit_s(self) -> float:
        if not self.wall_clock_caps:
            return self.NO_TIME_LIMIT_S
        return self.config.qp_time_budget_s / self.config.alternations

    # -- one solve ----------------------------------------------------------------------------
    def solve(self, lin: MpcLinearization, time_limit_s: float | None = None) -> QpOutcome:
        t_build = time.perf_counter()
        active = self._write_matrix(lin)
        self._write_vectors(lin, active)
        return self._run(lin, time_limit_s, t_build)

    def _write_matrix(self, lin: MpcLinearization) -> np.ndarray:
        """The varying entries of A (dynamics, collision rows) in OSQP's order; returns which
        collision rows are active, (H*K,) bool."""
        H, K = self.H, self.K
        vals, sl = self._values, self._slices
        vals[sl["a02"]] = lin.a02
        vals[sl["a12"]] = lin.a12
        vals[sl["b0"]] = lin.b0
        vals[sl["b1"]] = lin.b1
        coef = lin.coll_coef.reshape(H * K, 3)
        active = lin.coll_active.reshape(H * K)
        vals[sl["cx"]] = coef[:, 0] * active  # inactive rows: explicit zeros (fixed pattern)
        vals[sl["cy"]] = coef[:, 1] * active
        if "cth" in sl:
            vals[sl["cth"]] = coef[:, 2] * active
        np.take(vals, self._perm, out=self._Ax)
        return active

    def _write_vectors(self, lin: MpcLinearization, active: np.ndarray) -> None:
        """The cost's linear term q and the bounds l, u of this solve."""
        H, n_s, n_u = self.H, self.n_s, self.n_u
        w = self.config.weights
        q, l, u = self._q, self._l, self._u  # q: zero where not written (set up once)
        q[3 : n_s : 3] = self._neg2_pos_w * lin.ref_xy[:, 0]
        q[4 : n_s : 3] = self._neg2_pos_w * lin.ref_xy[:, 1]
        q[5 : n_s : 3] = -2 * w.heading * lin.ref_yaw
        q[n_s : n_s + n_u : 2] = -2 * w.speed * lin.ref_v
        q[n_s] += -2 * w.speed_change * lin.u_prev[0]
        q[n_s + 1] = -2 * w.angular_speed_change * lin.u_prev[1]
        q[n_s + n_u :] = lin.coll_slack_weight.reshape(-1)

        l[0:3] = lin.state0
        u[0:3] = lin.state0
        dyn = -lin.offset.reshape(-1)
        l[3 : 3 + 3 * H] = dyn
        u[3 : 3 + 3 * H] = dyn
        rb, rr, rc = self.r_box, self.r_rate, self.r_coll
        l[rb:rr:2], l[rb + 1 : rr : 2] = lin.u_lo[0], lin.u_lo[1]
        u[rb:rr:2], u[rb + 1 : rr : 2] = lin.u_hi[0], lin.u_hi[1]
        l[rr:rc:2], l[rr + 1 : rc : 2] = -lin.du_max[0], -lin.du_max[1]
        u[rr:rc:2], u[rr + 1 : rc : 2] = lin.du_max[0], lin.du_max[1]
        l[rr : rr + 2] += lin.u_prev
        u[rr : rr + 2] += lin.u_prev
        l[rc : self.r_slack] = np.where(active, lin.coll_rhs.reshape(-1), -np.inf)

    def _run(self, lin: MpcLinearization, time_limit_s: float | None, t_build: float) -> QpOutcome:
        """Hand the numbers to OSQP, warm-start at the nominal trajectory, solve."""
        H, n_s, n_u = self.H, self.n_s, self.n_u
        solver = self._solver
        solver.update(q=self._q, l=self._l, u=self._u, Ax=self._Ax)
        if not self.wall_clock_caps:
            time_limit_s = None
        if time_limit_s is not None and time_limit_s != self._time_limit_s:
            solver.update_settings(time_limit=time_limit_s)
            self._time_limit_s = time_limit_s
        z = self._z_guess
        z[:n_s] = lin.nominal_states.reshape(-1)
        z[n_s : n_s + n_u] = lin.nominal_inputs.reshape(-1)
        z[n_s + n_u :] = 0.0
        solver.warm_start(x=z)
        t_solve = time.perf_counter()
        res = solver.solve(raise_error=False)
        t_done = time.perf_counter()
        status_val = res.info.status_val
        ok = status_val in (1, 2)  # solved, solved inaccurate
        capped = status_val in (7, 8)  # max iterations, time limit
        inputs = None
        max_slack = 0.0
        if ok:
            inputs = res.x[n_s : n_s + n_u].reshape(H, 2).copy()
            max_slack = float(max(0.0, res.x[n_s + n_u :].max()))
        return QpOutcome(
            ok, capped, str(res.info.status), int(res.info.iter), inputs, max_slack,
            build_ms=(t_solve - t_build) * 1e3, solve_ms=(t_done - t_solve) * 1e3,
        )
