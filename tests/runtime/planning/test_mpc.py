"""The OSQP MPC: closed loop around obstacles, through a narrow gap, bounds, capped solves, and
the causes of stalls beside obstacles (rows it could not meet, unreachable targets, the nominal;
docs/decisions/planning-mpc-standstill.md)."""
from __future__ import annotations


import numpy as np
import pytest

from calibration.robot_description import load_robot_description
from runtime.planning.distance_model import ExactRectangleDual, footprint_distance_to_points
from runtime.planning.errors import PlannerInputError
from runtime.planning.mpc import MpcPlanner
from runtime.planning.mpc_config import MpcConfig
from runtime.planning.mpc_qp import OsqpMpcBackend, QpOutcome
from runtime.planning.point_selection import PointSelectionConfig, PointSelector
from runtime.planning.reference_path import ReferencePathConfig, ReferencePathPlanner
from runtime.safety.supervisor import SafetySupervisor, SafetySupervisorConfig

ROBOT = load_robot_description()
HL, HW = ROBOT.footprint.length_m / 2, ROBOT.footprint.width_m / 2
TICK_S = 0.05


def _simulate(pts, start, goal, horizon=10, ticks=160, mpc_kw=None):
    """Closed loop: reference path + MPC + a kinematic unicycle integrated in 1 ms steps."""
    # A generous time cap: the tests check behaviour, not timing, on a shared machine.
    kw = {"qp_time_budget_s": 1.0, **(mpc_kw or {})}
    cfg = MpcConfig(horizon_steps=horizon, tick_period_s=TICK_S, **kw)
    planner = MpcPlanner(cfg, ROBOT, ExactRectangleDual.for_robot(ROBOT), wall_clock_caps=False)
    ref_planner = ReferencePathPlanner(ReferencePathConfig(horizon_steps=horizon, step_s=cfg.step_s), ROBOT)
    state = np.array(start, dtype=float)
    u = np.zeros(2)
    log = {"min_dist": np.inf, "results": [], "inputs_before": [], "reached": False}
    for _ in range(ticks):
        up = ref_planner.update(state, goal, pts)
        if up.goal_reached:
            log["reached"] = True
            break
        res = planner.plan(state, u, up.reference, pts)
        log["results"].append(res)
        log["inputs_before"].append(u.copy())
        u = res.commands[0].copy()
        ref_planner.replan_in_slack()  # as the loop runs it, after the command is written
        for _ in range(int(TICK_S / 0.001)):
            state = state + 0.001 * np.array([u[0] * np.cos(state[2]), u[0] * np.sin(state[2]), u[1]])
            d = footprint_distance_to_points(state[None], pts, HL, HW).min()
            log["min_dist"] = min(log["min_dist"], d)
    log["state"] = state
    log["planner"] = planner
    return log


def _gap_walls(gap_m: float) -> np.ndarray:
    ys = np.arange(gap_m / 2, 1.5, 0.02)
    xs = np.arange(1.4, 1.61, 0.02)
    X, Y = np.meshgrid(xs, ys)
    upper = np.stack([X.ravel(), Y.ravel()], axis=1)
    return np.concatenate([upper, upper * [1.0, -1.0]])


def test_drives_around_a_fixed_cluster_keeping_d_min() -> None:
    rng = np.random.default_rng(0)
    cluster = np.array([1.5, 0.0]) + rng.normal(scale=0.08, size=(60, 2))
    log = _simulate(cluster, [0.0, 0.0, 0.0], np.array([3.0, 0.0]))
    assert log["reached"], f"stopped at {log['state']}"
    d_min = log["planner"].config.d_min_m
    assert log["min_dist"] >= d_min - 0.01
    assert log["planner"].fallbacks == 0


def test_passes_a_gap_ten_centimetres_wider_than_the_robot() -> None:
    pts = _gap_walls(ROBOT.footprint.width_m + 0.10)
    log = _simulate(pts, [0.0, 0.1, 0.3], np.array([3.0, 0.0]))
    assert log["reached"], f"stopped at {log['state']}"
    assert log["min_dist"] > 0.0  # never touched the walls in the kinematic simulation


