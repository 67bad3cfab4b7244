"""Navigation modes and the selector: stall detection, the backoff recovery, back to normal."""
import math

import numpy as np
import pytest

from calibration.robot_description import load_robot_description
from models.distance_net import DistanceNet
from runtime.common.events import EventLog
from runtime.modes.backoff import BackoffMode, PoseTrail
from runtime.modes.base import ModeDecision, Situation
from runtime.modes.selector import ModeSelector, RecoveryConfig, StallDetector
from runtime.planning.mpc import MpcPlanner
from runtime.planning.mpc_config import MpcConfig


def test_stall_detector_fires_once_after_the_window_without_progress():
    det = StallDetector(RecoveryConfig(stall_window_s=3.0, min_progress_m=0.1))
    d = ModeDecision(remaining_m=2.0)
    fired = [det.update(t, d) for t in np.arange(0.0, 6.0, 0.05)]
    assert sum(fired) == 1 and det.stalled and det.stalls == 1
    assert fired.index(True) == pytest.approx(60, abs=1)  # at 3.0 s
    det.update(6.0, ModeDecision(remaining_m=1.85))  # progress clears it
    assert not det.stalled


def test_slow_progress_is_not_a_stall_and_a_longer_new_path_restarts_the_clock():
    det = StallDetector(RecoveryConfig(stall_window_s=3.0, min_progress_m=0.1))
    # 5 cm/s of progress: 0.15 m per window.
    assert not any(det.update(t, ModeDecision(remaining_m=3.0 - 0.05 * t)) for t in np.arange(0, 10, 0.05))
    det = StallDetector(RecoveryConfig(stall_window_s=3.0))
    det.update(0.0, ModeDecision(remaining_m=2.0))
    det.update(2.9, ModeDecision(remaining_m=2.6))  # replanned around something new: +0.6 m
    assert not det.update(5.0, ModeDecision(remaining_m=2.6))
    assert det.update(5.95, ModeDecision(remaining_m=2.6))


def test_blocked_or_at_goal_is_not_a_stall():
    det = StallDetector(RecoveryConfig(stall_window_s=1.0))
    assert not any(det.update(t, ModeDecision(blocked=True)) for t in np.arange(0, 5, 0.05))
    assert not any(det.update(t, ModeDecision(at_goal=True, remaining_m=0.0)) for t in np.arange(5, 9, 0.05))


def test_pose_trail_goes_back_along_the_recorded_path_and_forgets_it():
    trail = PoseTrail(spacing_m=0.02)
    for x in np.arange(0.0, 1.0, 0.005):
        trail.record(np.array([x, 0.5 * x, 0.0]))
    n = len(trail)
    assert 40 <= n <= 60  # one pose per 2 cm of a 1.1 m path
    back = trail.back_from(np.array([1.0, 0.5, 0.0]), 0.3)
    length = np.hypot(*np.diff(back, axis=0).T).sum()
    assert 0.3 <= length < 0.33 and np.all(np.diff(back[:, 0]) < 0)
    assert len(trail) < n  # the next backoff goes further back
    back2 = trail.back_from(back[-1], 0.3)
    assert back2[-1][0] < back[-1][0] - 0.25


class StuckMode:
    """A normal mode that never makes progress (the MPC's stall)."""

    name = "stuck"

    def __init__(self):
        self.resets = 0

    def reset(self):
        self.resets += 1

    def plan(self, s):
        return ModeDecision(0.0, 0.0, remaining_m=2.0)


@pytest.fixture(scope="module")
def mpc():
    robot = load_robot_description()
    planner = MpcPlanner(MpcConfig(), robot, DistanceNet.load(robot=robot), wall_clock_caps=False)
    planner.warm_up()
    return planner


def test_a_stall_backs_off_along_the_path_then_replans(mpc):
    cfg = RecoveryConfig(stall_window_s=1.0, backoff_distance_m=0.3, backoff_speed_mps=0.2, max_backoffs=2)
    events = EventLog()
    normal = StuckMode()
    sel = ModeSelector(normal, BackoffMode(mpc, 0.3, 0.2, 4.0), cfg, events)
    pose = np.array([0.0, 0.0, 0.0])
    # Drive to x = 1 m (recording the trail), then sit still.
    t = 0.0
    for x in np.arange(0.0, 1.0, 0.02):
        pose = np.array([x, 0.0, 0.0])
        sel.trail.record(pose)
    sel.reset(t)
    v = np.zeros(2)
    decisions = []
    while t < 4.0:
        s = Situation(t, pose, v, np.zeros((0, 2)), np.array([3.0, 0.0]))
        d = sel.plan(s)
        decisions.append((t, sel.mode_name, d.v_mps))
        if sel.mode_name == "backoff":  # a kinematic robot following the command
            v = np.array([d.v_mps, d.omega_radps])
            pose = pose + np.array([math.cos(pose[2]) * v[0], math.sin(pose[2]) * v[0], v[1]]) * 0.05
        else:
            v = np.zeros(2)
        t += 0.05
    names = [e.event for e in events]
    assert names[:3] == ["stall", "backoff", "backoff_end"], [(e.event, e.reason) for e in events]
    backing = [vv for _, m, vv in decisions if m == "backoff"]
    assert backing and max(backing) <= 1e-9 and min(backing) >= -0.2 - 1e-9  # v in [-v_rev, 0]
    assert pose[0] < 0.8 and abs(pose[1]) < 0.05  # went back along the recorded (straight) path
    assert normal.resets >= 2  # replanned after the backoff
    modes = [m for _, m, _ in decisions]
    first_back = modes.index("backoff")
    assert "stuck" in modes[first_back:]  # back to the normal mode after the backoff
    assert sel.backoffs == 2 and names.count("backoff") == 2  # stalled again: a second try, then none


