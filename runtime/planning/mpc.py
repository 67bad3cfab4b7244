"""The MPC of paper eq. (12)-(13), solved with OSQP, collision rows from a distance model.

State s = (x, y, theta), input u = (v, omega), unicycle s_{h+1} = s_h + f(s_h, u_h) dt (12b),
linearized along a nominal trajectory (the previous plan, shifted). Input and rate bounds (12c).
Collision (12d): for the K P_fix points nearest to each predicted pose h = 1..H, the model's dual
(mu, lambda) at the nominal pose gives a row linear in the pose,

    d(s_h) ~ d_bar + lambda_w^T (t_h - t_bar) + dd/dtheta (theta_h - theta_bar) >= r_hk - e_hk,

with lambda_w = R(theta_bar) lam_robot = -R G^T mu (the gradient of the dual objective in t) and
an L1-penalized slack e_hk >= 0 so that the QP is always feasible. The required clearance r_hk is
d_min, or the point's distance to the footprint now where that is smaller ("never plan deeper":
such a row holds with standing still, and its slack costs `slack_linear_holding`). Cost (13):
track the reference waypoints (position, heading, speed), re-timed so that their speed rises from
the speed now within the acceleration limit, and penalize input changes. Issue 10 (the MPC stood
still beside obstacles with a valid reference) came from rows it could not meet, targets it
could not reach and a linearization about a standstill; the methods say which does what.

The QP has a fixed sparsity pattern: all H*K collision rows are always present (unused ones have
zero coefficients, kept as explicit entries, and a lower bound of -inf), so OSQP is set up once
and each tick only `update(q, l, u, Ax)` + `warm_start` + `solve()`. Net and QP alternate up to
`alternations` times (NeuPAN's PAN iterations; the next is skipped when the solution stayed within
a millimetre of the poses the QP was linearized about, see MpcPlanner._converged). Each solve is
capped in iterations, and in real time also by the wall clock (`qp_time_budget_s`); on a cap the planner falls back to the shifted
previous plan and counts it. In lockstep (`wall_clock_caps=False`) only the iteration cap
applies, so the same inputs give the same plan under any machine load (DESIGN.md section 6).
"""
from __future__ import annotations

import math
import sys
import time
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np
import osqp
import scipy.sparse as sp
from pydantic import BaseModel, ConfigDict, Field, model_validator

from runtime.planning.distance_model import (
    DistanceModel,
    check_dual_output,
    footprint_distance_to_points,
    rectangle_signed_distance,
)
from runtime.planning.errors import PlannerInputError, check_points, check_vector
from runtime.planning.point_selection import PointSelectionConfig, PointSelector


class MpcWeights(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)

    position: float = Field(default=10.0, ge=0.0)
    terminal_position: float = Field(default=20.0, ge=0.0)
    heading: float = Field(default=0.3, ge=0.0)
    speed: float = Field(default=1.0, ge=0.0)
    angular_speed: float = Field(default=0.05, ge=0.0)
    speed_change: float = Field(default=2.0, ge=0.0)
    angular_speed_change: float = Field(default=0.3, ge=0.0)
    slack_linear: float = Field(default=200.0, gt=0.0, description="L1 weight of collision slack (per m)")
    slack_quadratic: float = Field(default=100.0, ge=0.0)
    slack_linear_holding: float = Field(
        default=2000.0,
        gt=0.0,
        description="L1 weight of the slack of rows that hold the current clearance (points already "
        "nearer than d_min, see MpcPlanner._required_clearance), per m",
    )


