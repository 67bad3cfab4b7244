"""Reference path: A*-equivalent search on the local grid, blocked detection, resampling."""
from __future__ import annotations

import numpy as np
import pytest

from calibration.robot_description import load_robot_description
from runtime.planning.errors import PlannerInputError
from runtime.planning.reference_path import ReferencePathConfig, ReferencePathPlanner

ROBOT = load_robot_description()


def _segment(a, b, step=0.02) -> np.ndarray:
    a, b = np.asarray(a, float), np.asarray(b, float)
    n = max(2, int(np.ceil(np.linalg.norm(b - a) / step)) + 1)
    return a + np.linspace(0, 1, n)[:, None] * (b - a)


def _path_clearance(path: np.ndarray, pts: np.ndarray) -> float:
    return float(np.hypot(path[:, None, 0] - pts[None, :, 0], path[:, None, 1] - pts[None, :, 1]).min())


def _planner(**kw) -> ReferencePathPlanner:
    return ReferencePathPlanner(ReferencePathConfig(**kw), ROBOT)


def _plan(rp: ReferencePathPlanner, pose, goal, pts):
    """The first tick towards a goal as the loop runs it: by default (first_search_in_tick) the
    tick searches and follows (or reports blocked); otherwise it waits, the slack after it
    searches, and the next tick follows."""
    if rp.config.first_search_in_tick:
        in_tick = rp.replans_in_tick
        up = rp.update(np.asarray(pose, float), np.asarray(goal, float), pts)
        assert not up.waiting and up.replanned and rp.replans_in_tick == in_tick + 1
        assert rp.replan_pending is None
        return up
    up = rp.update(np.asarray(pose, float), np.asarray(goal, float), pts)
    assert up.waiting and not up.blocked and rp.replan_pending == "no path"
    assert np.all(up.reference[:, 2] == 0.0)  # hold still meanwhile
    assert rp.replan_in_slack()
    return rp.update(np.asarray(pose, float), np.asarray(goal, float), pts)


def test_open_space_path_is_nearly_straight_and_reaches_the_goal() -> None:
    rp = _planner()
    up = _plan(rp, [0.0, 0.0, 0.0], [2.0, 1.0], np.zeros((0, 2)))
    assert not up.blocked and not up.waiting and rp.replans == 1
    np.testing.assert_allclose(up.path_world[-1], [2.0, 1.0])
    length = np.hypot(*np.diff(up.path_world, axis=0).T).sum()
    assert length < np.hypot(2.0, 1.0) * 1.1


def test_shortcut_makes_the_open_space_path_the_straight_line() -> None:
    """Any-angle shortcutting: in open space the 8-connected staircase (45 degree kinks, up to
    8% longer) becomes the straight segment, kept dense for the blocked-ahead check."""
    straight = _plan(_planner(), [0.0, 0.0, 0.0], [3.0, 1.1], np.zeros((0, 2))).path_world
    stairs = _plan(_planner(shortcut=False), [0.0, 0.0, 0.0], [3.0, 1.1], np.zeros((0, 2))).path_world
    d = np.abs(straight[:, 0] * 1.1 - straight[:, 1] * 3.0) / np.hypot(3.0, 1.1)  # off the line
    assert d.max() < 0.03
    assert np.hypot(*np.diff(straight, axis=0).T).max() <= 1.5 * 0.05  # dense (and smoothed)
    length = lambda p: np.hypot(*np.diff(p, axis=0).T).sum()  # noqa: E731
    assert length(straight) < np.hypot(3.0, 1.1) * 1.005 < length(stairs)


