"""The per-obstacle belief (BEACON): priors from the backend's answer, Bayes updates from push
outcomes and push resistance, the decisions taken from it, and the resistance estimate from the
motor currents."""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from calibration.robot_description import load_robot_description
from runtime.vpp.belief import CLASSES, BeliefConfig, BeliefTable, PushResistanceEstimator


def test_priors_follow_the_backends_label_and_cost():
    t = BeliefTable(never_touch_cost=8.0)
    cheap = t.prior(True, 1.0, 0.8)
    costly = t.prior(True, 7.0, 0.8)
    fragile = t.prior(True, 9.0, 0.8)
    fixed = t.prior(False, 5.0, 0.8)
    assert CLASSES[int(np.argmax(cheap))] == "movable" and cheap[2] < costly[2]  # cost moves mass to fragile
    assert CLASSES[int(np.argmax(fragile))] == "fragile"
    assert CLASSES[int(np.argmax(fixed))] == "heavy"
    for p in (cheap, costly, fragile, fixed):
        assert np.isclose(p.sum(), 1.0) and (p > 0).all()


def test_a_box_that_does_not_move_becomes_heavy_and_fixed_and_one_that_moves_stays_movable():
    t = BeliefTable()
    t.observe_answer(3, movable=True, cost=2.0, confidence=0.8, t_s=0.0)
    t.observe_answer(4, movable=True, cost=2.0, confidence=0.8, t_s=0.0)
    assert not t.is_fixed(3) and not t.is_fixed(4)
    t.observe_resistance(3, 0.95, 1.0)  # pushed at the drive's limit
    t.observe_push(3, moved=False, t_s=1.5)
    t.observe_resistance(4, 0.1, 1.0)
    t.observe_push(4, moved=True, t_s=1.5)
    assert t.is_fixed(3) and t.beliefs[3].most_likely() == "heavy"
    assert not t.is_fixed(4) and t.beliefs[4].most_likely() == "movable"
    assert t.expected_cost(3, 2.0) > 8.0 > t.expected_cost(4, 2.0)
    trace = t.describe()["objects"]["3"]["trace"]
    assert [e[1] for e in trace] == ["prior", "resistance 0.95", "not moved"]


def test_the_fixed_labels_ablation_keeps_the_backends_answer():
    t = BeliefTable(BeliefConfig(enabled=False))
    t.observe_answer(3, movable=True, cost=2.0, confidence=0.8, t_s=0.0)
    t.observe_push(3, moved=False, t_s=1.0)
    t.observe_resistance(3, 1.0, 1.0)
    assert not t.is_fixed(3) and t.expected_cost(3, 2.0) == 2.0 and t.updates == 0


def test_a_later_answer_keeps_what_contact_taught_and_a_renamed_object_keeps_its_belief():
    t = BeliefTable()
    t.observe_answer(3, True, 2.0, 0.8, 0.0)
    t.observe_push(3, moved=False, t_s=1.0)
    t.observe_push(3, moved=False, t_s=2.0)
    heavy = t.beliefs[3].probs.copy()
    t.observe_answer(3, True, 3.0, 0.9, 3.0)
    assert np.array_equal(t.beliefs[3].probs, heavy) and t.beliefs[3].backend_cost == 3.0
    t.observe_answer(9, True, 2.5, 0.9, 4.0)  # the same object under a new id: a fresh prior first
    t.rename(3, 9)
    assert 3 not in t.beliefs and t.is_fixed(9) and t.beliefs[9].backend_cost == 2.5


def test_beliefs_of_objects_no_longer_known_are_forgotten_and_the_table_stays_bounded():
    t = BeliefTable(BeliefConfig(max_remembered=2))
    for k in range(5):
        t.observe_answer(k, True, 2.0, 0.8, float(k))
    for k in (1, 2, 3):  # pushed: contact taught these something
        t.observe_push(k, moved=True, t_s=10.0 + k)
    assert t.forget(live={0, 4}) == 1  # 1, 2, 3 remembered beyond the live ones; max 2: 1 (the oldest) goes
    assert set(t.beliefs) == {0, 2, 3, 4}
    assert t.forget(live={0, 2, 3, 4}) == 0
    # A run of new objects that come and go (the backend naming each box it sees anew): the table
    # holds what is live and the few remembered, not every object of the run.
    for k in range(100, 5000):
        t.observe_answer(k, True, 2.0, 0.8, float(k))
        t.forget(live={k, k - 1})
    assert len(t.beliefs) <= 2 + 2 and t.forgotten >= 4895
    assert t.describe()["forgotten"] == t.forgotten