def test_respects_input_and_rate_bounds() -> None:
    rng = np.random.default_rng(1)
    cluster = np.array([1.2, 0.3]) + rng.normal(scale=0.1, size=(40, 2))
    log = _simulate(cluster, [0.0, 0.0, 1.5], np.array([2.5, 0.0]), horizon=15, ticks=60)
    lim = ROBOT.limits
    dv, dw = lim.max_linear_accel_mps2 * 0.1, lim.max_angular_accel_radps2 * 0.1
    tol = 1e-6
    v_rev = log["planner"].config.max_reverse_speed_mps
    for res, u_before in zip(log["results"], log["inputs_before"]):
        c = res.commands
        assert np.all(c[:, 0] <= lim.max_linear_speed_mps + tol) and np.all(c[:, 0] >= -v_rev - tol)
        assert np.all(np.abs(c[:, 1]) <= lim.max_angular_speed_radps + tol)
        steps = np.diff(np.vstack([u_before, c]), axis=0)
        assert np.all(np.abs(steps[:, 0]) <= dv + 1e-3) and np.all(np.abs(steps[:, 1]) <= dw + 1e-3)
    # The robot started facing away from the goal (yaw 1.5 rad): it had to turn at the limits.
    assert any(abs(r.commands[0, 1]) > 0.5 for r in log["results"])


def test_speed_bounds_restrict_to_reversing() -> None:
    planner = MpcPlanner(MpcConfig(), ROBOT, ExactRectangleDual.for_robot(ROBOT), wall_clock_caps=False)
    ref = np.zeros((11, 3))
    ref[:, 0] = -0.03 * np.arange(11)
    ref[:, 2] = -0.3
    res = planner.plan(np.zeros(3), np.zeros(2), ref, np.zeros((0, 2)), speed_bounds_mps=(-0.3, 0.0))
    assert np.all(res.commands[:, 0] <= 1e-6) and res.commands[:, 0].min() < -0.1


class _CappingBackend:
    """Delegates to OSQP, but reports a cap whenever `cap` is set (as a solver overrun would)."""

    def __init__(self, inner: OsqpMpcBackend) -> None:
        self.inner = inner
        self.cap = False

    def solve(self, lin, time_limit_s):
        if self.cap:
            return QpOutcome(False, True, "run time limit reached", 7, None, 0.0)
        return self.inner.solve(lin, time_limit_s)


def _straight_reference(x0: float, n: int = 11) -> np.ndarray:
    ref = np.zeros((n, 3))
    ref[:, 0] = x0 + 0.1 * np.arange(n)
    ref[:, 2] = 1.0
    return ref


def test_capped_solve_returns_the_shifted_previous_plan_and_counts() -> None:
    cfg = MpcConfig(tick_period_s=0.1, qp_time_budget_s=1.0)  # one tick = one step: the shift is exact
    backend = _CappingBackend(OsqpMpcBackend(cfg, MpcPlanner(cfg, ROBOT, ExactRectangleDual.for_robot(ROBOT)).limits))
    planner = MpcPlanner(cfg, ROBOT, ExactRectangleDual.for_robot(ROBOT), qp_backend=backend)
    first = planner.plan(np.zeros(3), np.array([0.5, 0.0]), _straight_reference(0.0), np.zeros((0, 2)))
    assert first.solve_status == "solved" and not first.capped and not first.fallback
    backend.cap = True
    second = planner.plan(first.states[1], first.commands[0], _straight_reference(0.1), np.zeros((0, 2)))
    assert second.capped and second.fallback
    np.testing.assert_allclose(second.commands[:-1], first.commands[1:], atol=1e-12)
    np.testing.assert_allclose(second.commands[-1], first.commands[-1])
    third = planner.plan(second.states[1], second.commands[0], _straight_reference(0.2), np.zeros((0, 2)))
    np.testing.assert_allclose(third.commands[:-2], first.commands[2:], atol=1e-12)
    assert planner.capped_solves == 2 and planner.fallbacks == 2 and planner.plans == 3
    backend.cap = False
    fourth = planner.plan(third.states[1], third.commands[0], _straight_reference(0.3), np.zeros((0, 2)))
    assert not fourth.fallback and planner.fallbacks == 2


def test_osqp_iteration_cap_is_detected_without_a_previous_plan() -> None:
    cfg = MpcConfig(max_iterations=10, eps_abs=1e-9, eps_rel=1e-9, qp_time_budget_s=1.0)
    planner = MpcPlanner(cfg, ROBOT, ExactRectangleDual.for_robot(ROBOT))
    res = planner.plan(np.zeros(3), np.array([0.8, 0.0]), _straight_reference(0.0), np.zeros((0, 2)))
    assert res.capped and res.fallback and res.iterations == 10
    assert planner.capped_solves == 1
    # No previous plan: brake at the rate limit.
    assert res.commands[0, 0] == pytest.approx(0.8 - ROBOT.limits.max_linear_accel_mps2 * 0.1)
    assert res.commands[-1, 0] == 0.0