def test_shortcut_keeps_clear_of_lethal_cells_and_out_of_the_soft_zone() -> None:
    """Round a wall's end the shortcut cuts no corner into the inflation, and where the straight
    line would run along the soft zone of a wall it costs more than the search's path, which stays."""
    wall = _segment([1.0, -2.0], [1.0, 0.5])
    rp = _planner()
    up = _plan(rp, [0.0, 0.0, 0.0], [2.0, 0.0], wall)
    assert _path_clearance(up.path_world, wall) >= rp.inflation_radius_m - 1e-9
    raw = _plan(_planner(shortcut=False), [0.0, 0.0, 0.0], [2.0, 0.0], wall).path_world
    length = lambda p: np.hypot(*np.diff(p, axis=0).T).sum()  # noqa: E731
    assert length(up.path_world) < length(raw)
    # Along a wall 0.25 m off the straight line (inside the soft zone) the search's path bows
    # away from it; the shortcut may straighten it only where that costs no more.
    side = _segment([0.5, 0.25], [2.5, 0.25])
    a = _plan(_planner(), [0.0, 0.0, 0.0], [3.0, 0.0], side).path_world
    b = _plan(_planner(shortcut=False), [0.0, 0.0, 0.0], [3.0, 0.0], side).path_world
    grid_cost = lambda p, r: sum(  # noqa: E731
        np.hypot(*(q1 - q0)) * r.last_grid.cost[tuple(r.last_grid.cell_of((q0 + q1) / 2))]
        for q0, q1 in zip(p[:-1], p[1:]))
    rp_a, rp_b = _planner(), _planner(shortcut=False)
    _plan(rp_a, [0.0, 0.0, 0.0], [3.0, 0.0], side)
    _plan(rp_b, [0.0, 0.0, 0.0], [3.0, 0.0], side)
    assert grid_cost(a, rp_a) <= grid_cost(b, rp_b) * 1.02
    assert _path_clearance(a, side) > 0.25


def test_path_goes_around_a_wall_through_its_opening_with_clearance() -> None:
    # Wall at x = 1 from y = -2 to 2 with a 0.6 m opening centred at y = 1.2.
    pts = np.concatenate([_segment([1.0, -2.0], [1.0, 0.9]), _segment([1.0, 1.5], [1.0, 2.0])])
    rp = _planner()
    up = _plan(rp, [0.0, 0.0, 0.0], [2.0, 0.0], pts)
    assert not up.blocked
    crossing = up.path_world[np.argmin(np.abs(up.path_world[:, 0] - 1.0))]
    assert 0.9 < crossing[1] < 1.5
    assert _path_clearance(up.path_world, pts) >= rp.inflation_radius_m - 1e-9


def test_gap_ten_centimetres_wider_than_the_robot_is_passable() -> None:
    gap = ROBOT.footprint.width_m + 0.10
    pts = np.concatenate([_segment([1.0, gap / 2], [1.0, 2.0]), _segment([1.0, -gap / 2], [1.0, -2.0])])
    # Make the wall thick (0.2 m) as a real obstacle.
    pts = np.concatenate([pts + [dx, 0.0] for dx in np.arange(0.0, 0.21, 0.02)])
    up = _plan(_planner(), [0.0, 0.0, 0.0], [2.5, 0.0], pts)
    assert not up.blocked
    at_gap = up.path_world[(up.path_world[:, 0] > 1.0) & (up.path_world[:, 0] < 1.2)]
    assert at_gap.size and np.abs(at_gap[:, 1]).max() < 0.03
    # A gap narrower than the robot is not.
    narrow = ROBOT.footprint.width_m - 0.02
    pts2 = np.concatenate([_segment([1.0, narrow / 2], [1.0, 4.0]), _segment([1.0, -narrow / 2], [1.0, -4.0])])
    up2 = _plan(_planner(), [0.0, 0.0, 0.0], [2.5, 0.0], pts2)
    assert up2.blocked and up2.path_world is None


def test_goal_inside_a_closed_ring_is_reported_blocked() -> None:
    ang = np.linspace(0, 2 * np.pi, 400)
    ring = np.stack([2.0 + 0.6 * np.cos(ang), 0.6 * np.sin(ang)], axis=1)
    up = _plan(_planner(), np.zeros(3), [2.0, 0.0], ring)
    assert up.blocked and up.reason == "no path to the goal"
    assert np.all(up.reference[:, 2] == 0.0) and np.allclose(up.reference[:, :2], 0.0)
    up2 = _plan(_planner(), np.zeros(3), [2.0, 0.6], ring)
    assert up2.blocked and "inflated" in up2.reason


