"""Wheel + gyro dead reckoning: a counter that restarts is not motion, a gap the wheels bridge is."""
from __future__ import annotations

import numpy as np
import pytest

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
