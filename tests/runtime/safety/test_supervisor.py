"""Safety supervisor: stops in front of a wall, lets clear or escaping commands through."""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from calibration.robot_description import load_robot_description
from runtime.planning.distance_model import rectangle_signed_distance
from runtime.planning.errors import PlannerInputError
from runtime.safety.supervisor import SafetySupervisor, SafetySupervisorConfig

ROBOT = load_robot_description()
HL, HW = ROBOT.footprint.length_m / 2, ROBOT.footprint.width_m / 2


def _wall_x(x_m: float) -> np.ndarray:
    y = np.arange(-1.0, 1.0, 0.01)
    return np.stack([np.full_like(y, x_m), y], axis=1)


def _supervisor(**kw) -> SafetySupervisor:
    return SafetySupervisor(SafetySupervisorConfig(**kw), ROBOT)


def test_stops_in_front_of_a_wall() -> None:
    sup = _supervisor()
    wall = _wall_x(HL + 0.25)  # 25 cm ahead of the front bumper
    dec = sup.check(np.zeros(3), np.array([1.0, 0.0]), wall)
    assert dec.stopped and np.all(dec.command_out == 0.0)
    assert dec.min_distance_m < sup.config.stop_distance_m
    assert dec.distance_now_m == pytest.approx(0.25)
    assert sup.stops == 1


def test_lets_through_when_clear_and_when_moving_away() -> None:
    sup = _supervisor()
    wall = _wall_x(HL + 0.25)
    slow = sup.check(np.zeros(3), np.array([0.1, 0.0]), wall)  # 0.1 m/s: stops well short
    assert not slow.stopped and not slow.slowed
    np.testing.assert_array_equal(slow.command_out, [0.1, 0.0])
    away = sup.check(np.zeros(3), np.array([-0.3, 0.0]), wall)
    assert not away.stopped
    np.testing.assert_array_equal(away.command_out, [-0.3, 0.0])
    # Already inside the stop zone (touching the wall): backing off is allowed.
    touching = _wall_x(HL + 0.005)
    back = sup.check(np.zeros(3), np.array([-0.2, 0.0]), touching)
    assert not back.stopped and back.distance_now_m == pytest.approx(0.005)
    nothing = sup.check(np.zeros(3), np.array([1.0, 0.5]), np.zeros((0, 2)))
    assert not nothing.stopped and nothing.reason == "clear"


def test_slow_down_zone_scales_the_command() -> None:
    sup = _supervisor(lookahead_s=0.2, stop_distance_m=0.01, slow_distance_m=0.2)
    v = 0.4
    travel = v * 0.2 + v * v / (2 * ROBOT.limits.max_linear_accel_mps2)  # held, then braking
    wall = _wall_x(HL + travel + 0.08)  # swept footprint ends 8 cm short: inside the slow zone
    dec = sup.check(np.zeros(3), np.array([v, 0.0]), wall)
    assert dec.slowed and not dec.stopped
    assert 0.0 < dec.command_out[0] < v
    assert dec.min_distance_m == pytest.approx(0.08, abs=0.02)


def test_rotation_swinging_a_corner_into_a_wall_is_stopped() -> None:
    sup = _supervisor()
    wall = np.stack([np.arange(-1, 1, 0.01), np.full(200, HW + 0.01)], axis=1)  # 1 cm to the left
    dec = sup.check(np.zeros(3), np.array([0.0, 2.0]), wall)
    assert dec.stopped
    along = sup.check(np.zeros(3), np.array([0.5, 0.0]), wall)  # parallel: distance stays 1 cm
    assert not along.stopped


def test_bad_input_raises_named_errors() -> None:
    sup = _supervisor()
    with pytest.raises(PlannerInputError, match="command"):
        sup.check(np.zeros(3), np.array([np.nan, 0.0]), np.zeros((0, 2)))
    with pytest.raises(PlannerInputError, match="pose"):
        sup.check(np.zeros(2), np.zeros(2), np.zeros((0, 2)))
    with pytest.raises(PlannerInputError, match="points"):
        sup.check(np.zeros(3), np.zeros(2), np.array([[np.inf, 0.0]]))


@settings(max_examples=200, deadline=None)
@given(st.floats(-1.0, 1.0), st.floats(-1.0, 1.0))
def test_rectangle_signed_distance_matches_a_dense_boundary(px: float, py: float) -> None:
    t = np.linspace(0, 1, 4001)
    edges = [
        np.stack([np.full_like(t, HL), -HW + 2 * HW * t], 1),
        np.stack([np.full_like(t, -HL), -HW + 2 * HW * t], 1),
        np.stack([-HL + 2 * HL * t, np.full_like(t, HW)], 1),
        np.stack([-HL + 2 * HL * t, np.full_like(t, -HW)], 1),
    ]
    boundary = np.concatenate(edges)
    d_boundary = np.hypot(boundary[:, 0] - px, boundary[:, 1] - py).min()
    inside = abs(px) < HL and abs(py) < HW
    expected = -d_boundary if inside else d_boundary
    assert rectangle_signed_distance(np.array([px, py]), HL, HW) == pytest.approx(expected, abs=2e-4)


@pytest.mark.parametrize("v, omega", [(0.6, 0.0), (0.5, 1.2), (-0.3, -0.8), (0.0, 1.5), (0.8, -0.4)])
def test_swept_poses_follow_the_held_then_braking_command(v: float, omega: float) -> None:
    """The swept curve equals a fine Euler integration of: hold (v, omega) for the look-ahead,
    then ramp both to zero at the limiter's deceleration limits; it ends at standstill."""
    sup = _supervisor(lookahead_s=0.2, sample_period_s=0.02)
    pose = np.array([0.3, -0.2, 0.7])
    poses = sup.swept_poses(pose, v, omega)
    a_v, a_w = ROBOT.limits.max_linear_accel_mps2, ROBOT.body_max_angular_accel_radps2
    dt = 1e-5
    t_end = (poses.shape[0] - 1) * 0.02
    s = pose.copy()
    ref = [s.copy()]
    for k in range(int(round(t_end / dt))):
        tb = max(k * dt - 0.2, 0.0)
        vk = np.sign(v) * max(abs(v) - a_v * tb, 0.0)
        wk = np.sign(omega) * max(abs(omega) - a_w * tb, 0.0)
        s = s + dt * np.array([vk * np.cos(s[2]), vk * np.sin(s[2]), wk])
        if (k + 1) % 2000 == 0:
            ref.append(s.copy())
    np.testing.assert_allclose(poses, np.array(ref), atol=2e-4)
    brake = max(abs(v) / a_v, abs(omega) / a_w)
    assert t_end == pytest.approx(0.2 + brake, abs=0.02 + 1e-9)