def test_goal_outside_the_window_heads_towards_it() -> None:
    rp = _planner(window_m=4.0)
    up = _plan(rp, np.zeros(3), [10.0, 0.0], np.zeros((0, 2)))
    assert not up.blocked
    assert up.path_world[-1, 0] > 1.8 and abs(up.path_world[-1, 1]) < 0.2
    assert np.all(up.reference[:, 2] == pytest.approx(1.0))  # no slow-down at a window border


def test_replans_when_an_obstacle_appears_on_the_path() -> None:
    rp = _planner(replan_every_ticks=1000)
    pose = np.zeros(3)
    goal = np.array([3.0, 0.0])
    first = _plan(rp, pose, goal, np.zeros((0, 2)))
    kept = rp.update(pose, goal, np.zeros((0, 2)))
    assert not kept.replanned and kept.reason == "kept"
    assert rp.replans == 1 and rp.replan_pending is None
    box = _segment([1.5, -0.3], [1.5, 0.3])
    # Not urgent: this tick keeps the old path and asks for a replan in the slack after it.
    asked = rp.update(pose, goal, box)
    assert not asked.replanned and rp.replan_pending == "path blocked"
    np.testing.assert_array_equal(asked.path_world, first.path_world)
    assert rp.replan_in_slack() and rp.replan_pending is None and not rp.replan_in_slack()
    again = rp.update(pose, goal, box)
    assert not again.blocked and rp.replans_in_slack == 1 and rp.replans_in_tick == 1
    assert _path_clearance(again.path_world, box) >= rp.inflation_radius_m - 1e-9


def test_without_slack_replans_every_replan_runs_in_the_tick() -> None:
    rp = _planner(replan_every_ticks=1000, replan_in_slack=False)
    pose, goal = np.zeros(3), np.array([3.0, 0.0])
    rp.update(pose, goal, np.zeros((0, 2)))
    box = _segment([1.5, -0.3], [1.5, 0.3])
    again = rp.update(pose, goal, box)
    assert again.replanned and again.reason == "path blocked" and rp.replan_pending is None
    assert _path_clearance(again.path_world, box) >= rp.inflation_radius_m - 1e-9


def test_periodic_replans_wait_for_the_slack_and_a_blocked_search_is_retried_there() -> None:
    rp = _planner(replan_every_ticks=3, first_search_in_tick=False)
    pose, goal = np.zeros(3), np.array([2.0, 0.0])
    _plan(rp, pose, goal, np.zeros((0, 2)))
    for _ in range(2):  # the third tick after the search is due
        up = rp.update(pose, goal, np.zeros((0, 2)))
    assert rp.replan_pending == "periodic" and not up.replanned and not up.blocked
    # The goal gets walled in; the slack search finds no path ...
    ang = np.linspace(0, 2 * np.pi, 400)
    ring = np.stack([2.0 + 0.6 * np.cos(ang), 0.6 * np.sin(ang)], axis=1)
    rp.update(pose, goal, ring)
    searches = rp.replans
    assert rp.replan_in_slack() and rp.replans == searches + 1
    # ... so the next tick reports blocked without searching, and asks the slack again.
    held = rp.update(pose, goal, ring)
    assert held.blocked and held.reason == "no path to the goal" and rp.replans == searches + 1
    assert rp.replan_pending is not None
    # A reset (a stop, a recovery) forgets all of it: the next tick waits for a fresh search.
    rp.reset()
    assert rp.replan_pending is None
    again = _plan(rp, pose, goal, ring)
    assert again.blocked and rp.replans == searches + 2 and rp.replans_in_tick == 0


