"""Correcting mode (DCT IV-C-3): the stuck trigger (odometry, checked by the lidar for slipping
wheels), the relabelling (eq. 14) in the mask memory and the label memory, and the selector's
state machine normal -> correcting -> normal with its records."""
from __future__ import annotations

import math

import numpy as np
import pytest

from runtime.common.events import EventLog
from runtime.modes.base import ModeDecision, Situation
from runtime.modes.correcting import CorrectingConfig, StuckDetector, slip_fraction
from runtime.modes.selector import ModeSelector, RecoveryConfig
from runtime.vpp.mask_memory import MaskMemory
from runtime.vpp.partition.label_memory import LabelMemory
from runtime.vpp.partition.labels import FIXED, MOVABLE
from tests.runtime.vpp.test_mask_memory import PINHOLE, answer, rect

CONFIG = CorrectingConfig(v_min_mps=0.1, d_stuck_m=0.05, tau_stuck_s=0.8)


def _room(rng) -> np.ndarray:
    """P_fix of a 6 x 4 m room (odom frame), 2 cm noise."""
    t = np.linspace(0, 1, 150)
    walls = np.concatenate([
        np.column_stack([-2 + 6 * t, np.full_like(t, -2)]), np.column_stack([-2 + 6 * t, np.full_like(t, 2)]),
        np.column_stack([np.full_like(t, -2), -2 + 4 * t]), np.column_stack([np.full_like(t, 4), -2 + 4 * t]),
    ])
    return walls + rng.normal(0, 0.01, walls.shape)


def _situation(t, pose, cmd_v, points) -> Situation:
    return Situation(t, np.asarray(pose, float), np.array([cmd_v, 0.0]), points, np.array([3.0, 0.0]))


def _drive(det, odom_speed, true_speed, seconds=2.0, v_cmd=0.8):
    """Ticks at 20 Hz, a scan every other tick; the odometry says odom_speed, the world moves by
    true_speed (the scan is of the room seen from the true pose, placed with the odometry's)."""
    room = _room(np.random.default_rng(0))
    pts = room
    for k in range(int(seconds / 0.05)):
        t = 0.05 * k
        odom = np.array([odom_speed * t, 0.0, 0.0])
        if k % 2 == 0:  # a new scan: the room seen from the true pose, placed with the odometry's
            pts = room - [true_speed * t, 0.0] + odom[:2]
        why = det.update(_situation(t, odom, v_cmd, pts))
        if why is not None:
            return t, why
    return None, None


def test_commanding_motion_without_moving_is_stuck_after_tau():
    t, why = _drive(StuckDetector(CONFIG), odom_speed=0.0, true_speed=0.0)
    assert t == pytest.approx(0.8, abs=0.06) and "moved 0.0 cm" in why


def test_slipping_wheels_are_found_by_the_lidar_and_the_slip_measured():
    det = StuckDetector(CONFIG)
    t, why = _drive(det, odom_speed=0.6, true_speed=0.0)
    assert t is not None and t < 1.2 and "wheels slipping" in why
    # The odometry moved ~0.5 m in the window; the scan shows none of it.
    assert det.last_slip_xy[0] == pytest.approx(0.6 * 0.8, abs=0.1)


def test_real_motion_and_no_command_are_not_stuck():
    assert _drive(StuckDetector(CONFIG), odom_speed=0.6, true_speed=0.6)[0] is None
    assert _drive(StuckDetector(CONFIG), odom_speed=0.0, true_speed=0.0, v_cmd=0.05)[0] is None


def test_a_featureless_corridor_never_makes_a_lidar_stuck():
    """Walls parallel to the motion only (longer than the lidar check's range): a scan that moves
    with the odometry (slip) and one that does not look the same, "stood still" and "moved" fit
    alike, and the odometry is believed."""
    t = np.linspace(-20, 20, 1600)
    corridor = np.concatenate([np.column_stack([t, np.full_like(t, -1.0)]), np.column_stack([t, np.full_like(t, 1.0)])])
    det = StuckDetector(CONFIG)
    for k in range(40):
        s = 0.05 * k
        assert det.update(_situation(s, [0.6 * s, 0.0, 0.0], 0.8, corridor + [0.6 * s, 0.0])) is None


def test_slip_fraction_finds_the_share_of_the_motion_the_scan_does_not_show():
    room = _room(np.random.default_rng(1))
    pose0, pose1 = np.zeros(3), np.array([0.5, 0.0, 0.0])
    q0 = room.copy()
    q1 = room - [0.1, 0.0]  # the robot truly moved 0.1 of the odometry's 0.5 m
    assert slip_fraction(q0, pose0, q1, pose1) == pytest.approx(0.8, abs=0.11)


def test_label_memory_fix_object_relabels_only_that_objects_voxels():
    mem = LabelMemory(0.1, 5.0, 64)
    pts = np.array([[0.05, 0.05, 0.1], [1.05, 0.05, 0.1], [2.05, 0.05, 0.1]])
    mem.write(pts, np.ones(3, bool), np.array([MOVABLE, MOVABLE, FIXED], np.int8), np.array([4, 5, -1]),
              np.array([2.0, 2.0, np.nan]), 0.0)
    assert mem.fix_object(4) == 1
    found, lab, obj, cost = mem.read(pts, np.ones(3, bool), 0.1)
    assert found.all() and lab.tolist() == [FIXED, MOVABLE, FIXED] and obj.tolist() == [-1, 5, -1]
    assert math.isnan(cost[0]) and cost[1] == 2.0


