"""The gyro bias learnt online from ICP's rotation: a step is found and given back to the
heading, ICP's jitter and one bad block are not steps, a slow drift is followed."""
from __future__ import annotations

import math

import numpy as np
import pytest

from runtime.odometry.fusion import FusionConfig, PoseFusion
from runtime.odometry.gyro_bias import GyroBiasConfig, GyroBiasEstimator

from tests.runtime.odometry.test_fusion import _result, _room_constraint

DT = 0.1  # one ICP frame
ON = GyroBiasConfig(enabled=True)


def _frames(bias_at, seconds, rng, jitter_rad=0.005, turn_radps=0.3, start_s=0.0):
    """(t, raw gyro rotation, ICP rotation) per frame: the robot turns at turn_radps, the gyro
    adds bias_at(t), ICP's heading jitters (independently per frame: its increments are
    anti-correlated, as KISS-ICP's are)."""
    out, err_prev = [], rng.normal(0.0, jitter_rad)
    for k in range(int(round(seconds / DT))):
        t = start_s + (k + 1) * DT
        err = rng.normal(0.0, jitter_rad)
        out.append((t, (turn_radps + bias_at(t - 0.5 * DT)) * DT, turn_radps * DT + err - err_prev))
        err_prev = err
    return out


def _feed(est, frames):
    """Feeds the frames; returns the steps found (time, new bias) and the rotation given back to
    ICP over all blocks."""
    steps, given_back = [], 0.0
    for t, g, icp in frames:
        n = est.stats.steps
        back = est.add_frame(t, g, icp, DT, DT)
        given_back += back or 0.0
        if est.stats.steps != n:
            steps.append(est.last_step)
    return steps, given_back


@pytest.mark.parametrize("seed,bias", [(0, 0.0), (1, 0.004), (2, -0.011), (3, 0.02), (4, -0.02)])
def test_icp_jitter_alone_is_no_step_and_the_bias_is_learnt(seed, bias):
    # Fixed seeds: with the gate at 3 sigma, two agreeing blocks beyond it happen by chance about
    # once in 300,000 pairs (Gaussian jitter), so a random draw would make this test flaky.
    est = GyroBiasEstimator(ON)
    steps, _ = _feed(est, _frames(lambda t: bias, 600.0, np.random.default_rng(seed)))
    assert steps == []
    assert abs(est.bias_radps - bias) < 0.003, est.describe()


def test_a_bias_step_is_found_within_two_blocks_and_its_heading_given_back():
    est = GyroBiasEstimator(ON)
    steps, _ = _feed(est, _frames(lambda t: 0.1 if 10.0 <= t < 20.0 else 0.0, 15.0, np.random.default_rng(3)))
    ((t_on, bias_on),) = steps
    assert 10.0 < t_on <= 11.05 and abs(bias_on - 0.1) < 0.02, steps
    # the two blocks before the step was sure: the gyro's extra rotation went back to ICP
    on_blocks = GyroBiasEstimator(ON)
    _feed(on_blocks, _frames(lambda t: 0.0, 10.0, np.random.default_rng(3)))
    _, back = _feed(on_blocks, _frames(lambda t: 0.1, 1.0, np.random.default_rng(4), start_s=10.0))
    assert abs(back - 0.1) < 0.02, back
    steps, _ = _feed(est, _frames(lambda t: 0.1 if t < 20.0 else 0.0, 15.0, np.random.default_rng(5), start_s=15.0))
    ((t_off, bias_off),) = steps
    assert 20.0 < t_off <= 21.05 and abs(bias_off) < 0.02 and est.stats.steps == 2, steps


def test_one_bad_block_is_suspect_not_a_step():
    est = GyroBiasEstimator(ON)
    frames = _frames(lambda t: 0.0, 20.0, np.random.default_rng(4))
    frames[52] = (frames[52][0], frames[52][1], frames[52][2] + 0.05)  # ICP off by 3 degrees once
    steps, _ = _feed(est, frames)
    assert steps == [] and est.stats.suspect >= 1 and abs(est.bias_radps) < 0.003


def test_a_slow_drift_is_followed_without_steps():
    est = GyroBiasEstimator(ON)
    steps, _ = _feed(est, _frames(lambda t: 0.015 * min(t / 120.0, 1.0), 300.0, np.random.default_rng(5)))
    assert steps == [] and abs(est.bias_radps - 0.015) < 0.004, est.describe()


def test_frames_the_gyro_did_not_cover_break_the_block():
    est = GyroBiasEstimator(ON)
    for k in range(20):
        est.add_frame(0.1 * k, 0.05, 0.0, DT, 0.02)  # the IMU was silent for most of each frame
    assert est.stats.observations == 0 and est.stats.skipped == 20 and est.bias_radps == 0.0


def test_disabled_the_bias_stays_at_the_calibration():
    est = GyroBiasEstimator(GyroBiasConfig(enabled=False), bias_radps=0.004)
    _feed(est, _frames(lambda t: 0.1, 10.0, np.random.default_rng(6)))
    assert est.bias_radps == 0.004 and est.stats.observations == 0


def _drive_with_biased_gyro(config: FusionConfig, seconds=20.0):
    """Drive in a room at 0.3 m/s turning at 0.1 rad/s; from t = 5 s the gyro reads 0.1 rad/s too
    much. ICP (with jitter) measures the truth. The dead reckoning applies the fusion's bias, as
    the odometry stage does. Returns the fused heading's error at the end."""
    rng = np.random.default_rng(7)
    f = PoseFusion(config)
    d, truth_yaw, raw_int, covered = np.zeros(3), 0.0, 0.0, 0.0
    f.add_dead_reckoning(0.0, d.copy(), gyro=(0.0, 0.0))
    f.icp_update(_result(0, None, 0.0, None, _room_constraint()))
    err_prev = 0.0
    for k in range(1, int(seconds / DT) + 1):
        t = k * DT
        raw = (0.1 + (0.1 if t > 5.0 else 0.0)) * DT
        raw_int, covered = raw_int + raw, covered + DT
        d = np.array([d[0] + 0.03 * math.cos(d[2]), d[1] + 0.03 * math.sin(d[2]),
                      d[2] + raw - f.gyro_bias.bias_radps * DT])
        truth_yaw += 0.1 * DT
        f.add_dead_reckoning(t, d.copy(), gyro=(raw_int, covered))
        err = rng.normal(0.0, 0.003)
        assert f.icp_update(_result(k, t - DT, t, [0.03, 0.0, 0.1 * DT + err - err_prev], _room_constraint())) is None
        err_prev = err
    pose, _ = f.pose_now(d, seconds)
    return abs(math.remainder(pose[2] - truth_yaw, math.tau)), f


def test_with_the_estimate_a_bias_step_costs_the_heading_little():
    off, _ = _drive_with_biased_gyro(FusionConfig(gyro_bias=GyroBiasConfig(enabled=False)))
    on, f = _drive_with_biased_gyro(FusionConfig(gyro_bias=ON))
    assert off > 0.5  # 15 s of 0.1 rad/s, the gyro leading: most of 1.5 rad
    # the step's second is given back; what stays is the estimate's own error (a few mrad/s)
    # integrated over the 14 s after it
    assert on < 0.06 and f.gyro_bias.stats.steps == 1, (on, f.gyro_bias.describe())
