"""Patrols and goal changes while driving: the scenario form (goals: + patrol:), the sequencer,
and lockstep episodes (deterministic) where the goal changes mid-drive and where a patrol loops."""
from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from calibration.errors import ConfigFileError
from calibration.robot_description import load_robot_description
from hil_sim.episode.patrol import PatrolError, PatrolSequencer, goal_in_odom, with_duration
from hil_sim.episode.lockstep import run_episode
from hil_sim.world.scenario import Scenario, load_scenario
from hil_sim.world.scenario_checks import ScenarioError, check_scenario_against_robot
from runtime.config import load_controller_config
from runtime.common.geometry import Pose2D

ROBOT = load_robot_description()

ROOM = {
    "name": "patrol_mini",
    "floor": {"size_m": [6.0, 6.0], "friction": 0.8},
    "robot": {"start": {"x_m": -1.5, "y_m": -1.0, "yaw_deg": 0.0}},
    "goals": [
        {"pose": {"x_m": 1.5, "y_m": -1.0}, "tolerance_m": 0.2},
        {"pose": {"x_m": 1.5, "y_m": 1.0}, "tolerance_m": 0.2},
        {"pose": {"x_m": -1.5, "y_m": 1.0}, "tolerance_m": 0.2},
    ],
    "patrol": {"loops": 2},
    "time_limit_s": 120.0,
}


def scenario(**changes) -> Scenario:
    return Scenario.model_validate({**ROOM, **changes})


def write(tmp_path: Path, raw: dict) -> Path:
    p = tmp_path / "scn.yaml"
    p.write_text(yaml.safe_dump(raw))
    return p


# -- the scenario form -----------------------------------------------------------------------------
def test_goals_make_a_patrol_whose_first_goal_is_the_goal_and_single_goal_files_are_unchanged():
    sc = scenario()
    assert sc.is_patrol and sc.goal == sc.goals[0] and len(sc.goal_sequence) == 3
    assert Scenario.model_validate(sc.model_dump(by_alias=True)) == sc  # a dumped patrol loads again
    case1 = load_scenario("case1")
    assert not case1.is_patrol and case1.goal_sequence == [case1.goal] and case1.patrol is None
    lib = load_scenario("patrol_room")
    assert lib.is_patrol and lib.patrol.loops == 2
    assert check_scenario_against_robot(lib, ROBOT) == []


@pytest.mark.parametrize("change,words", [
    ({"patrol": {"loops": 2, "duration_s": 60.0}}, "patrol: give exactly one of loops"),
    ({"patrol": {}}, "patrol: give exactly one of loops"),
    ({"patrol": {"loops": 0}}, "patrol.loops"),
    ({"goal": {"pose": {"x_m": 0.0, "y_m": 0.0}, "tolerance_m": 0.1}}, "goal and goals"),
    ({"goals": [ROOM["goals"][0]]}, "goals"),
    ({"goals": [ROOM["goals"][0], {"pose": {"x_m": 1.6, "y_m": -1.0}, "tolerance_m": 0.2}]}, "goals[1] is 0.100 m from goals[0]"),
    ({"goals": ROOM["goals"] + [{"pose": {"x_m": 1.55, "y_m": -0.95}, "tolerance_m": 0.2}]}, "goals[0]"),
    ({"goals": ROOM["goals"][:2] + [{"pose": {"x_m": 9.0, "y_m": 0.0}, "tolerance_m": 0.2}]}, "goals[2].pose (9.0, 0.0) lies outside the floor"),
    ({"patrol": {"duration_s": 200.0}}, "patrol.duration_s 200 is longer than time_limit_s 120"),
])
def test_a_bad_patrol_is_one_line_naming_the_field(tmp_path, change, words):
    raw = {**ROOM, **change}
    with pytest.raises(ConfigFileError) as err:
        load_scenario(write(tmp_path, raw))
    msg = str(err.value)
    assert words in msg and "\n" not in msg, msg


def test_patrol_without_goals_and_no_goal_at_all_are_refused(tmp_path):
    single = {k: v for k, v in ROOM.items() if k != "goals"}
    with pytest.raises(ConfigFileError, match="patrol: needs goals"):
        load_scenario(write(tmp_path, {**single, "goal": ROOM["goals"][0]}))
    with pytest.raises(ConfigFileError, match="goal: required"):
        load_scenario(write(tmp_path, {k: v for k, v in single.items() if k != "patrol"}))