class MpcConfig(BaseModel):
    """MPC settings (robot limits come from the robot description)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    horizon_steps: int = Field(default=10, ge=2, le=60, description="H")
    step_s: float = Field(default=0.1, gt=0.0, le=1.0, description="dt of the prediction model")
    tick_period_s: float = Field(default=0.05, gt=0.0, le=1.0, description="shift of the previous plan per tick")
    alternations: int = Field(default=2, ge=1, le=10, description="net/QP alternations per tick (at most)")
    alternation_tolerance_m: float = Field(
        default=0.001, ge=0.0, le=0.1,
        description="stop alternating when the solution moved no predicted position farther than this from "
        "the poses it was linearized about (and no heading more than alternation_tolerance_rad): the next "
        "linearization would change the QP by less than its own tolerance (eps 1e-3). 0 = always alternate",
    )
    alternation_tolerance_rad: float = Field(default=0.001, ge=0.0, le=0.1)
    d_min_m: float = Field(default=0.03, ge=0.0, le=1.0, description="minimum footprint distance to P_fix")
    max_reverse_speed_mps: float = Field(default=0.3, ge=0.0, le=5.0, description="v_rev")
    linearize_heading: bool = Field(
        default=True,
        description="collision rows also depend on theta (the paper's rows are linear in position only)",
    )
    max_iterations: int = Field(
        default=1000, ge=10, le=100000,
        description="OSQP iterations per solve: the cap (measured need in the library's scenes: at most 515, "
        "p99 under 380; 200 capped 15 of 283 solves at gap_offset)",
    )
    qp_time_budget_s: float = Field(
        default=0.008, gt=0.0, le=1.0, description="all alternations together; wall clock, real time only"
    )
    eps_abs: float = Field(default=1e-3, gt=0.0)
    eps_rel: float = Field(default=1e-3, gt=0.0)
    weights: MpcWeights = MpcWeights()
    points: PointSelectionConfig = PointSelectionConfig()

    @model_validator(mode="after")
    def _check(self) -> "MpcConfig":
        if self.tick_period_s > self.step_s * self.horizon_steps:
            raise ValueError(
                f"tick_period_s ({self.tick_period_s}) is longer than the horizon "
                f"({self.horizon_steps} x {self.step_s} s)"
            )
        return self


class MpcLimits(BaseModel):
    """Input bounds (12c): speeds and per-step rate limits."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    v_min_mps: float = Field(le=0.0)
    v_max_mps: float = Field(gt=0.0)
    omega_max_radps: float = Field(gt=0.0)
    accel_mps2: float = Field(gt=0.0)
    angular_accel_radps2: float = Field(gt=0.0)

    @classmethod
    def from_robot(cls, robot, max_reverse_speed_mps: float) -> "MpcLimits":
        lim = robot.limits
        return cls(
            v_min_mps=-float(max_reverse_speed_mps),
            v_max_mps=lim.max_linear_speed_mps,
            omega_max_radps=robot.body_max_angular_speed_radps,  # body yaw rate, skid slip included
            accel_mps2=lim.max_linear_accel_mps2,
            angular_accel_radps2=robot.body_max_angular_accel_radps2,
        )


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


@dataclass
class PlanResult:
    commands: np.ndarray  # (H, 2) v_mps, omega_radps; commands[0] is applied now
    states: np.ndarray  # (H+1, 3) predicted with the nonlinear model, states[0] = current state
    solve_status: str
    iterations: int  # OSQP iterations over all alternations
    capped: bool  # some solve hit the iteration or time cap
    fallback: bool  # commands are the shifted previous plan (or a braking plan), not a fresh solve
    timings_ms: dict[str, float]  # select, net, rows, build, solve, qp (= build + solve), check, total
    min_predicted_distance_m: float  # exact footprint distance of states[1:] to their constraint points
    max_slack_m: float
    constraint_points: int  # valid (point, pose) rows in the last QP
    alternations_done: int


def unicycle_rollout(state: np.ndarray, inputs: np.ndarray, step_s: float, out: np.ndarray | None = None) -> np.ndarray:
    """States (H+1, 3) of s_{h+1} = s_h + f(s_h, u_h) dt (eq. 12b, explicit Euler as in the QP)."""
    h = inputs.shape[0]
    if out is None:
        out = np.empty((h + 1, 3))
    out[0] = state
    # theta first (it does not depend on x, y), then positions from the theta at each step start.
    out[1:, 2] = state[2] + np.cumsum(inputs[:, 1]) * step_s
    th = out[:-1, 2]
    out[1:, 0] = state[0] + np.cumsum(inputs[:, 0] * np.cos(th)) * step_s
    out[1:, 1] = state[1] + np.cumsum(inputs[:, 0] * np.sin(th)) * step_s
    return out