@pytest.mark.parametrize("seed", range(3))
def test_collision_rows_are_the_first_order_expansion_of_the_exact_distance(seed: int) -> None:
    """The row coefficients equal finite differences of the exact distance in (x, y, theta)."""
    rng = np.random.default_rng(seed)
    cfg = MpcConfig(horizon_steps=4, linearize_heading=True)
    planner = MpcPlanner(cfg, ROBOT, ExactRectangleDual.for_robot(ROBOT), wall_clock_caps=False)
    pts = rng.uniform(-1.0, 1.5, size=(30, 2))
    pts = pts[footprint_distance_to_points(np.zeros((1, 3)), pts, HL, HW)[0] > 0.05]
    nominal = np.array([[0.0, 0.0, 0.0], [0.1, 0.02, 0.1], [0.2, 0.05, 0.3], [0.3, 0.1, 0.4], [0.4, 0.1, 0.6]])
    timings = {"select": 0.0, "net": 0.0, "rows": 0.0}
    planner.rows.linearize(planner.lin, nominal, pts, timings)
    lin, sel = planner.lin, planner.last_selection
    eps = 1e-6
    for h in range(4):
        for k in np.flatnonzero(sel.valid[h]):
            p = sel.points_world[h, k][None]
            s = nominal[h + 1]
            grad = []
            for j in range(3):
                dp, dm = s.copy(), s.copy()
                dp[j] += eps
                dm[j] -= eps
                grad.append((footprint_distance_to_points(dp[None], p, HL, HW) - footprint_distance_to_points(dm[None], p, HL, HW))[0, 0] / (2 * eps))
            np.testing.assert_allclose(lin.coll_coef[h, k], grad, atol=1e-5)
            d = footprint_distance_to_points(s[None], p, HL, HW)[0, 0]
            # Row value at the nominal pose = d - d_min.
            assert lin.coll_coef[h, k] @ s - lin.coll_rhs[h, k] == pytest.approx(d - cfg.d_min_m, abs=1e-9)


def test_exact_stand_in_agrees_with_the_models_reference_dual() -> None:
    footprint_dual = pytest.importorskip("models.footprint_dual")
    G, g = ROBOT.footprint.halfspaces()
    pts = np.random.default_rng(5).uniform(-1, 1, size=(500, 2))
    mu_ref, d_ref = footprint_dual.exact_dual(pts, G, g)
    mu, lam, d = ExactRectangleDual.for_robot(ROBOT).dual(pts)
    np.testing.assert_allclose(d, d_ref, atol=1e-9)
    np.testing.assert_allclose(lam, -(mu @ G))
    outside = d_ref > 1e-6
    np.testing.assert_allclose(mu[outside], mu_ref[outside], atol=1e-6)


def test_bad_inputs_raise_named_errors() -> None:
    planner = MpcPlanner(MpcConfig(), ROBOT, ExactRectangleDual.for_robot(ROBOT), wall_clock_caps=False)
    ok_ref = _straight_reference(0.0)
    with pytest.raises(PlannerInputError, match="reference"):
        planner.plan(np.zeros(3), np.zeros(2), ok_ref[:5], np.zeros((0, 2)))
    with pytest.raises(PlannerInputError, match="state"):
        planner.plan(np.array([0.0, np.nan, 0.0]), np.zeros(2), ok_ref, np.zeros((0, 2)))
    with pytest.raises(PlannerInputError, match="points_fix_world"):
        planner.plan(np.zeros(3), np.zeros(2), ok_ref, np.array([[1.0, np.inf]]))
    with pytest.raises(PlannerInputError, match="speed_bounds"):
        planner.plan(np.zeros(3), np.zeros(2), ok_ref, np.zeros((0, 2)), speed_bounds_mps=(0.5, -0.5))
    with pytest.raises(PlannerInputError, match="dual"):
        MpcPlanner(MpcConfig(), ROBOT, object())


# -- The MPC must not stand still beside obstacles while the reference path is valid ----------