def test_a_goal_inside_an_obstacle_names_its_index():
    block = {"name": "block", "shape": "box", "size": {"xyz_m": [0.6, 0.6, 0.6]}, "pose": {"x_m": 1.5, "y_m": 1.0},
             "class": "fixed"}
    with pytest.raises(ScenarioError, match=r"goals\[1\]\.pose: the goal \(1.5, 1\) lies inside"):
        check_scenario_against_robot(scenario(obstacles=[block]), ROBOT)


def test_duration_replaces_the_patrol_and_only_a_patrol_has_one():
    sc = with_duration(scenario(), 600.0)
    assert sc.patrol.duration_s == 600.0 and sc.patrol.loops is None and sc.time_limit_s == 600.0
    assert with_duration(scenario(), None) == scenario()
    with pytest.raises(PatrolError, match="--duration: scenario case1 has a single goal"):
        with_duration(load_scenario("case1"), 60.0)


# -- the sequencer ---------------------------------------------------------------------------------
def test_the_sequencer_sends_the_next_goal_only_when_the_controller_finished_with_the_one_sent():
    sc = scenario(patrol={"loops": 1, "goal_timeout_s": 10.0})
    seq = PatrolSequencer(sc, t0_s=5.0)
    g0, g1 = goal_in_odom(sc, 0), goal_in_odom(sc, 1)
    assert (g0.x_m, g0.y_m) == pytest.approx((3.0, 0.0))
    # finished, but with another goal (a stale report): nothing
    assert seq.update(6.0, (1.5, -1.0), (0.0, 0.0), True, False) is None
    # finished with the goal sent, at it: reached, the next goal comes
    nxt = seq.update(7.0, (1.45, -1.0), (g0.x_m, g0.y_m), True, False)
    assert nxt == g1 and seq.visits[0].outcome == "reached" and seq.visits[0].ended_at_s == pytest.approx(2.0)
    # the controller has not taken g1 yet and still says finished with g0: no double count
    assert seq.update(7.05, (1.45, -1.0), (g0.x_m, g0.y_m), True, False) is None
    assert seq.resend_due(7.5, (g0.x_m, g0.y_m)) is False and seq.resend_due(8.1, (g0.x_m, g0.y_m)) is True
    assert seq.resend_due(9.5, (g1.x_m, g1.y_m)) is False  # it has it
    # not reached within the timeout: missed, the next is sent
    nxt = seq.update(17.0, (1.5, 0.0), (g1.x_m, g1.y_m), False, False)
    assert seq.visits[1].outcome == "missed_timeout" and nxt == goal_in_odom(sc, 2)
    # finished with g2 but 0.5 m off in the world (odometry drift): missed; one loop: the patrol ends
    g2 = goal_in_odom(sc, 2)
    assert seq.update(20.0, (-1.0, 1.0), (g2.x_m, g2.y_m), True, False) is None
    assert seq.visits[2].outcome == "missed_odometry" and seq.done and seq.end_reason == "loops_done"
    c = seq.counts()
    assert c == {"goals_sent": 3, "goals_reached": 1, "goals_missed": 2, "goals_in_progress": 0, "loops_completed": 1}
    assert not seq.succeeded


def test_a_localized_patrol_places_each_goal_in_the_odometry_frame_as_it_lies_now():
    sc = scenario(patrol={"loops": 1, "localized": True})
    seq = PatrolSequencer(sc, t0_s=0.0)
    g0 = goal_in_odom(sc, 0)  # the first goal: the start's frame (the controller was given it at start)
    assert seq.current_goal_odom() == g0
    # at goal 0 in the world, the odometry says 0.2 m further along x than it went: drift
    odom = Pose2D(g0.x_m + 0.2, g0.y_m, 0.0)
    nxt = seq.update(5.0, (1.5, -1.0, 0.0), (g0.x_m, g0.y_m), True, False, odom)
    assert seq.visits[0].outcome == "reached" and seq.visits[0].odometry_drift_m == pytest.approx(0.2)
    # goal 1 is (1.5, 1.0) in the world: 2 m to the left of the robot, wherever the odometry thinks it is
    assert (nxt.x_m, nxt.y_m) == pytest.approx((odom.x_m, odom.y_m + 2.0))
    plain = PatrolSequencer(scenario(patrol={"loops": 1}), t0_s=0.0)
    nxt = plain.update(5.0, (1.5, -1.0, 0.0), (g0.x_m, g0.y_m), True, False, odom)
    assert nxt == goal_in_odom(sc, 1) and plain.visits[0].odometry_drift_m == pytest.approx(0.2)
    assert seq.report(5.0)["localized"] and not plain.report(5.0)["localized"]