class OsqpMpcBackend:
    """The QP in OSQP form with a fixed sparsity pattern; set up once, then update + solve.

    Variables z = [s_0..s_H (3(H+1)), u_0..u_{H-1} (2H), e_{1,1}..e_{H,K} (HK)].
    Rows: initial state (3), dynamics (3H), input bounds (2H), rate bounds (2H),
    collision (HK), slack >= 0 (HK).
    """

    #: OSQP's own default time limit (1e10 s): in effect, none.
    NO_TIME_LIMIT_S = 1.0e10

    def __init__(self, config: MpcConfig, limits: MpcLimits, wall_clock_caps: bool = True) -> None:
        """wall_clock_caps: cap each solve at qp_time_budget_s / alternations of wall-clock time
        (real time). False: iterations only (lockstep: deterministic under any load)."""
        self.config = config
        self.limits = limits
        self.wall_clock_caps = wall_clock_caps
        H = config.horizon_steps
        K = config.points.points_per_pose
        self.H, self.K = H, K
        dt = config.step_s
        self.n_s, self.n_u, self.n_e = 3 * (H + 1), 2 * H, H * K
        self.n = self.n_s + self.n_u + self.n_e
        sx = lambda h: 3 * h  # noqa: E731
        uv = lambda h: self.n_s + 2 * h  # noqa: E731
        hs = np.arange(H)

        rows: list[np.ndarray] = []
        cols: list[np.ndarray] = []
        vals: list[np.ndarray] = []
        self._slices: dict[str, slice] = {}
        nnz = 0

        def add(name: str | None, r, c, v) -> None:
            nonlocal nnz
            r = np.asarray(r, dtype=np.int64).ravel()
            c = np.asarray(c, dtype=np.int64).ravel()
            v = np.broadcast_to(np.asarray(v, dtype=np.float64), r.shape).ravel()
            rows.append(r)
            cols.append(c)
            vals.append(v.copy())
            if name is not None:
                self._slices[name] = slice(nnz, nnz + r.size)
            nnz += r.size

        # Initial state.
        add(None, [0, 1, 2], [0, 1, 2], 1.0)
        r_dyn = 3
        rx, ry, rt = r_dyn + 3 * hs, r_dyn + 3 * hs + 1, r_dyn + 3 * hs + 2
        add(None, rx, sx(hs), 1.0)
        add("a02", rx, sx(hs) + 2, 0.0)
        add("b0", rx, uv(hs), 0.0)
        add(None, rx, sx(hs + 1), -1.0)
        add(None, ry, sx(hs) + 1, 1.0)
        add("a12", ry, sx(hs) + 2, 0.0)
        add("b1", ry, uv(hs), 0.0)
        add(None, ry, sx(hs + 1) + 1, -1.0)
        add(None, rt, sx(hs) + 2, 1.0)
        add(None, rt, uv(hs) + 1, dt)
        add(None, rt, sx(hs + 1) + 2, -1.0)
        self.r_box = r_dyn + 3 * H
        add(None, self.r_box + np.arange(2 * H), self.n_s + np.arange(2 * H), 1.0)
        self.r_rate = self.r_box + 2 * H
        add(None, self.r_rate + np.arange(2 * H), self.n_s + np.arange(2 * H), 1.0)
        add(None, self.r_rate + 2 + np.arange(2 * H - 2), self.n_s + np.arange(2 * H - 2), -1.0)
        self.r_coll = self.r_rate + 2 * H
        hk_h = np.repeat(hs + 1, K)  # pose index 1..H of each collision row
        r_c = self.r_coll + np.arange(H * K)
        add("cx", r_c, sx(hk_h), 0.0)
        add("cy", r_c, sx(hk_h) + 1, 0.0)
        if config.linearize_heading:  # else the rows do not touch theta: no entries to factorize
            add("cth", r_c, sx(hk_h) + 2, 0.0)
        e_cols = self.n_s + self.n_u + np.arange(H * K)
        add(None, r_c, e_cols, 1.0)
        self.r_slack = self.r_coll + H * K
        add(None, self.r_slack + np.arange(H * K), e_cols, 1.0)
        self.m = self.r_slack + H * K

        r_all, c_all, v_all = np.concatenate(rows), np.concatenate(cols), np.concatenate(vals)
        # CSC with a known map from our entry order to OSQP's data order: build it from entry ids.
        ids = sp.csc_matrix((np.arange(1, nnz + 1, dtype=np.float64), (r_all, c_all)), shape=(self.m, self.n))
        ids.sort_indices()
        if ids.nnz != nnz:
            raise AssertionError("OsqpMpcBackend: duplicate entries in the constraint pattern")
        self._perm = ids.data.astype(np.int64) - 1  # csc position -> our entry index
        self._values = v_all  # our order; varying groups rewritten each solve
        self._Ax = np.empty(nnz)
        A = sp.csc_matrix((self._values[self._perm], ids.indices.copy(), ids.indptr.copy()), shape=(self.m, self.n))

        self._P = self._build_cost_matrix()
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
            self._P, self._q, A, self._l, self._u,
            verbose=False, polishing=False, warm_starting=True,
            max_iter=config.max_iterations, eps_abs=config.eps_abs, eps_rel=config.eps_rel,
            time_limit=self._default_time_limit_s(),
            # Measured on every QP of gap_offset, corridor_boxes, corridor_l and case2 replayed
            # (issue 12): checking every 5 iterations and adapting rho when it is off by 2x
            # (OSQP's default 5x) cut the most iterations any solve needed from 530-710 to
            # 270-515 and the mean by 15-30%.
            check_termination=5,
            adaptive_rho_interval=25,  # fixed, not time-based: the same inputs give the same plan
            adaptive_rho_tolerance=2.0,
        )
        self._time_limit_s = self._default_time_limit_s()

    def _default_time_limit_s(self) -> float:
        if not self.wall_clock_caps:
            return self.NO_TIME_LIMIT_S
        return self.config.qp_time_budget_s / self.config.alternations

    # -- cost ---------------------------------------------------------------------------------
    def _build_cost_matrix(self) -> sp.csc_matrix:
        w = self.config.weights
        H, n_s = self.H, self.n_s
        diag = np.zeros(self.n)
        pos_w = np.full(H, w.position)
        pos_w[-1] = w.terminal_position
        diag[3 * np.arange(1, H + 1)] = 2 * pos_w
        diag[3 * np.arange(1, H + 1) + 1] = 2 * pos_w
        diag[3 * np.arange(1, H + 1) + 2] = 2 * w.heading
        dv, dw = w.speed_change, w.angular_speed_change
        # Input changes: (u_0 - u_prev)^2 + sum_h (u_h - u_{h-1})^2.
        cnt = np.full(H, 2.0)
        cnt[-1] = 1.0
        diag[n_s + 2 * np.arange(H)] = 2 * w.speed + 2 * dv * cnt
        diag[n_s + 2 * np.arange(H) + 1] = 2 * w.angular_speed + 2 * dw * cnt
        diag[n_s + self.n_u :] = 2 * w.slack_quadratic + 1e-6
        r = [np.arange(self.n), n_s + 2 * np.arange(H - 1), n_s + 2 * np.arange(H - 1) + 1]
        c = [np.arange(self.n), n_s + 2 * np.arange(1, H), n_s + 2 * np.arange(1, H) + 1]
        v = [diag, np.full(H - 1, -2 * dv), np.full(H - 1, -2 * dw)]
        P = sp.csc_matrix((np.concatenate(v), (np.concatenate(r), np.concatenate(c))), shape=(self.n, self.n))
        return sp.triu(P, format="csc")

    # -- one solve ----------------------------------------------------------------------------
    def solve(self, lin: MpcLinearization, time_limit_s: float | None = None) -> QpOutcome:
        t_build = time.perf_counter()
        H, K, n_s, n_u = self.H, self.K, self.n_s, self.n_u
        w = self.config.weights
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

        solver = self._solver
        solver.update(q=q, l=l, u=u, Ax=self._Ax)
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


