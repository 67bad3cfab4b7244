"""The MPC of paper eq. (12)-(13), solved with OSQP, collision rows from a distance model:
the planner (MpcPlanner), its result (PlanResult) and the unicycle rollout.

State s = (x, y, theta), input u = (v, omega), unicycle s_{h+1} = s_h + f(s_h, u_h) dt (12b),
linearized along a nominal trajectory (the previous plan, shifted). Input and rate bounds (12c).
Collision (12d): rows linear in the pose from the distance model's dual at the nominal poses,
with an L1-penalized slack (runtime.planning.mpc_collision_rows). Cost (13): track the reference
waypoints (position, heading, speed), re-timed so that their speed rises from the speed now
within the acceleration limit, and penalize input changes (runtime.planning.mpc_targets).

Where the pieces live: the settings in runtime.planning.mpc_config; the QP's fixed sparsity
pattern in runtime.planning.mpc_qp_layout; the QP's numbers and the OSQP backend in
runtime.planning.mpc_qp. Net and QP alternate up to `alternations` times (NeuPAN's PAN
iterations; the next is skipped when the solution stayed within a millimetre of the poses the QP
was linearized about, see MpcPlanner._converged). Each solve is capped in iterations, and in real
time also by the wall clock (`qp_time_budget_s`); on a cap the planner falls back to the shifted
previous plan and counts it. In lockstep (`wall_clock_caps=False`) only the iteration cap
applies, so the same inputs give the same plan under any machine load (docs/architecture.md).
Why the planner never stalls beside an obstacle with a valid reference (rows it can meet,
targets it can reach, a nominal that moves): docs/decisions/planning-mpc-standstill.md.
"""
from __future__ import annotations

import math
import sys
import time
from dataclasses import dataclass

import numpy as np

from runtime.planning.distance_model import DistanceModel
from runtime.planning.errors import PlannerInputError, check_points, check_vector
from runtime.planning.mpc_collision_rows import CollisionRows
from runtime.planning.mpc_config import MpcConfig, MpcLimits
from runtime.planning.mpc_qp import MpcLinearization, OsqpMpcBackend, QpBackend
from runtime.planning.mpc_targets import (
    braking_plan,
    reachable_reference,
    reference_following_inputs,
    set_reference,
    shifted_plan,
)


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