def test_a_duration_patrol_ends_on_time_with_the_goal_in_progress_counted_as_neither():
    sc = with_duration(scenario(), 30.0)
    seq = PatrolSequencer(sc, t0_s=0.0)
    g0 = goal_in_odom(sc, 0)
    seq.update(10.0, (1.5, -1.0), (g0.x_m, g0.y_m), True, False)
    assert seq.update(29.9, (0.0, 0.0), None, False, False) is None and not seq.done
    seq.update(30.0, (0.0, 0.0), None, False, False)
    assert seq.done and seq.end_reason == "duration" and seq.succeeded
    assert [v.outcome for v in seq.visits] == ["reached", "in_progress"]


def test_a_stopped_controller_ends_the_patrol_as_a_failure():
    seq = PatrolSequencer(scenario(), t0_s=0.0)
    seq.update(3.0, (0.0, -1.0), None, False, True)
    assert seq.done and seq.end_reason == "controller_stopped" and not seq.succeeded


def test_a_random_order_patrol_draws_each_next_goal_from_the_seed_among_the_others():
    sc = scenario(patrol={"duration_s": 100.0, "order": "random"})

    def drive(seed: int) -> list[int]:
        seq = PatrolSequencer(sc, t0_s=0.0, seed=seed)
        for k in range(60):
            g = seq.current_goal_odom()
            world = sc.goals[seq.current.goal_index]
            seq.update(float(k + 1), (world.x_m, world.y_m), (g.x_m, g.y_m), True, False)
        return [v.goal_index for v in seq.visits]

    order = drive(3)
    assert order[0] == 0 and len(order) == 61
    assert all(a != b for a, b in zip(order, order[1:]))  # never the goal it is at
    assert set(order) == {0, 1, 2} and order == drive(3)  # every goal, and the same for the same seed
    assert order != drive(4)
    in_order = PatrolSequencer(scenario(patrol={"duration_s": 100.0}), t0_s=0.0, seed=3)
    assert [v.goal_index for v in in_order.visits] == [0]


def test_a_random_order_patrol_checks_every_pair_of_goals():
    goals = [{"pose": {"x_m": 1.5, "y_m": -1.0}, "tolerance_m": 0.2}, {"pose": {"x_m": 1.5, "y_m": 1.0}, "tolerance_m": 0.2},
             {"pose": {"x_m": 1.6, "y_m": -0.9}, "tolerance_m": 0.2}]
    assert scenario(goals=goals, patrol={"loops": 1}).is_patrol  # in order, once: goals[2] follows goals[1] only
    with pytest.raises(ValueError, match=r"goals\[2\] is 0.141 m from goals\[0\]"):
        scenario(goals=goals, patrol={"duration_s": 50.0, "order": "random"})


def test_a_day_long_patrol_is_allowed_and_longer_is_refused():
    assert with_duration(scenario(), 4 * 3600.0).patrol.duration_s == 14400.0
    with pytest.raises(PatrolError, match="not in"):
        with_duration(scenario(), 86401.0)
    assert load_scenario("patrol_people").patrol.order == "random"
    assert check_scenario_against_robot(load_scenario("patrol_people"), ROBOT) == []