class MpcPlanner:
    """Plans (v, omega) over H steps around P_fix; see the module docstring."""

    def __init__(
        self,
        config: MpcConfig,
        robot,
        distance_model: DistanceModel,
        qp_backend: QpBackend | None = None,
        wall_clock_caps: bool = True,
    ) -> None:
        """wall_clock_caps: False in lockstep (iteration caps only; see the module docstring)."""
        if not callable(getattr(distance_model, "dual", None)):
            raise PlannerInputError(f"MpcPlanner: distance_model {type(distance_model).__name__} has no dual()")
        if "torch" in sys.modules:  # the distance net runs on one thread (ENVIRONMENT.md)
            sys.modules["torch"].set_num_threads(1)
        self.config = config
        self.robot = robot
        self.distance_model = distance_model
        self.half_length_m = robot.footprint.length_m / 2.0
        self.half_width_m = robot.footprint.width_m / 2.0
        self.limits = MpcLimits.from_robot(robot, config.max_reverse_speed_mps)
        self.selector = PointSelector(config.points, self.half_length_m, self.half_width_m)
        self.wall_clock_caps = wall_clock_caps
        self.backend: QpBackend = (
            qp_backend if qp_backend is not None else OsqpMpcBackend(config, self.limits, wall_clock_caps)
        )
        H, K = config.horizon_steps, config.points.points_per_pose
        self.lin = MpcLinearization(H, K)
        self._prev_commands: np.ndarray | None = None
        self._ticks_since_plan = 0
        self._dummy_far = np.array([1.0e3, 0.0])
        self._local = np.empty((H, K, 2))  # robot-frame points of the net's batch
        # Counters (never reset by plan()).
        self.plans = 0
        self.capped_solves = 0  # plans in which a solve hit its cap
        self.fallbacks = 0
        self.qp_solves = 0  # every QP solve (alternations count one each)
        self.qp_capped = 0  # solves that hit the iteration (or, in real time, the time) cap
        self.alternations_skipped = 0  # alternations not needed (the linearization had converged)
        self.last_selection = None

    def reset(self) -> None:
        """Forget the previous plan (e.g. after a stop or a new goal far away)."""
        self._prev_commands = None
        self._ticks_since_plan = 0

    def warm_up(self, plans: int = 4) -> None:
        """Plan a few times on a synthetic corridor, then forget it: TorchScript's profiling
        executor optimizes the net only after its first calls (the first one takes ~20 ms) and
        OSQP allocates on its first solve. Call before the loop starts, never in a tick."""
        H, dt = self.config.horizon_steps, self.config.step_s
        v = 0.5 * self.limits.v_max_mps
        reference = np.zeros((H + 1, 3))
        reference[:, 0] = np.arange(H + 1) * v * dt
        reference[:, 2] = v
        x = np.arange(-1.0, 3.0, 0.05)
        wall = np.concatenate([np.stack([x, np.full_like(x, 0.5)], 1), np.stack([x, np.full_like(x, -0.5)], 1)])
        counters = (self.plans, self.capped_solves, self.fallbacks, self.qp_solves, self.qp_capped,
                    self.alternations_skipped)
        for _ in range(plans):
            self.plan(np.zeros(3), np.array([v, 0.0]), reference, wall)
        (self.plans, self.capped_solves, self.fallbacks, self.qp_solves, self.qp_capped,
         self.alternations_skipped) = counters
        self.reset()
        self.last_selection = None

    # -- helpers ------------------------------------------------------------------------------
    def _shifted_previous(self, ticks: int) -> np.ndarray | None:
        if self._prev_commands is None:
            return None
        H = self.config.horizon_steps
        shift = ticks * self.config.tick_period_s / self.config.step_s
        t = np.arange(H) + shift
        prev = self._prev_commands
        grid = np.arange(H)
        return np.stack([np.interp(t, grid, prev[:, 0]), np.interp(t, grid, prev[:, 1])], axis=1)

    def _converged(self, linearized_at: np.ndarray, solution_states: np.ndarray) -> bool:
        """The solution stayed within the alternation tolerances of the poses the QP was
        linearized about: another net/QP alternation would re-linearize at (almost) the same
        poses, changing the QP by less than the solver's own tolerance (MpcConfig)."""
        d = np.abs(solution_states - linearized_at)
        return bool(d[:, :2].max() <= self.config.alternation_tolerance_m
                    and d[:, 2].max() <= self.config.alternation_tolerance_rad)

    def _enforce_bounds(self, inputs: np.ndarray) -> np.ndarray:
        """Project a solution onto the box and rate bounds exactly (OSQP meets them to eps_abs)."""
        lin = self.lin
        out = np.empty_like(inputs)
        lo0, lo1, hi0, hi1 = float(lin.u_lo[0]), float(lin.u_lo[1]), float(lin.u_hi[0]), float(lin.u_hi[1])
        d0, d1 = float(lin.du_max[0]), float(lin.du_max[1])
        p0, p1 = float(lin.u_prev[0]), float(lin.u_prev[1])
        for h in range(inputs.shape[0]):  # H steps, not points
            p0 = min(max(float(inputs[h, 0]), p0 - d0, lo0), p0 + d0, hi0)
            p1 = min(max(float(inputs[h, 1]), p1 - d1, lo1), p1 + d1, hi1)
            out[h, 0], out[h, 1] = p0, p1
        return out

    def _braking_plan(self, u_now: np.ndarray) -> np.ndarray:
        """Decelerate to standstill at the rate limits (used when no previous plan exists)."""
        H, dt = self.config.horizon_steps, self.config.step_s
        k = np.arange(1, H + 1)
        v = np.sign(u_now[0]) * np.maximum(abs(u_now[0]) - k * self.limits.accel_mps2 * dt, 0.0)
        w = np.sign(u_now[1]) * np.maximum(abs(u_now[1]) - k * self.limits.angular_accel_radps2 * dt, 0.0)
        return np.stack([v, w], axis=1)

    def _reachable_reference(self, reference: np.ndarray, v_now_mps: float) -> np.ndarray:
        """The reference re-timed along its own polyline so that its speed rises from the speed
        now at no more than the acceleration limit (never faster than the reference's own).

        The reference path is resampled at the target speed whatever the robot does, so from a
        standstill its waypoints run away at 1 m/s while the rate limits allow 0.2, 0.4, ... m/s:
        position errors of 0.2-0.3 m that no input can remove. Their gradient buys collision
        slack at the L1 price (the plan cuts into d_min to turn early), and the supervisor then
        stops the command. Targets the inputs can reach keep tracking and slack in proportion."""
        H, dt = self.config.horizon_steps, self.config.step_s
        xy = reference[:, :2]
        v_ref = reference[:H, 2]
        direction = -1.0 if np.all(v_ref <= 0.0) and np.any(v_ref < 0.0) else 1.0  # reversing reference
        seg = np.hypot(*np.diff(xy, axis=0).T)
        cum = np.concatenate([[0.0], np.cumsum(seg)])
        speed_now = max(direction * v_now_mps, 0.0)
        reachable = speed_now + self.limits.accel_mps2 * dt * np.arange(1, H + 1)
        speed = np.minimum(np.abs(v_ref), reachable)
        s = np.minimum(np.concatenate([[0.0], np.cumsum(speed * dt)]), cum[-1])
        out = np.empty_like(reference)
        out[:, 0] = np.interp(s, cum, xy[:, 0])
        out[:, 1] = np.interp(s, cum, xy[:, 1])
        out[:H, 2] = direction * speed
        out[H, 2] = reference[H, 2]
        return out

    def _reference_following_inputs(self, state: np.ndarray) -> np.ndarray:
        """(H, 2) inputs that follow the reference within the box and rate bounds: turn towards
        each waypoint's heading, drive at its speed scaled by the cosine of the heading error.

        The nominal trajectory when no moving plan exists (first plan, or the robot stopped).
        Straight ahead at the reference speeds, as before, drives the nominal poses into whatever
        the robot faces when the path leaves sideways (a start turned 60 degrees in a corridor):
        the collision rows are then linearized at poses deep inside a wall, where they describe
        nothing reachable, and the QP plans through it (slack 0.13 m; the supervisor stops every
        command)."""
        lin, H, dt = self.lin, self.config.horizon_steps, self.config.step_s
        out = np.empty((H, 2))
        theta = float(state[2])
        v, w = float(lin.u_prev[0]), float(lin.u_prev[1])
        for h in range(H):  # H scalar steps
            err = (float(lin.ref_yaw[h]) - theta + math.pi) % (2 * math.pi) - math.pi
            w_goal = min(max(err / dt, -lin.u_hi[1]), lin.u_hi[1])
            v_goal = min(max(float(lin.ref_v[h]) * max(math.cos(err), 0.0), lin.u_lo[0]), lin.u_hi[0])
            w = min(max(w_goal, w - lin.du_max[1]), w + lin.du_max[1])
            v = min(max(v_goal, v - lin.du_max[0]), v + lin.du_max[0])
            out[h] = v, w
            theta += w * dt
        return out

    def _set_reference(self, state: np.ndarray, reference: np.ndarray) -> None:
        lin, H = self.lin, self.config.horizon_steps
        lin.ref_xy[:] = reference[1:, :2]
        lin.ref_v[:] = reference[:H, 2]
        d = np.diff(reference[:, :2], axis=0)  # (H, 2) segment h -> h+1
        seg = np.hypot(d[:, 0], d[:, 1])
        yaw = np.arctan2(d[:, 1], d[:, 0]) + np.where(reference[:H, 2] < 0.0, math.pi, 0.0)
        # Where the reference does not move (at the goal), keep the heading of the last moving
        # segment, or the current heading if there is none.
        moving = seg > 1e-6
        idx = np.where(moving, np.arange(H), -1)
        np.maximum.accumulate(idx, out=idx)
        yaw = np.where(idx >= 0, yaw[np.maximum(idx, 0)], state[2])
        # Unwrapped from the current heading: each step of the sequence taken the short way round.
        steps = np.diff((yaw - state[2] + math.pi) % (2 * math.pi) - math.pi, prepend=0.0)
        lin.ref_yaw[:] = state[2] + np.cumsum((steps + math.pi) % (2 * math.pi) - math.pi)

    def _linearize_dynamics(self, nominal_states: np.ndarray, nominal_inputs: np.ndarray) -> None:
        lin, dt = self.lin, self.config.step_s
        th = nominal_states[:-1, 2]
        v = nominal_inputs[:, 0]
        c, s = np.cos(th), np.sin(th)
        lin.a02[:] = -dt * v * s
        lin.a12[:] = dt * v * c
        lin.b0[:] = dt * c
        lin.b1[:] = dt * s
        lin.offset[:, 0] = dt * v * s * th
        lin.offset[:, 1] = -dt * v * c * th
        lin.offset[:, 2] = 0.0
        lin.nominal_states[:] = nominal_states
        lin.nominal_inputs[:] = nominal_inputs

    def _select_points(self, nominal_states: np.ndarray, points_world: np.ndarray, timings: dict) -> None:
        """The K P_fix points nearest to each nominal pose; once per plan, kept for all alternations
        (NeuPAN's PAN iterations also keep the point set and re-run only the net and the QP)."""
        t0 = time.perf_counter()
        self.last_selection = self.selector.select(nominal_states[1:], points_world, points_checked=True)
        timings["select"] += (time.perf_counter() - t0) * 1e3

    def _selected_in_pose_frames(self, poses: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(cos, sin) of the poses' yaw (H, 1) and the selected points in pose h's frame, written
        into the preallocated (H, K, 2) buffer."""
        sel = self.last_selection
        c, s = np.cos(poses[:, 2])[:, None], np.sin(poses[:, 2])[:, None]
        dx = sel.points_world[..., 0] - poses[:, 0, None]
        dy = sel.points_world[..., 1] - poses[:, 1, None]
        local = self._local
        local[..., 0] = c * dx + s * dy
        local[..., 1] = -s * dx + c * dy
        return c, s, local

    def _collision_rows(self, nominal_states: np.ndarray, timings: dict) -> int:
        """Run the distance model at the nominal poses on the selected points and fill the rows."""
        lin, H, K = self.lin, self.config.horizon_steps, self.config.points.points_per_pose
        sel = self.last_selection
        t1 = time.perf_counter()
        poses = nominal_states[1:]
        c, s, local = self._selected_in_pose_frames(poses)
        local[~sel.valid] = self._dummy_far  # fixed-size batch for the net; rows inactive anyway
        n = H * K
        mu, lam_r, dist = check_dual_output(self.distance_model.dual(local.reshape(n, 2)), n)
        t2 = time.perf_counter()
        lam_r = lam_r.reshape(H, K, 2)
        dist = dist.reshape(H, K)
        lx = c * lam_r[..., 0] - s * lam_r[..., 1]  # lambda_w = R lam_robot
        ly = s * lam_r[..., 0] + c * lam_r[..., 1]
        coef = lin.coll_coef
        coef[..., 0] = lx
        coef[..., 1] = ly
        required = self._required_clearance(sel)
        rhs = required - dist + lx * poses[:, 0, None] + ly * poses[:, 1, None]
        if self.config.linearize_heading:
            lth = lam_r[..., 1] * local[..., 0] - lam_r[..., 0] * local[..., 1]
            coef[..., 2] = lth
            rhs += lth * poses[:, 2, None]
        lin.coll_rhs[:] = rhs
        lin.coll_active[:] = sel.valid
        w = self.config.weights
        lin.coll_slack_weight[:] = np.where(required < self.config.d_min_m, w.slack_linear_holding, w.slack_linear)
        timings["net"] += (t2 - t1) * 1e3
        timings["rows"] += (time.perf_counter() - t2) * 1e3
        return sel.count

    def _required_clearance(self, sel) -> np.ndarray:
        """(H, K) clearance each row demands: d_min, or, for a point the footprint at the current
        pose is already nearer to than d_min, that current distance ("never plan deeper").

        A non-holonomic robot cannot step sideways out of d_min within 0.1 s, so a row demanding
        d_min of such a point is violated by every plan: its slack is paid anyway, and the QP
        then trades further millimetres of penetration for tracking at the slack's flat L1 price.
        The safety supervisor stops any command that brings the footprint nearer than now inside
        d_stop, so that plan is refused tick after tick (issue 10's stall: zero command with
        solved QPs, no fallback). Demanding the current distance keeps every row satisfiable
        (standing still meets it), so the exact L1 penalty holds it, and the plan slides along
        or away from the point, which the supervisor accepts."""
        pts = sel.points_world
        d_now = footprint_distance_to_points(
            self.lin.state0[None], pts.reshape(-1, 2), self.half_length_m, self.half_width_m
        ).reshape(pts.shape[:2])
        return np.minimum(self.config.d_min_m, d_now)

    def _linearize_collisions(self, nominal_states: np.ndarray, points_world: np.ndarray, timings: dict) -> int:
        """Select the points at the nominal poses, then fill the collision rows (both steps)."""
        points_world = check_points(points_world, "MpcPlanner._linearize_collisions: points_world")
        self._select_points(nominal_states, points_world, timings)
        return self._collision_rows(nominal_states, timings)

    # -- the planning step --------------------------------------------------------------------
    def plan(
        self,
        state: np.ndarray,
        current_input: np.ndarray,
        reference: np.ndarray,
        points_fix_world: np.ndarray,
        speed_bounds_mps: tuple[float, float] | None = None,
    ) -> PlanResult:
        """One planning step.

        state (x_m, y_m, yaw_rad) in the odom frame; current_input (v_mps, omega_radps) being
        applied now (start of the rate limits); reference (H+1, 3) waypoints (x_m, y_m, v_mps),
        row 0 at the robot; points_fix_world (N, 2) P_fix in the odom frame. speed_bounds_mps
        narrows [v_min, v_max] for this step (correcting mode reverses with [-v_rev, 0]).
        """
        t_start = time.perf_counter()
        cfg, lim, lin = self.config, self.limits, self.lin
        H = cfg.horizon_steps
        state = check_vector(state, 3, "MpcPlanner.plan", "state")
        u_now = check_vector(current_input, 2, "MpcPlanner.plan", "current_input")
        reference = np.asarray(reference, dtype=np.float64)
        if reference.shape != (H + 1, 3) or not np.isfinite(reference).all():
            raise PlannerInputError(
                f"MpcPlanner.plan: reference must be finite (H+1, 3) = ({H + 1}, 3) (x_m, y_m, v_mps), "
                f"got shape {reference.shape}"
            )
        points = check_points(points_fix_world, "MpcPlanner.plan: points_fix_world")
        v_lo, v_hi = lim.v_min_mps, lim.v_max_mps
        if speed_bounds_mps is not None:
            lo, hi = float(speed_bounds_mps[0]), float(speed_bounds_mps[1])
            if not (math.isfinite(lo) and math.isfinite(hi) and lo <= hi):
                raise PlannerInputError(f"MpcPlanner.plan: speed_bounds_mps {speed_bounds_mps} is not a range")
            v_lo, v_hi = max(v_lo, lo), min(v_hi, hi)
            if v_lo > v_hi:
                raise PlannerInputError(
                    f"MpcPlanner.plan: speed_bounds_mps {speed_bounds_mps} outside the robot's "
                    f"[{lim.v_min_mps}, {lim.v_max_mps}]"
                )
        timings = {"select": 0.0, "net": 0.0, "rows": 0.0, "build": 0.0, "solve": 0.0, "qp": 0.0,
                   "check": 0.0, "total": 0.0}
        lin.state0[:] = state
        lin.u_lo[:] = (v_lo, -lim.omega_max_radps)
        lin.u_hi[:] = (v_hi, lim.omega_max_radps)
        lin.du_max[:] = (lim.accel_mps2 * cfg.step_s, lim.angular_accel_radps2 * cfg.step_s)
        # The rate limit starts from the input now, brought inside the box so the QP is feasible.
        lin.u_prev[:] = np.clip(u_now, lin.u_lo, lin.u_hi)
        self._set_reference(state, self._reachable_reference(reference, float(lin.u_prev[0])))

        # Nominal trajectory: the previous plan shifted by one tick; where there is none, or it
        # stands still, the reference's (reachable) speeds. Linearized about a standstill, the
        # dynamics lose the heading's effect on position (d x_{h+1} / d theta_h = -dt v sin theta
        # is 0 at v = 0): the QP then sees no use in turning towards the path before it moves
        # and holds still beside an obstacle it could turn away from (issue 10).
        shifted = self._shifted_previous(self._ticks_since_plan + 1)
        if shifted is None or np.abs(shifted[:, 0]).max() < lin.du_max[0]:
            nominal_inputs = self._reference_following_inputs(state)
        else:
            nominal_inputs = np.clip(shifted, lin.u_lo, lin.u_hi)
        nominal_states = unicycle_rollout(state, nominal_inputs, cfg.step_s)

        iterations, capped, status = 0, False, "not run"
        solution: np.ndarray | None = None
        max_slack, n_rows, done = 0.0, 0, 0
        per_solve_limit = cfg.qp_time_budget_s / cfg.alternations if self.wall_clock_caps else None
        self._select_points(nominal_states, points, timings)
        for _ in range(cfg.alternations):
            n_rows = self._collision_rows(nominal_states, timings)
            self._linearize_dynamics(nominal_states, nominal_inputs)
            t0 = time.perf_counter()
            out = self.backend.solve(lin, per_solve_limit)
            timings["qp"] += (time.perf_counter() - t0) * 1e3
            timings["build"] += out.build_ms
            timings["solve"] += out.solve_ms
            self.qp_solves += 1
            self.qp_capped += int(out.capped)
            iterations += out.iterations
            status = out.status
            if not out.ok:
                capped = capped or out.capped
                break
            done += 1
            solution = self._enforce_bounds(out.inputs)
            max_slack = out.max_slack_m
            nominal_inputs = solution
            previous_states = nominal_states
            nominal_states = unicycle_rollout(state, solution, cfg.step_s)
            if done < cfg.alternations and self._converged(previous_states, nominal_states):
                self.alternations_skipped += cfg.alternations - done
                break

        self.plans += 1
        if capped:
            self.capped_solves += 1
        fallback = solution is None
        if fallback:
            self.fallbacks += 1
            commands = self._shifted_previous(self._ticks_since_plan + 1)
            if commands is None:
                commands = self._braking_plan(u_now)
            self._ticks_since_plan += 1
        else:
            commands = solution
            self._prev_commands = commands.copy()
            self._ticks_since_plan = 0
        # The last alternation already rolled the solution out (nominal_states); a fallback has not.
        states = unicycle_rollout(state, commands, cfg.step_s) if fallback else nominal_states
        t0 = time.perf_counter()
        sel = self.last_selection
        if sel is not None and sel.count:
            # Exact distance of each predicted pose to its own constraint points (the rows it saw).
            local = self._selected_in_pose_frames(states[1:])[2]
            d = rectangle_signed_distance(local, self.half_length_m, self.half_width_m)
            min_dist = float(d[sel.valid].min())
        else:
            min_dist = math.inf
        timings["check"] = (time.perf_counter() - t0) * 1e3
        timings["total"] = (time.perf_counter() - t_start) * 1e3
        return PlanResult(
            commands=commands.copy(),
            states=states,
            solve_status=status,
            iterations=iterations,
            capped=capped,
            fallback=fallback,
            timings_ms=timings,
            min_predicted_distance_m=min_dist,
            max_slack_m=max_slack,
            constraint_points=n_rows,
            alternations_done=done,
        )