def test_a_demoted_object_stays_demoted_through_reconciliation():
    """Matched by IoU: the id (and its demotion) carries over; dropped meanwhile (out of view) and
    seen again: the fresh detection is matched against the demoted object's last entry."""
    mem = MaskMemory(PINHOLE)
    box, other = rect(100, 100, 200, 200), rect(400, 100, 500, 200)
    mem.reconcile(answer(0.0, np.eye(4), [box, other]))
    mem.demote(0)
    mem.reconcile(answer(1.0, np.eye(4), [rect(101, 100, 201, 200), other]))
    assert [e.object_id for e in mem.entries] == [0, 1] and mem.is_demoted(0) and not mem.is_demoted(1)
    r = mem.reconcile(answer(2.0, np.eye(4), [other]))  # the box out of view: dropped
    assert r.dropped == (0,) and [e.object_id for e in mem.entries] == [1]
    r = mem.reconcile(answer(3.0, np.eye(4), [other, rect(100, 100, 200, 200)]))
    assert sorted(e.object_id for e in mem.entries) == [0, 1] and r.inserted == ()
    assert mem.is_demoted(0)
    # A different object in another place is a new, movable one.
    mem.reconcile(answer(4.0, np.eye(4), [other, rect(100, 100, 200, 200), rect(250, 300, 350, 400)]))
    assert [mem.is_demoted(e.object_id) for e in mem.entries] == [False, True, False]


class _Normal:
    name = "all-fixed"

    def __init__(self):
        self.resets = 0

    def plan(self, s):
        return ModeDecision(0.8, 0.0, remaining_m=2.0)

    def reset(self):
        self.resets += 1

    def counters(self):
        return {}

    def slack_work(self):
        return False


class _Partition:
    def __init__(self):
        self.calls = []

    def relabel_fixed_in_front(self, pose, half_length_m, half_width_m, margin_m, forward):
        self.calls.append((pose, forward))
        return 7


class _Backoff:
    """The reverse: done after 1 s."""
    distance_m = 0.0

    def start(self, s, trail):
        self._t0 = s.now_s
        return f"reversing {self.distance_m:.2f} m"

    def plan(self, s):
        if s.now_s - self._t0 >= 1.0:
            return ModeDecision(done=True, note="backed off")
        return ModeDecision(-0.2, 0.0, note="backing off")

    def reset(self):
        pass


def test_selector_stuck_relabels_reverses_replans_and_records():
    from calibration.robot_description import load_robot_description
    from runtime.modes.correcting import CorrectingMode

    partition = _Partition()
    corr = CorrectingMode(CONFIG, _Backoff(), load_robot_description(), partition)
    events = EventLog()
    normal = _Normal()
    sel = ModeSelector(normal, None, RecoveryConfig(), events, corr)
    pts = _room(np.random.default_rng(2))
    names = []
    for k in range(80):
        t = 0.05 * k
        sel.plan(_situation(t, [0.0, 0.0, 0.0], 0.8, pts))
        names.append(sel.mode_name)
    assert "correcting" in names and names[-1] == "all-fixed"
    first = names.index("correcting")
    assert 0.05 * first == pytest.approx(0.8, abs=0.06)
    assert partition.calls and partition.calls[0][1] is True  # forward: the object ahead
    rep = sel.counters()
    assert rep["correcting_events"] >= 1
    c = rep["correcting"][0]
    assert c["object_id"] == 7 and c["duration_s"] == pytest.approx(1.0, abs=0.06) and c["reason"].startswith("stuck")
    assert c["traceback_m"] == pytest.approx(CONFIG.traceback_states * CONFIG.trail_spacing_m)
    ev = [e.event for e in events]
    assert ev[:3] == ["stuck", "correcting", "correcting_end"]
    # A second correction at the same place traces back further.
    assert len(rep["correcting"]) < 2 or rep["correcting"][1]["traceback_m"] > c["traceback_m"]


class _BlockedForAWhile(_Normal):
    """Drives (0.8 m/s) for 0.5 s, has no path (blocked) from 0.5 s to 3.5 s, then drives again."""

    def plan(self, s):
        if 0.5 <= s.now_s < 3.5:
            return ModeDecision(0.0, 0.0, remaining_m=2.0, blocked=True)
        return ModeDecision(0.8, 0.0, remaining_m=2.0)


def test_waiting_for_the_way_to_clear_is_not_a_stuck_push():
    """A robot that drove up to a person standing in a corridor, held while there was no path and
    goes on when the way clears is not stuck at that tick: the window starts afresh while blocked
    (it spanned the wait, and person_blocking's robot reversed 0.45 m the tick the way cleared).
    Standing still with the command on for tau_stuck after that is stuck again."""
    from calibration.robot_description import load_robot_description
    from runtime.modes.correcting import CorrectingMode

    corr = CorrectingMode(CONFIG, _Backoff(), load_robot_description(), _Partition())
    events = EventLog()
    sel = ModeSelector(_BlockedForAWhile(), None, RecoveryConfig(), events, corr)
    pts = _room(np.random.default_rng(3))
    stuck_at, scan = None, pts
    for k in range(int(5.0 / 0.05)):
        t = 0.05 * k
        if k % 2 == 0:
            scan = pts.copy()  # a new scan every other tick (10 Hz)
        sel.plan(_situation(t, [0.0, 0.0, 0.0], 0.8 if not 0.5 <= t < 3.5 else 0.0, scan))
        if stuck_at is None and any(e.event == "stuck" for e in events):
            stuck_at = t
    assert stuck_at is not None and stuck_at >= 3.5 + CONFIG.tau_stuck_s - 0.06, stuck_at