# -- lockstep episodes ----------------------------------------------------------------------------
def test_lockstep_goal_change_mid_drive_redirects_the_robot_deterministically():
    """all-fixed (lidar, reference path, MPC): driving east, at 2 s the goal becomes a point to the
    north-east; the robot replans and ends there, not at the first goal. Same seed, same metrics."""
    sc = Scenario.model_validate({
        "name": "redirect", "floor": {"size_m": [6.0, 6.0], "friction": 0.8},
        "walls": [{"from": [-3.0, -3.0], "to": [3.0, -3.0], "thickness_m": 0.1, "height_m": 0.8},
                  {"from": [-3.0, 3.0], "to": [3.0, 3.0], "thickness_m": 0.1, "height_m": 0.8}],
        "obstacles": [{"name": "post", "shape": "cylinder", "size": {"radius_m": 0.15, "height_m": 0.8},
                       "pose": {"x_m": 0.5, "y_m": 1.0}, "class": "fixed"}],
        "robot": {"start": {"x_m": -2.0, "y_m": 0.0, "yaw_deg": 0.0}},
        "goal": {"pose": {"x_m": 2.0, "y_m": 0.0}, "tolerance_m": 0.15},
        "time_limit_s": 25.0,
    })
    config = load_controller_config().with_planner_mode("all-fixed")
    new_goal_world = (1.5, 1.8)
    poses_at_change = []

    def observe(ctl):
        if not poses_at_change and ctl.clock() >= 2.0:
            poses_at_change.append(ctl.pose)
            # the goal in the odometry frame (start at (-2, 0), yaw 0)
            ctl.request_goal(Pose2D(new_goal_world[0] + 2.0, new_goal_world[1], 0.0), "test")

    runs = []
    for _ in range(2):
        poses_at_change.clear()
        runs.append(run_episode(sc, robot=ROBOT, config=config, seed=0, observe=observe))
    m = runs[0].metrics
    assert json.dumps(m, sort_keys=True) == json.dumps(runs[1].metrics, sort_keys=True)
    p = poses_at_change[0]
    assert p.x_m > 0.4 and abs(p.y_m) < 0.1  # it was on its way east
    x, y, _ = m["final_pose_world"]
    assert math.hypot(x - new_goal_world[0], y - new_goal_world[1]) < 0.15, m["final_pose_world"]
    assert m["controller_state"] == "GOAL_REACHED" and m["fixed_contacts"] == 0
    ev = [e for e in m["events"] if e["event"] == "new_goal"]
    assert len(ev) == 1 and "while driving" in ev[0]["reason"]
    assert m["controller"]["goals_received"] == 2 and m["controller"]["goals_reached"] == 1


def test_lockstep_patrol_visits_the_goals_in_order_round_twice_deterministically():
    """Pure pursuit without sensors (fast): six goals sent in order, each the moment the controller
    finished with the one before. (Wheel odometry alone drifts in the turns: the later visits end
    away from their goals in the world, and the metrics say so: missed_odometry.)"""
    config = load_controller_config().with_planner_mode("pure-pursuit")
    sc = scenario()
    a = run_episode(sc, robot=ROBOT, config=config, seed=0).metrics
    b = run_episode(sc, robot=ROBOT, config=config, seed=0).metrics
    assert json.dumps(a, sort_keys=True) == json.dumps(b, sort_keys=True)
    p = a["patrol"]
    assert p["end_reason"] == "loops_done" and p["goals_sent"] == 6 and p["loops_completed"] == 2
    assert [v["goal_index"] for v in p["visits"]] == [0, 1, 2, 0, 1, 2]
    assert [v["loop"] for v in p["visits"]] == [0, 0, 0, 1, 1, 1]
    assert p["visits"][0]["outcome"] == "reached"
    for v in p["visits"]:
        assert (v["outcome"] == "reached") == (v["world_error_m"] <= 0.2), v
    assert all(v2["sent_at_s"] == v1["ended_at_s"] for v1, v2 in zip(p["visits"], p["visits"][1:]))
    assert a["success"] == (p["goals_missed"] == 0)
    assert a["controller"]["goals_received"] == 6 and a["controller"]["goals_reached"] == 6
    assert [e["event"] for e in a["events"]].count("new_goal") == 5