@dataclass
class _Alternations:
    """What the net/QP alternations of one plan gave."""

    iterations: int = 0
    capped: bool = False
    status: str = "not run"
    solution: np.ndarray | None = None  # (H, 2) the last solution, bounds enforced
    states: np.ndarray | None = None  # (H+1, 3) its rollout
    max_slack: float = 0.0
    rows: int = 0
    done: int = 0


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
        # The distance net runs on one thread (docs/decisions/planning-distance-net-threads.md).
        if "torch" in sys.modules:
            sys.modules["torch"].set_num_threads(1)
        self.config = config
        self.robot = robot
        self.distance_model = distance_model
        self.half_length_m = robot.footprint.length_m / 2.0
        self.half_width_m = robot.footprint.width_m / 2.0
        self.limits = MpcLimits.from_robot(robot, config.max_reverse_speed_mps)
        self.rows = CollisionRows(config, distance_model, self.half_length_m, self.half_width_m)
        self.wall_clock_caps = wall_clock_caps
        self.backend: QpBackend = (
            qp_backend if qp_backend is not None else OsqpMpcBackend(config, self.limits, wall_clock_caps)
        )
        H, K = config.horizon_steps, config.points.points_per_pose
        self.lin = MpcLinearization(H, K)
        self._prev_commands: np.ndarray | None = None
        self._ticks_since_plan = 0
        # Counters (never reset by plan()).
        self.plans = 0
        self.capped_solves = 0  # plans in which a solve hit its cap
        self.fallbacks = 0
        self.qp_solves = 0  # every QP solve (alternations count one each)
        self.qp_capped = 0  # solves that hit the iteration (or, in real time, the time) cap
        self.alternations_skipped = 0  # alternations not needed (the linearization had converged)

    @property
    def last_selection(self):
        """The constraint points of the last plan (runtime.planning.point_selection.SelectedPoints)."""
        return self.rows.last_selection

    @last_selection.setter
    def last_selection(self, value) -> None:
        self.rows.last_selection = value

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

    def _speed_bounds(self, speed_bounds_mps: tuple[float, float] | None) -> tuple[float, float]:
        """[v_min, v_max] of this step: the robot's, narrowed by speed_bounds_mps."""
        lim = self.limits
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
        return v_lo, v_hi

    def _checked_reference(self, reference: np.ndarray) -> np.ndarray:
        H = self.config.horizon_steps
        reference = np.asarray(reference, dtype=np.float64)
        if reference.shape != (H + 1, 3) or not np.isfinite(reference).all():
            raise PlannerInputError(
                f"MpcPlanner.plan: reference must be finite (H+1, 3) = ({H + 1}, 3) (x_m, y_m, v_mps), "
                f"got shape {reference.shape}"
            )
        return reference

    def _set_bounds_and_targets(self, state: np.ndarray, u_now: np.ndarray, reference: np.ndarray,
                                speed_range: tuple[float, float]) -> None:
        """The step's input and rate bounds, the start of the rate limit, the tracking targets."""
        cfg, lim, lin = self.config, self.limits, self.lin
        v_lo, v_hi = speed_range
        lin.state0[:] = state
        lin.u_lo[:] = (v_lo, -lim.omega_max_radps)
        lin.u_hi[:] = (v_hi, lim.omega_max_radps)
        lin.du_max[:] = (lim.accel_mps2 * cfg.step_s, lim.angular_accel_radps2 * cfg.step_s)
        # The rate limit starts from the input now, brought inside the box so the QP is feasible.
        lin.u_prev[:] = np.clip(u_now, lin.u_lo, lin.u_hi)
        set_reference(lin, state, reachable_reference(cfg, lim, reference, float(lin.u_prev[0])), cfg.horizon_steps)

    def _nominal_inputs(self, state: np.ndarray) -> np.ndarray:
        """The inputs the first linearization is about: the previous plan shifted by one tick;
        where there is none, or it stands still, inputs that follow the reference. Linearized
        about a standstill, the dynamics lose the heading's effect on position (d x_{h+1} /
        d theta_h = -dt v sin theta is 0 at v = 0): the QP would see no use in turning towards
        the path before it moves (docs/decisions/planning-mpc-standstill.md)."""
        lin = self.lin
        shifted = shifted_plan(self.config, self._prev_commands, self._ticks_since_plan + 1)
        if shifted is None or np.abs(shifted[:, 0]).max() < lin.du_max[0]:
            return reference_following_inputs(lin, state, self.config.horizon_steps, self.config.step_s)
        return np.clip(shifted, lin.u_lo, lin.u_hi)

    def _alternate(self, state: np.ndarray, nominal_states: np.ndarray, nominal_inputs: np.ndarray,
                   timings: dict) -> _Alternations:
        """Net and QP, up to `alternations` times, each solve under its caps (module docstring)."""
        cfg, lin = self.config, self.lin
        run = _Alternations(states=nominal_states)
        per_solve_limit = cfg.qp_time_budget_s / cfg.alternations if self.wall_clock_caps else None
        for _ in range(cfg.alternations):
            run.rows = self.rows.fill(lin, nominal_states, timings)
            lin.set_dynamics(nominal_states, nominal_inputs, cfg.step_s)
            t0 = time.perf_counter()
            out = self.backend.solve(lin, per_solve_limit)
            timings["qp"] += (time.perf_counter() - t0) * 1e3
            timings["build"] += out.build_ms
            timings["solve"] += out.solve_ms
            self.qp_solves += 1
            self.qp_capped += int(out.capped)
            run.iterations += out.iterations
            run.status = out.status
            if not out.ok:
                run.capped = run.capped or out.capped
                break
            run.done += 1
            run.solution = self._enforce_bounds(out.inputs)
            run.max_slack = out.max_slack_m
            nominal_inputs = run.solution
            previous_states = nominal_states
            nominal_states = unicycle_rollout(state, run.solution, cfg.step_s)
            run.states = nominal_states
            if run.done < cfg.alternations and self._converged(previous_states, nominal_states):
                self.alternations_skipped += cfg.alternations - run.done
                break
        return run

    def _commands(self, state: np.ndarray, u_now: np.ndarray, run: _Alternations) -> tuple[np.ndarray, np.ndarray]:
        """The plan's commands and predicted states: the solution, or on a fallback the shifted
        previous plan (a braking plan without one)."""
        self.plans += 1
        if run.capped:
            self.capped_solves += 1
        if run.solution is None:
            self.fallbacks += 1
            commands = shifted_plan(self.config, self._prev_commands, self._ticks_since_plan + 1)
            if commands is None:
                commands = braking_plan(self.config, self.limits, u_now)
            self._ticks_since_plan += 1
            return commands, unicycle_rollout(state, commands, self.config.step_s)
        self._prev_commands = run.solution.copy()
        self._ticks_since_plan = 0
        # The last alternation already rolled the solution out.
        return run.solution, run.states

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
        state = check_vector(state, 3, "MpcPlanner.plan", "state")
        u_now = check_vector(current_input, 2, "MpcPlanner.plan", "current_input")
        reference = self._checked_reference(reference)
        points = check_points(points_fix_world, "MpcPlanner.plan: points_fix_world")
        speed_range = self._speed_bounds(speed_bounds_mps)
        timings = {"select": 0.0, "net": 0.0, "rows": 0.0, "build": 0.0, "solve": 0.0, "qp": 0.0,
                   "check": 0.0, "total": 0.0}
        self._set_bounds_and_targets(state, u_now, reference, speed_range)
        nominal_inputs = self._nominal_inputs(state)
        nominal_states = unicycle_rollout(state, nominal_inputs, self.config.step_s)
        self.rows.select(nominal_states, points, timings)
        run = self._alternate(state, nominal_states, nominal_inputs, timings)
        commands, states = self._commands(state, u_now, run)
        t0 = time.perf_counter()
        min_dist = self.rows.min_predicted_distance(states)
        timings["check"] = (time.perf_counter() - t0) * 1e3
        timings["total"] = (time.perf_counter() - t_start) * 1e3
        return PlanResult(
            commands=commands.copy(),
            states=states,
            solve_status=run.status,
            iterations=run.iterations,
            capped=run.capped,
            fallback=run.solution is None,
            timings_ms=timings,
            min_predicted_distance_m=min_dist,
            max_slack_m=run.max_slack,
            constraint_points=run.rows,
            alternations_done=run.done,
        )