def _segment_points(a, b, step_m: float = 0.02) -> np.ndarray:
    a, b = np.asarray(a, dtype=float), np.asarray(b, dtype=float)
    n = max(int(np.ceil(np.hypot(*(b - a)) / step_m)), 1)
    return a + (b - a) * np.linspace(0.0, 1.0, n + 1)[:, None]


def _simulate_supervised(pts, start, goal, ticks):
    """Closed loop as the controller runs it: reference path, MPC, safety supervisor (which may
    stop the MPC's command), kinematic unicycle in 1 ms steps. Iteration caps only (lockstep)."""
    planner = MpcPlanner(MpcConfig(), ROBOT, ExactRectangleDual.for_robot(ROBOT), wall_clock_caps=False)
    reference = ReferencePathPlanner(ReferencePathConfig(), ROBOT)
    supervisor = SafetySupervisor(SafetySupervisorConfig(), ROBOT)
    state, u = np.array(start, dtype=float), np.zeros(2)
    log = {"reached": False, "stops": 0, "min_dist": np.inf, "ticks": 0}
    for log["ticks"] in range(1, ticks + 1):
        up = reference.update(state, goal, pts)
        if up.goal_reached:
            log["reached"] = True
            break
        plan = planner.plan(state, u, up.reference, pts)
        decision = supervisor.check(state, plan.commands[0], pts)
        log["stops"] += int(decision.stopped)
        u = decision.command_out.copy()
        reference.replan_in_slack()  # as the loop runs it, after the command is written
        for _ in range(int(TICK_S / 0.001)):
            state = state + 0.001 * np.array([u[0] * np.cos(state[2]), u[0] * np.sin(state[2]), u[1]])
            log["min_dist"] = min(log["min_dist"], footprint_distance_to_points(state[None], pts, HL, HW).min())
    log["state"] = state
    return log


def _box_corner_beside_the_robot() -> tuple[np.ndarray, np.ndarray]:
    """corridor_boxes in small: a corridor 1.02 m wide, a box against its south wall, the robot
    heading 45 degrees across the box's top face with the box's corner 3 mm from its right side,
    ahead of its centre (turning right towards the goal first swings that side into the corner)."""
    box = np.concatenate([
        _segment_points((0.13, -0.6), (0.13, -0.03)),
        _segment_points((0.13, -0.03), (0.53, -0.03)),
        _segment_points((0.53, -0.03), (0.53, -0.6)),
    ])
    walls = np.concatenate([_segment_points((-1.0, 0.42), (2.5, 0.42)), _segment_points((-1.0, -0.6), (2.5, -0.6))])
    yaw = np.pi / 4
    corner_in_robot = np.array([0.07, -HW - 0.003])
    rot = np.array([[np.cos(yaw), -np.sin(yaw)], [np.sin(yaw), np.cos(yaw)]])
    xy = np.array([0.13, -0.03]) - rot @ corner_in_robot
    return np.concatenate([box, walls]), np.array([xy[0], xy[1], yaw])


def test_beside_a_box_corner_inside_d_min_the_plan_slides_past_instead_of_stalling() -> None:
    """Before: rows demanding d_min of a point 3 mm away cannot be met by any plan; the QP paid
    the slack and bought more penetration for tracking (a right turn into the corner), the
    supervisor stopped every such command: 109 stops in 120 ticks, the robot never passed."""
    pts, start = _box_corner_beside_the_robot()
    assert footprint_distance_to_points(start[None], pts, HL, HW).min() == pytest.approx(0.003, abs=1e-6)
    log = _simulate_supervised(pts, start, np.array([2.0, 0.2]), ticks=120)
    assert log["reached"], f"stalled at {log['state']} after {log['stops']} supervisor stops"
    assert log["stops"] <= 10
    assert log["min_dist"] > 0.0  # never touched