@pytest.mark.slow  # (the dct patrol round twice is the fast one)
def test_lockstep_patrol_all_fixed_reaches_every_goal_in_a_walled_room():
    """The MPC mode with lidar and IMU: one loop of three goals (placed as a localizer would), each
    reached in the world, no contact, the odometry's drift reported per visit."""
    walls = [{"from": [-3.0, -3.0], "to": [3.0, -3.0], "thickness_m": 0.1, "height_m": 0.8},
             {"from": [3.0, -3.0], "to": [3.0, 3.0], "thickness_m": 0.1, "height_m": 0.8},
             {"from": [3.0, 3.0], "to": [-3.0, 3.0], "thickness_m": 0.1, "height_m": 0.8},
             {"from": [-3.0, 3.0], "to": [-3.0, -3.0], "thickness_m": 0.1, "height_m": 0.8}]
    post = {"name": "post", "shape": "cylinder", "size": {"radius_m": 0.2, "height_m": 0.8},
            "pose": {"x_m": 0.0, "y_m": 0.0}, "class": "fixed"}
    sc = scenario(walls=walls, obstacles=[post], patrol={"loops": 1, "localized": True})
    m = run_episode(sc, robot=ROBOT, config=load_controller_config().with_planner_mode("all-fixed"), seed=0).metrics
    p = m["patrol"]
    assert [v["outcome"] for v in p["visits"]] == ["reached"] * 3, p["visits"]
    assert m["success"] and m["fixed_contacts"] == 0 and p["end_reason"] == "loops_done"
    assert all(v["odometry_drift_m"] is not None for v in p["visits"]) and p["localized"]


def test_lockstep_patrol_goal_not_reached_in_time_is_missed_and_the_patrol_goes_on():
    """goal_timeout_s 4.5 s: a 3 m leg ending in a turn is not done in time; the patrol sends the
    next goal anyway and fails naming the missed visit."""
    config = load_controller_config().with_planner_mode("pure-pursuit")
    sc = scenario(patrol={"loops": 1, "goal_timeout_s": 4.5})
    m = run_episode(sc, robot=ROBOT, config=config, seed=0).metrics
    p = m["patrol"]
    outcomes = [v["outcome"] for v in p["visits"]]
    assert "missed_timeout" in outcomes and "reached" in outcomes, p["visits"]
    assert not m["success"] and m["failure_reason"].startswith("patrol: ")
    assert "not reached within 4.5 s" in m["failure_reason"]


def test_cli_duration_needs_a_patrol(tmp_path):
    r = subprocess.run([sys.executable, "-m", "runtime.app.cli", "hil", "run", "case1", "--duration", "30"],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 2 and "--duration: scenario case1 has a single goal" in r.stderr


@pytest.mark.slow
def test_patrol_room_one_loop_all_fixed():
    config = load_controller_config().with_planner_mode("all-fixed")
    sc = load_scenario("patrol_room").model_copy(update={"patrol": load_scenario("patrol_room").patrol.model_copy(
        update={"loops": 1})})
    m = run_episode(sc, robot=ROBOT, config=config, seed=0).metrics
    assert m["success"], m["failure_reason"]
    assert m["patrol"]["goals_reached"] == 4 and m["fixed_contacts"] == 0


@pytest.mark.slow
@pytest.mark.realtime
def test_patrol_room_realtime_two_processes_with_a_recording(tmp_path):
    out, rec = tmp_path / "p.json", tmp_path / "p.mcap"
    r = subprocess.run([sys.executable, "-m", "runtime.app.cli", "hil", "run", "patrol_room", "--realtime", "--duration",
                        "40", "--record", str(rec), "--json", str(out)], capture_output=True, text=True, timeout=400)
    assert r.returncode in (0, 1), r.stderr[-2000:]
    m = json.loads(out.read_text())
    p = m["patrol"]
    assert p["goals_published"] >= 1, p
    # Two goals in the 40 s, unless the simulator fell behind the wall clock by more than a CAN
    # stream's 0.1 s timeout: the controller then holds still on its late data, as it must, and
    # the patrol's time runs on (the simulator shares the two cores with the controller).
    lagged = (m["simulator"]["sim_lag_ms"]["max"] or 0.0) > 100.0
    assert p["goals_reached"] >= 2 or lagged, (p, m["simulator"]["sim_lag_ms"])
    # Real time on a shared 2-core machine: the controller may miss its command deadline 3 ticks
    # in a row (the simulator, the ICP worker and another test take the cores) and then stops, as
    # it must. That is the only early end allowed here; timing itself is the benchmarks' to report.
    early = p["end_reason"] == "controller_stopped" and "deadline" in (m["stop_reason"] or "")
    assert p["end_reason"] == "duration" or early, (p["end_reason"], m["stop_reason"])
    assert m["realtime"]["recording"]["path"] == str(rec) and rec.is_file()