def test_reference_is_resampled_at_the_target_speed_and_stops_at_the_goal() -> None:
    rp = _planner(target_speed_mps=0.8, decel_mps2=1.0, horizon_steps=20)
    up = _plan(rp, np.zeros(3), [1.0, 0.0], np.zeros((0, 2)))
    ref = up.reference
    assert ref.shape == (21, 3)
    assert np.all(ref[:, 2] <= 0.8 + 1e-12) and ref[0, 2] == pytest.approx(0.8)
    spacing = np.hypot(*np.diff(ref[:, :2], axis=0).T)
    assert np.all(spacing <= ref[:-1, 2] * 0.1 + 1e-9)  # chords of arcs of v * dt
    assert spacing[0] == pytest.approx(0.08, abs=1e-3)
    np.testing.assert_allclose(ref[-1], [1.0, 0.0, 0.0], atol=1e-9)


def test_bad_input_raises_named_errors() -> None:
    rp = _planner()
    with pytest.raises(PlannerInputError, match="goal"):
        rp.update(np.zeros(3), np.array([np.nan, 0.0]), np.zeros((0, 2)))
    with pytest.raises(PlannerInputError, match="points"):
        rp.update(np.zeros(3), np.array([1.0, 0.0]), np.zeros((3,)))


def test_a_new_goal_is_searched_in_its_first_tick() -> None:
    """first_search_in_tick (default): no period standing (or braking) for a path to a new goal."""
    rp = _planner()
    pose = np.zeros(3)
    _plan(rp, pose, [2.0, 0.0], np.zeros((0, 2)))
    up = rp.update(pose, np.array([0.0, 2.0]), np.zeros((0, 2)))
    assert not up.waiting and up.replanned and rp.replans_in_tick == 2 and rp.replans_in_slack == 0
    assert np.allclose(up.path_world[-1], [0.0, 2.0]) and up.reference[-1, 2] > 0.0
    rp.reset()  # after a reset (the robot stands: a recovery) the search waits for the slack
    up = rp.update(pose, np.array([0.0, 2.0]), np.zeros((0, 2)))
    assert up.waiting and rp.replan_pending == "no path"


def test_a_robot_standing_still_waits_one_period_for_its_first_path() -> None:
    """first_search_in_tick saves a moving robot a period of braking; one that stands (the start,
    a goal reached) gives up nothing by waiting, so its search runs in the slack, not its tick."""
    rp = _planner()
    pose, goal, pts = np.zeros(3), np.array([2.0, 0.0]), np.zeros((0, 2))
    up = rp.update(pose, goal, pts, moving=False)
    assert up.waiting and rp.replan_pending == "no path" and rp.replans_in_tick == 0
    assert np.all(up.reference[:, 2] == 0.0)
    assert rp.replan_in_slack() and rp.replans_in_slack == 1
    up = rp.update(pose, goal, pts, moving=False)
    assert not up.waiting and np.allclose(up.path_world[-1], goal) and up.reference[-1, 2] > 0.0
    up = rp.update(pose, np.array([0.0, 2.0]), pts, moving=False)  # a new goal at a standstill: the same
    assert up.waiting and rp.replan_pending == "new goal" and rp.replans_in_tick == 0


def test_a_new_goal_holds_for_one_tick_then_follows_the_path_to_it() -> None:
    rp = _planner(first_search_in_tick=False)
    pose = np.zeros(3)
    _plan(rp, pose, [2.0, 0.0], np.zeros((0, 2)))
    up = rp.update(pose, np.array([0.0, 2.0]), np.zeros((0, 2)))
    assert up.waiting and rp.replan_pending == "new goal" and np.all(up.reference[:, 2] == 0.0)
    rp.replan_in_slack()
    up = rp.update(pose, np.array([0.0, 2.0]), np.zeros((0, 2)))
    assert not up.waiting and np.allclose(up.path_world[-1], [0.0, 2.0])