def test_after_max_backoffs_the_stall_stays_reported():
    cfg = RecoveryConfig(stall_window_s=0.5, max_backoffs=0)
    events = EventLog()
    sel = ModeSelector(StuckMode(), None, cfg, events)
    sel.reset(0.0)
    for t in np.arange(0.0, 3.0, 0.05):
        sel.plan(Situation(t, np.zeros(3), np.zeros(2), np.zeros((0, 2)), np.array([2.0, 0.0])))
    assert [e.event for e in events] == ["stall"] and sel.stall.stalled


# -- mode dct before the VLM's first answer (Situation.unclassified) ------------------------------
def _segment(a, b, step=0.02):
    a, b = np.asarray(a, float), np.asarray(b, float)
    n = max(2, int(np.ceil(np.linalg.norm(b - a) / step)) + 1)
    return a + np.linspace(0, 1, n)[:, None] * (b - a)


def _box(cx, cy, half):
    c = [(cx - half, cy - half), (cx + half, cy - half), (cx + half, cy + half), (cx - half, cy + half)]
    return np.concatenate([_segment(c[k], c[(k + 1) % 4]) for k in range(4)])


def _mpc_mode(mpc):
    from runtime.modes.mpc import MpcMode
    from runtime.planning.reference_path import ReferencePathConfig, ReferencePathPlanner

    mpc.reset()
    return MpcMode(ReferencePathPlanner(ReferencePathConfig(), load_robot_description()), mpc)


def _first_plans(mode, points, unclassified, movable=None, ticks=3):
    """A few ticks standing at the origin, the slack's search after each, as the loop runs them."""
    out = []
    for k in range(ticks):
        s = Situation(0.05 * k, np.zeros(3), np.zeros(2), points, np.array([3.0, 0.0]),
                      *(movable if movable is not None else ()), unclassified=unclassified)
        out.append(mode.plan(s))
        mode.slack_work()
    return out


def test_before_the_first_answer_a_free_detour_is_driven(mpc):
    """An unclassified box in open space: the reference path sees it touchable at the unknown
    cost (10), goes round it, and the robot drives (the MPC keeps clear of it: it is P_fix)."""
    mode = _mpc_mode(mpc)
    box = _box(1.5, 0.0, 0.2)
    d = _first_plans(mode, box, unclassified=True)[-1]
    assert mode.reference.last_choice == "detour" and d.v_mps > 0.0 and not d.blocked


def test_before_the_first_answer_a_way_through_something_waits_and_the_answer_resumes(mpc):
    """A box filling a corridor: the only way leads through it. Unclassified, the robot holds
    still (closing in would only shrink the VLM's view of it); once the answer calls it
    touchable (P_mov) the push is driven."""
    mode = _mpc_mode(mpc)
    walls = np.concatenate([_segment([-5.0, 0.3], [8.0, 0.3]), _segment([-5.0, -0.3], [8.0, -0.3])])
    box = _box(1.5, 0.0, 0.2)
    d = _first_plans(mode, np.concatenate([walls, box]), unclassified=True)[-1]
    assert mode.reference.last_choice == "push"
    assert d.v_mps == 0.0 and d.omega_radps == 0.0 and not d.blocked and "waiting for the VLM" in d.note
    d = _first_plans(mode, walls, unclassified=False, movable=(box, np.full(len(box), 2.0)))[-1]
    assert mode.reference.last_choice == "push" and d.v_mps > 0.0


def test_waiting_for_the_first_answer_is_neither_a_stall_nor_stuck():
    cfg = RecoveryConfig(stall_window_s=0.5, max_backoffs=1)
    events = EventLog()
    sel = ModeSelector(StuckMode(), None, cfg, events)
    sel.reset(0.0)
    for t in np.arange(0.0, 3.0, 0.05):
        sel.plan(Situation(t, np.zeros(3), np.zeros(2), np.zeros((0, 2)), np.array([2.0, 0.0]), unclassified=True))
    assert list(events) == [] and not sel.stall.stalled
    for t in np.arange(3.0, 4.0, 0.05):  # the answer came: the same standstill is a stall now
        sel.plan(Situation(t, np.zeros(3), np.zeros(2), np.zeros((0, 2)), np.array([2.0, 0.0])))
    assert [e.event for e in events] == ["stall"]
