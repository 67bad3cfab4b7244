"""Wheel + gyro dead reckoning: a counter that restarts is not motion, a gap the wheels bridge is."""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from runtime.common.sensor_data import ImuSample
from runtime.odometry.wheels import MAX_WHEEL_SPEED_MPS, WheelGyroOdometry


def _imu(t):
    return [ImuSample(t, np.zeros(3), np.array([0.0, 0.0, 9.81]))]


def test_a_wheel_jump_further_than_the_wheels_could_turn_re_anchors_and_a_bridged_gap_counts():
    w = WheelGyroOdometry(0.2)
    w.update_with_imu((10.0, 10.0), _imu(0.0), gap_s=None)
    w.update_with_imu((10.05, 10.05), _imu(0.05), gap_s=0.05)
    assert w.pose.x_m == pytest.approx(0.05)
    # the base rebooted: its odometers start again at zero (a 10 m step in 0.05 s)
    w.update_with_imu((0.0, 0.0), _imu(0.10), gap_s=0.05)
    assert w.pose.x_m == pytest.approx(0.05) and w.jumps == 1
    w.update_with_imu((0.05, 0.05), _imu(0.15), gap_s=0.05)
    assert w.pose.x_m == pytest.approx(0.10)
    # a gap of a second the wheels turned through (a bus-off): 0.8 m is within 2 m/s x 1 s
    w.update_with_imu((0.85, 0.85), _imu(1.15), gap_s=1.0)
    assert w.pose.x_m == pytest.approx(0.90) and w.jumps == 1
    assert 0.8 < MAX_WHEEL_SPEED_MPS * 1.0
    # an explicit re-anchor (the base said it restarted) drops the next step
    w.reanchor()
    w.update_with_imu((0.3, 0.3), _imu(1.2), gap_s=0.05)
    assert w.pose.x_m == pytest.approx(0.90)


def _turning(t0: float, t1: float, rate: float, dt: float = 0.005) -> list[ImuSample]:
    """Gyro samples of a robot turning at `rate` rad/s, stamped every dt in (t0, t1]."""
    return [ImuSample(float(t), np.array([0.0, 0.0, rate]), np.array([0.0, 0.0, 9.81]))
            for t in np.arange(t0 + dt, t1 + 1e-9, dt)]


def _drive(w: WheelGyroOdometry, ticks: list[tuple[float, list[ImuSample]]], rate: float, track: float,
           wheel_yaw_factor: float) -> None:
    """Tick every 50 ms with the wheels turning at `rate` as the gyro sees it, times
    `wheel_yaw_factor` (a skid-steer's wheels say more rotation than there was)."""
    for k, (t, samples) in enumerate(ticks):
        half = 0.5 * rate * wheel_yaw_factor * track * t
        w.update_with_imu((10.0 - half, 10.0 + half), samples, gap_s=0.05 if k else None)


@given(late=st.lists(st.booleans(), min_size=20, max_size=40))
@settings(max_examples=60, deadline=None)
def test_late_gyro_samples_replace_the_wheels_yaw_that_stood_in_for_them(late):
    """Samples held back (a loaded link: none in some ticks, a burst in the next) are a true
    rotation: the yaw over the whole run is the gyro's, not the gyro's plus the wheels' stand-in
    for the ticks that had none."""
    rate, track = 0.5, 0.2
    w = WheelGyroOdometry(track)
    held: list[ImuSample] = []
    ticks = []
    n = len(late)
    for k in range(n + 1):
        t = 0.05 * k
        held += _turning(t - 0.05, t, rate) if k else _turning(-0.005, 0.0, rate)
        if k == n or not late[k]:  # delivered now, or held back to a later tick (the last tick gets all)
            ticks.append((t, held))
            held = []
        else:
            ticks.append((t, []))
    _drive(w, ticks, rate, track, wheel_yaw_factor=1.4)
    assert w.pose.yaw_rad == pytest.approx(rate * 0.05 * n, abs=1e-9)
    assert (w.late_imu_yaw_replaced_rad > 0.0) == any(late[1:])


def test_a_lost_imu_leaves_the_wheels_yaw_over_the_gap():
    """Samples that never come (a gap longer than the gyro integrates) do not take back the
    wheels' yaw: it is all that is known of the rotation then."""
    rate, track = 0.5, 0.2
    w = WheelGyroOdometry(track)
    ticks = [(0.0, _turning(-0.005, 0.0, rate)), (0.05, _turning(0.0, 0.05, rate))]
    ticks += [(0.05 * k, []) for k in range(2, 8)]  # 0.3 s without a sample: lost
    ticks += [(0.40, _turning(0.345, 0.40, rate))]  # they come back; the gap before is not integrated
    _drive(w, ticks, rate, track, wheel_yaw_factor=1.0)
    assert w.pose.yaw_rad == pytest.approx(rate * 0.40, abs=0.01)
    assert w.late_imu_yaw_replaced_rad == 0.0