def test_points_just_outside_the_window_do_not_block_its_border() -> None:
    """A wall 0.3 m beyond the window's edge is 0.3 m from the border cells: not lethal (points
    out there count in their own cells, not clipped onto the border ring)."""
    rp = _planner(window_m=8.0)
    wall = _segment([4.30, -5.0], [4.30, 5.0])
    grid = rp.build_grid(np.zeros(2), wall)
    assert not grid.lethal.any()
    near = _segment([4.05, -5.0], [4.05, 5.0])  # 5 cm from the border cells' centres: lethal there
    assert rp.build_grid(np.zeros(2), near).lethal[-1].all()
    up = _plan(rp, np.zeros(3), [10.0, 0.0], wall)
    assert abs(up.path_world[-1, 1]) < 0.1 and up.path_world[-1, 0] > 3.9


def test_a_request_the_slack_did_not_run_is_dropped_by_the_next_tick() -> None:
    """Real time may skip a slack window: the next tick's update stands on its own, a search
    from where the robot was is never run later."""
    rp = _planner(replan_every_ticks=1000, deviation_replan_m=0.3)
    goal = np.array([3.0, 0.0])
    _plan(rp, np.zeros(3), goal, np.zeros((0, 2)))
    rp.update(np.array([0.5, 0.6, 0.0]), goal, np.zeros((0, 2)))
    assert rp.replan_pending == "strayed from the path"
    rp.update(np.array([0.6, 0.0, 0.0]), goal, np.zeros((0, 2)))  # back on the path: nothing to do
    assert rp.replan_pending is None and not rp.replan_in_slack()


def test_a_new_goal_after_a_failed_search_waits_for_its_own_search() -> None:
    ang = np.linspace(0, 2 * np.pi, 400)
    ring = np.stack([2.0 + 0.6 * np.cos(ang), 0.6 * np.sin(ang)], axis=1)
    rp = _planner(first_search_in_tick=False)
    assert _plan(rp, np.zeros(3), [2.0, 0.0], ring).blocked
    up = rp.update(np.zeros(3), np.array([-2.0, 0.0]), ring)
    assert up.waiting and not up.blocked and rp.replan_pending == "no path"
    rp.replan_in_slack()
    up = rp.update(np.zeros(3), np.array([-2.0, 0.0]), ring)
    assert not up.blocked and np.allclose(up.path_world[-1], [-2.0, 0.0])


# --------------------------------------------------------- touchable objects (push or detour)
def _box_points(cx, cy, half):
    """The outline of a square box (P_mov), 2 cm spacing."""
    c = [(cx - half, cy - half), (cx + half, cy - half), (cx + half, cy + half), (cx - half, cy + half)]
    return np.concatenate([_segment(c[k], c[(k + 1) % 4]) for k in range(4)])


def _plan_with(rp, pose, goal, fix, movable):
    pose, goal = np.asarray(pose, float), np.asarray(goal, float)
    up = rp.update(pose, goal, fix, movable)
    if rp.config.first_search_in_tick:  # searched in this tick (a new goal)
        assert up.replanned and not rp.replan_in_slack()
        return up
    assert rp.replan_in_slack()
    return rp.update(pose, goal, fix, movable)


def _crosses(path, cx, cy, half):
    return bool(((np.abs(path[:, 0] - cx) < half) & (np.abs(path[:, 1] - cy) < half)).any())


def test_a_cheap_detour_beats_a_push_and_a_free_curtain_is_passed_through() -> None:
    """A 0.4 m box on the straight line in open space: going round costs a few decimetres, less
    than pushing a cost-6 box; a cost-0 curtain of the same size is passed through."""
    box = _box_points(1.5, 0.0, 0.2)
    rp = _planner()
    up = _plan_with(rp, [0.0, 0.0, 0.0], [3.0, 0.0], np.zeros((0, 2)), (box, np.full(len(box), 6.0)))
    assert rp.last_choice == "detour" and not _crosses(up.path_world, 1.5, 0.0, 0.2)
    assert rp.detours_chosen == 1 and rp.pushes_chosen == 0
    rp = _planner()
    up = _plan_with(rp, [0.0, 0.0, 0.0], [3.0, 0.0], np.zeros((0, 2)), (box, np.zeros(len(box))))
    assert rp.last_choice == "push" and _crosses(up.path_world, 1.5, 0.0, 0.2)