def test_rows_of_points_already_inside_d_min_demand_the_current_distance() -> None:
    """A row's required clearance is min(d_min, distance now) and its slack costs the holding
    weight: standing still meets it, so the plan never goes deeper than the robot is now."""
    pts, start = _box_corner_beside_the_robot()
    cfg = MpcConfig()
    planner = MpcPlanner(cfg, ROBOT, ExactRectangleDual.for_robot(ROBOT), wall_clock_caps=False)
    planner.lin.state0[:] = start
    nominal = np.repeat(start[None], cfg.horizon_steps + 1, axis=0)  # standing still
    planner.rows.linearize(planner.lin, nominal, pts, {"select": 0.0, "net": 0.0, "rows": 0.0})
    lin, sel = planner.lin, planner.last_selection
    d_now = footprint_distance_to_points(start[None], sel.points_world.reshape(-1, 2), HL, HW).reshape(sel.valid.shape)
    row_at_standstill = np.einsum("hkj,j->hk", lin.coll_coef, start) - lin.coll_rhs
    inside = sel.valid & (d_now < cfg.d_min_m)
    assert inside.any()
    np.testing.assert_allclose(row_at_standstill[inside], 0.0, atol=1e-9)  # met exactly, no slack
    np.testing.assert_allclose(row_at_standstill[sel.valid & ~inside], (d_now - cfg.d_min_m)[sel.valid & ~inside], atol=1e-9)
    assert (lin.coll_slack_weight[inside] == cfg.weights.slack_linear_holding).all()
    assert (lin.coll_slack_weight[~inside] == cfg.weights.slack_linear).all()


def test_turned_towards_a_wall_with_the_path_leaving_sideways_it_turns_and_drives() -> None:
    """corridor_l's start (and the robot after a corner taken wide): facing a wall 0.2 m ahead,
    the path along the corridor. Before: the nominal trajectory ran straight ahead into the wall,
    the rows linearized there let the QP plan through it (slack 0.13 m), the supervisor stopped
    it: the robot never left. Now the nominal follows the reference."""
    walls = np.concatenate([_segment_points((-1.0, 0.4), (3.0, 0.4)), _segment_points((-1.0, -0.4), (3.0, -0.4))])
    log = _simulate_supervised(walls, [0.0, 0.0, np.radians(60.0)], np.array([2.0, 0.0]), ticks=80)
    assert log["reached"], f"stalled at {log['state']} after {log['stops']} supervisor stops"
    assert log["stops"] == 0 and log["min_dist"] > 0.03


def test_from_standstill_the_tracked_waypoints_are_reachable_within_the_acceleration_limit() -> None:
    """The reference runs at 1 m/s whatever the robot does; the MPC re-times it along the same
    path so that the targets' speed rises from the speed now at the acceleration limit."""
    cfg = MpcConfig()
    planner = MpcPlanner(cfg, ROBOT, ExactRectangleDual.for_robot(ROBOT), wall_clock_caps=False)
    planner.plan(np.zeros(3), np.zeros(2), _straight_reference(0.0), np.zeros((0, 2)))
    a_dt = ROBOT.limits.max_linear_accel_mps2 * cfg.step_s
    expected_speed = np.minimum(a_dt * np.arange(1, cfg.horizon_steps + 1), 1.0)
    np.testing.assert_allclose(planner.lin.ref_v, expected_speed, atol=1e-12)
    np.testing.assert_allclose(planner.lin.ref_xy[:, 0], np.cumsum(expected_speed) * cfg.step_s, atol=1e-12)
    np.testing.assert_allclose(planner.lin.ref_xy[:, 1], 0.0, atol=1e-12)
    # At speed, the reference is kept as it is.
    planner.reset()
    planner.plan(np.zeros(3), np.array([1.0, 0.0]), _straight_reference(0.0), np.zeros((0, 2)))
    np.testing.assert_allclose(planner.lin.ref_xy[:, 0], 0.1 * np.arange(1, cfg.horizon_steps + 1), atol=1e-12)


def test_each_pose_sees_the_nearest_point_of_every_cell() -> None:
    """Thinning keeps one point per 5 cm cell per pose, the one nearest to that pose: a box
    corner the later poses pass closest to is not lost to a neighbour in its cell (before: the
    first point of each cell for all poses, up to the cell's diagonal farther away)."""
    cell_first = np.array([0.32, -0.16])  # the same 5 cm cell, first in input order
    corner = np.array([0.34, -0.196])
    poses = np.array([[0.0, 0.0, 0.0], [0.3, -0.33, 0.0]])  # the second passes just below the corner
    selector = PointSelector(PointSelectionConfig(points_per_pose=1, voxel_size_m=0.05), HL, HW)
    sel = selector.select(poses, np.stack([cell_first, corner]))
    exact = footprint_distance_to_points(poses, np.stack([cell_first, corner]), HL, HW)
    for h in range(2):
        np.testing.assert_allclose(sel.points_world[h, 0], [cell_first, corner][int(exact[h].argmin())])
        assert sel.distance_m[h, 0] == pytest.approx(exact[h].min())