@settings(max_examples=50, deadline=None)
@given(st.lists(st.tuples(st.booleans(), st.floats(0.0, 2.0)), max_size=30))
def test_the_belief_stays_a_distribution_and_never_reaches_zero(evidence):
    t = BeliefTable()
    t.observe_answer(1, True, 4.0, 0.7, 0.0)
    for k, (moved, force) in enumerate(evidence):
        t.observe_push(1, moved, float(k))
        t.observe_resistance(1, force, float(k))
    p = t.beliefs[1].probs
    assert np.isclose(p.sum(), 1.0) and (p >= t.config.floor / (1 + 3 * t.config.floor) - 1e-12).all()


def test_bad_likelihoods_are_refused_naming_the_field():
    with pytest.raises(ValueError, match="p_moved"):
        BeliefConfig(p_moved=(1.0, 0.5, 0.5))


def test_push_resistance_is_the_force_beyond_what_the_robot_needs_for_itself():
    robot = load_robot_description()
    est = PushResistanceEstimator(robot)
    kt, r = robot.motors.torque_constant_nm_per_a, robot.drive.wheel_radius_m
    free_current = 0.5  # per motor, steady driving at 0.4 m/s with no contact
    t = 0.0
    for _ in range(50):  # free driving: learns what driving itself costs
        t += 0.05
        assert est.update(t, 0.4, [free_current] * 4, in_contact=False) is None
    push_n = 40.0  # an obstacle resisting with 40 N at the same speed: more current
    extra = push_n * r / kt / 4
    t += 0.05
    assert est.update(t, 0.4, [free_current + extra] * 4, in_contact=True) == pytest.approx(push_n / est.f_max, rel=1e-6)
    assert est.update(t + 0.05, 0.4, None, in_contact=True) is None  # no currents: no estimate


def test_contact_evidence_updates_the_belief_once_per_window_of_continuous_push():
    from runtime.vpp.belief import ContactEvidence

    robot = load_robot_description()
    table = BeliefTable()
    table.observe_answer(5, True, 2.0, 0.8, 0.0)
    est = PushResistanceEstimator(robot)
    ev = ContactEvidence(table, est, window_s=1.0)
    kt, r = robot.motors.torque_constant_nm_per_a, robot.drive.wheel_radius_m
    t = 0.0
    for _ in range(40):  # free driving first
        t += 0.05
        ev.update(t, 0.3, [0.4] * 4, None, lambda o, s: None)
    assert table.updates == 0
    stalled = 0.4 + 0.95 * est.f_max * r / kt / 4  # the drive at 95% of its force, the box not moving
    for _ in range(22):  # 1.05 s of contact
        t += 0.05
        ev.update(t, 0.3, [stalled] * 4, 5, lambda o, s: 0.0)
    assert ev.windows == 1 and table.updates == 2  # one resistance and one push outcome
    assert table.is_fixed(5) and table.beliefs[5].most_likely() == "heavy"
    ev.update(t + 0.05, 0.0, [0.4] * 4, None, lambda o, s: 0.0)  # stopped: the window restarts
    assert ev.windows == 1


def test_the_drive_losses_are_learned_only_from_free_driving():
    """Pressing on a wall (not free) must not become the baseline, or every later push would
    read as light."""
    robot = load_robot_description()
    est = PushResistanceEstimator(robot)
    t = 0.0
    for _ in range(40):  # free driving at 0.4 A a motor
        t += 0.05
        est.update(t, 0.3, [0.4] * 4, in_contact=False, learn=True)
    for _ in range(40):  # pressing on a fixed obstacle: not contact with a touchable object, not free
        t += 0.05
        est.update(t, 0.3, [3.0] * 4, in_contact=False, learn=False)
    t += 0.05
    heavy = est.update(t, 0.3, [3.0] * 4, in_contact=True)
    assert heavy > 0.5  # still reads as a hard push