def test_in_a_corridor_the_only_way_is_through_the_box_and_none_with_it_fixed() -> None:
    """A box filling a corridor: the push is the only path (the detour search finds none); the
    same box as P_fix blocks the corridor."""
    walls = np.concatenate([_segment([-5.0, 0.3], [8.0, 0.3]), _segment([-5.0, -0.3], [8.0, -0.3])])
    box = _box_points(1.5, 0.0, 0.2)
    rp = _planner()
    up = _plan_with(rp, [0.0, 0.0, 0.0], [3.0, 0.0], walls, (box, np.full(len(box), 7.0)))
    assert not up.blocked and rp.last_choice == "push" and rp.last_costs[1] == np.inf
    rp = _planner()
    up = _plan_with(rp, [0.0, 0.0, 0.0], [3.0, 0.0], np.concatenate([walls, box]), None)
    assert up.blocked


def test_movable_costs_out_of_range_are_refused() -> None:
    rp = _planner()
    with pytest.raises(PlannerInputError, match="movable costs"):
        rp.update(np.zeros(3), np.array([1.0, 0.0]), np.zeros((0, 2)), (np.zeros((2, 2)), np.array([1.0, 11.0])))


def test_the_goal_approach_brakes_at_the_robots_limit_unless_configured() -> None:
    """decel_mps2 unset: the reference slows to the goal as the base brakes (the robot
    description's max_linear_accel_mps2), v = sqrt(2 a d) at d from the goal; set, it rules."""
    a_robot = ROBOT.limits.max_linear_accel_mps2
    for decel, expected in ((None, a_robot), (1.0, 1.0)):
        rp = _planner(horizon_steps=20, decel_mps2=decel)
        assert rp.decel_mps2 == expected
        up = _plan(rp, np.zeros(3), [0.5, 0.0], np.zeros((0, 2)))
        ref = up.reference
        d = np.hypot(ref[:, 0] - 0.5, ref[:, 1])
        slowing = ref[:, 2] < rp.config.target_speed_mps - 1e-9
        np.testing.assert_allclose(ref[slowing, 2], np.sqrt(2.0 * expected * d[slowing]), atol=0.03)


def test_keep_clear_gives_touchable_points_the_berth_of_fixed_ones() -> None:
    """Points of unknown touchability (mode dct before the VLM's first answer) are P_mov at the
    never-touch cost: the path goes round them, and with keep_clear it keeps the soft zone's
    berth from them (the MPC treats them as fixed) instead of grazing the lethal edge."""
    box = _box_points(1.5, 0.0, 0.2)
    clearances = {}
    for keep_clear in (False, True):
        rp = _planner()
        pose, goal, mov = np.zeros(3), np.array([3.0, 0.0]), (box, np.full(len(box), 10.0))
        up = rp.update(pose, goal, np.zeros((0, 2)), mov, keep_clear=keep_clear)
        assert up.replanned  # a new goal: searched in its tick
        assert rp.last_choice == "detour" and not _crosses(up.path_world, 1.5, 0.0, 0.2)
        clearances[keep_clear] = _path_clearance(up.path_world, box)
    assert clearances[False] < rp.inflation_radius_m + 0.1
    assert clearances[True] > clearances[False] + 0.2


def test_a_requested_replan_follows_the_current_path_until_the_slack_has_searched() -> None:
    rp = _planner()
    up = _plan(rp, np.zeros(3), [2.0, 0.0], np.zeros((0, 2)))
    searches = rp.replans
    rp.request_replan()
    up = rp.update(np.zeros(3), np.array([2.0, 0.0]), np.zeros((0, 2)))
    assert not up.waiting and up.reference[0, 2] > 0.0 and rp.replan_pending == "periodic"
    assert rp.replan_in_slack() and rp.replans == searches + 1
