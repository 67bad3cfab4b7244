"""Input checks: lidar frames that cannot see, frozen frames, stale streams (unit level)."""
import math

import numpy as np
import pytest

from runtime.io.hardware import BaseInputs
from runtime.safety.input_monitor import InputMonitor, InputsConfig, LidarInputConfig, judge_lidar_frame
from runtime.common.sensor_data import ImuSample, LidarScan
from runtime.io.sensor_inbox import SensorInbox, SensorSnapshot

RNG = np.random.default_rng(0)


def ring_scan(stamp, n=5000, r=2.0, az_range=(-math.pi, math.pi), noise=0.02):
    az = RNG.uniform(*az_range, n)
    rr = r + RNG.normal(0.0, noise, n)
    pts = np.stack([rr * np.cos(az), rr * np.sin(az), np.zeros(n)], axis=1).astype(np.float32)
    return LidarScan(stamp, pts, np.zeros(n, np.float32), 0.1)


def fresh_inputs(now):
    return BaseInputs(now, False, True, True, 0, 0.0, 0.0, (0.0, 0.0))


def test_a_frame_with_enough_returns_in_range_is_good():
    v = judge_lidar_frame(ring_scan(0.0), LidarInputConfig(), planner_range_m=6.0)
    assert v.ok and v.returns_in_range == 5000


@pytest.mark.parametrize("n, r, words", [
    (900, 2.0, "900 of 20000 rays returned within 6 m"),  # fewer than 5 % of the rays
    (5000, 9.0, "5000 beyond it"),  # all beyond the planner's range
    (5000, 0.05, "0 of 20000"),  # all inside the sensor's minimum range (its own housing)
])
def test_frames_that_see_too_little_in_range_are_blind(n, r, words):
    v = judge_lidar_frame(ring_scan(0.0, n=n, r=r, noise=0.0), LidarInputConfig(), planner_range_m=6.0)
    assert not v.ok and v.reason.startswith("lidar blind") and words in v.reason


def test_sector_check_catches_a_half_covered_sensor_when_enabled():
    half = ring_scan(0.0, az_range=(0.0, math.pi))
    assert judge_lidar_frame(half, LidarInputConfig(), 6.0).ok  # off by default
    cfg = LidarInputConfig(min_sector_return_fraction=0.02)
    v = judge_lidar_frame(half, cfg, 6.0)
    assert not v.ok and "azimuth -180..-135 deg" in v.reason and "0..45" not in v.reason


def test_inbox_rejects_a_repeated_frame_with_or_without_a_new_stamp():
    inbox = SensorInbox()
    a = ring_scan(1.0)
    assert inbox.put_scan(a)
    assert not inbox.put_scan(a)  # the same frame again, stamp included
    same_points = LidarScan(1.1, a.points_m, a.point_time_offsets_s, 0.1)
    assert not inbox.put_scan(same_points)  # new stamp, identical points
    assert inbox.put_scan(ring_scan(1.2))  # a live frame (noise differs)
    snap = inbox.take()
    assert [r.name for r in snap.rejected] == ["frozen_frame", "frozen_frame"]
    assert "and its stamp" in snap.rejected[0].message and "and its stamp" not in snap.rejected[1].message
    assert inbox.error_counts == {"lidar.frozen_frame": 2}
    assert inbox.take().rejected == ()  # handed over once


def test_frames_without_any_return_are_blind_not_frozen():
    """A Livox reports a ray with no return as a point at (0, 0, 0): a sensor that sees nothing
    sends frames of such points, alike from frame to frame. They are blind, not a repeated buffer."""
    from hil_sim.episode.serve import no_return_frame

    mon = InputMonitor(InputsConfig(), planner_range_m=6.0, uses_lidar=True, uses_imu=False)
    inbox = SensorInbox()
    inbox.put_scan(ring_scan(0.0))
    assert mon.check(fresh_inputs(0.1), inbox.take(), 0.1) == ()
    for k in (1, 2, 3):
        empty = LidarScan(0.1 * k, np.zeros((0, 3), np.float32), np.zeros(0, np.float32), 0.1, nothing_seen=True)
        frame = no_return_frame(empty, 20_000)
        assert frame.num_points == 20_000 and not frame.points_m.any()
        assert inbox.put_scan(frame)
        faults = mon.check(fresh_inputs(0.1 * k + 0.12), inbox.take(), 0.1 * k + 0.12)
        assert [f.reason for f in faults] == ["lidar blind: 0 of 20000 rays returned within 6 m (minimum 5%)"]
    assert inbox.error_counts == {}


def test_monitor_names_frozen_then_stale_then_resumes_on_a_good_frame():
    mon = InputMonitor(InputsConfig(), planner_range_m=6.0, uses_lidar=True, uses_imu=False)
    inbox = SensorInbox()
    a = ring_scan(0.0)
    inbox.put_scan(a)
    assert mon.check(fresh_inputs(0.1), inbox.take(), 0.1) == ()
    inbox.put_scan(a)  # frozen
    faults = mon.check(fresh_inputs(0.2), inbox.take(), 0.2)
    assert [f.stream for f in faults] == ["lidar"] and faults[0].reason.startswith("lidar frozen")
    faults = mon.check(fresh_inputs(0.3), SensorSnapshot(None, None, ()), 0.3)
    assert faults and faults[0].reason.startswith("lidar frozen")  # until a good frame arrives
    inbox.put_scan(ring_scan(0.3))
    faults = mon.check(fresh_inputs(0.4), inbox.take(), 0.4)
    assert faults and faults[0].reason.startswith("lidar frozen")  # one good frame is not enough
    inbox.put_scan(ring_scan(0.4))
    assert mon.check(fresh_inputs(0.5), inbox.take(), 0.5) == ()  # the second in a row is
    # No frame at all: stale after max_age_frames (3) periods after the newest frame's end (0.5 s).
    assert mon.check(fresh_inputs(0.79), SensorSnapshot(None, None, ()), 0.79) == ()
    faults = mon.check(fresh_inputs(0.81), SensorSnapshot(None, None, ()), 0.81)
    assert faults and faults[0].reason.startswith("lidar stale")


def test_a_frame_or_sample_stamped_in_the_future_never_counts_as_fresh():
    """One frame stamped 30 s ahead must not switch the staleness watchdog off for 30 s."""
    mon = InputMonitor(InputsConfig(), planner_range_m=6.0, uses_lidar=True, uses_imu=True)
    inbox = SensorInbox()
    imu = ImuSample(0.095, np.zeros(3), np.array([0, 0, 9.81]))
    inbox.put_scan(ring_scan(0.0))
    inbox.put_imu(imu)
    assert mon.check(fresh_inputs(0.1), inbox.take(), 0.1) == ()
    inbox.put_scan(ring_scan(0.1))
    inbox.put_imu(ImuSample(0.195, np.zeros(3), np.array([0, 0, 9.81])))
    assert mon.check(fresh_inputs(0.2), inbox.take(), 0.2) == ()
    inbox.put_scan(ring_scan(30.0))
    inbox.put_imu(ImuSample(30.0, np.zeros(3), np.array([0, 0, 9.81])))
    faults = {f.stream: f.reason for f in mon.check(fresh_inputs(0.21), inbox.take(), 0.21)}
    assert "in the future" in faults["lidar"] and "in the future" in faults["imu"]
    later = {f.stream: f.reason for f in mon.check(fresh_inputs(0.6), SensorSnapshot(None, None, ()), 0.6)}
    assert "lidar" in later and "IMU stale" in later["imu"]


def test_a_frame_that_arrives_too_old_is_stale():
    mon = InputMonitor(InputsConfig(), planner_range_m=6.0, uses_lidar=True, uses_imu=False)
    inbox = SensorInbox()
    inbox.put_scan(ring_scan(0.0))
    (f,) = mon.check(fresh_inputs(1.0), inbox.take(), 1.0)
    assert f.reason.startswith("lidar stale (a frame arrived 0.90 s after its end")


def test_a_lidar_blind_every_other_frame_keeps_the_robot_stopped():
    mon = InputMonitor(InputsConfig(), planner_range_m=6.0, uses_lidar=True, uses_imu=False)
    verdicts = []
    for k in range(10):
        t = 0.1 * k
        scan = ring_scan(t) if k % 2 == 0 else ring_scan(t, n=10, noise=0.0)
        verdicts.append(mon.check(fresh_inputs(t + 0.1), SensorSnapshot(scan, None, ()), t + 0.1) == ())
    assert verdicts[0] and not any(verdicts[1:])


def test_monitor_never_treats_never_received_as_fresh():
    mon = InputMonitor(InputsConfig(), planner_range_m=6.0, uses_lidar=True, uses_imu=True)
    inputs = BaseInputs(0.0, True, False, False, 0, 0.0, 0.0, None, math.inf, math.inf, math.inf, None)
    faults = mon.check(inputs, SensorSnapshot(None, None, ()), 0.0)
    reasons = " | ".join(f.reason for f in faults)
    for words in ("0x221 stale (never received", "0x311 stale", "0x211 stale", "IMU stale (no sample yet",
                  "lidar stale (no good frame yet"):
        assert words in reasons


def test_imu_staleness_and_saturation():
    mon = InputMonitor(InputsConfig(), planner_range_m=6.0, uses_lidar=False, uses_imu=True)
    s = ImuSample(1.0, np.zeros(3), np.array([0, 0, 9.81]))
    assert mon.check(fresh_inputs(1.0), SensorSnapshot(None, None, (s,)), 1.0) == ()
    assert mon.check(fresh_inputs(1.04), SensorSnapshot(None, None, ()), 1.04) == ()
    faults = mon.check(fresh_inputs(1.06), SensorSnapshot(None, None, ()), 1.06)
    assert faults[0].reason.startswith("IMU stale (no sample for 0.060 s")
    sat = ImuSample(1.07, np.array([0.0, 0.0, 30.0]), np.zeros(3), saturated=True)
    good = ImuSample(1.075, np.zeros(3), np.array([0, 0, 9.81]))
    faults = mon.check(fresh_inputs(1.08), SensorSnapshot(None, None, (sat, good)), 1.08)
    assert [f.reason for f in faults] == ["IMU saturated"]  # not hidden by a later good sample
    from runtime.io.sensor_inbox import Rejection

    rej = Rejection("imu", "non_finite", "[non_finite] gyro_radps: non-finite value", 1.085)
    later = ImuSample(1.09, np.zeros(3), np.array([0, 0, 9.81]))
    faults = mon.check(fresh_inputs(1.1), SensorSnapshot(None, None, (later,), (rej,)), 1.1)
    assert faults[0].reason.startswith("IMU sample rejected")
    assert mon.check(fresh_inputs(1.15), SensorSnapshot(None, None, (ImuSample(1.14, np.zeros(3), np.zeros(3)),)),
                     1.15) == ()


def test_base_state_faults_need_a_restart():
    mon = InputMonitor(InputsConfig(), planner_range_m=6.0, uses_lidar=False, uses_imu=False)
    estop = BaseInputs(0.0, False, True, True, 0, 0.0, 0.0, (0.0, 0.0), vehicle_state=1)
    (f,) = mon.check(estop, SensorSnapshot(None, None, ()), 0.0)
    assert f.reason == "E-stop" and f.restart and f.blocks_restart
    lost = BaseInputs(0.0, False, True, True, 0x0200, 0.0, 0.0, (0.0, 0.0))
    (f,) = mon.check(lost, SensorSnapshot(None, None, ()), 0.0)
    assert f.restart and not f.blocks_restart


def _imu(t, rng=None):
    """A live IMU sample at rest: noise in every component (none: the very same values)."""
    noise = rng.normal(0.0, 1e-3, 6) if rng is not None else np.zeros(6)
    return ImuSample(t, noise[:3], np.array([0.0, 0.0, 9.81]) + noise[3:])


def test_a_stuck_imu_is_named_after_its_limit_and_holds_until_a_sample_differs():
    mon = InputMonitor(InputsConfig(), planner_range_m=6.0, uses_lidar=False, uses_imu=True)
    rng = np.random.default_rng(1)
    t = 1.0
    for _ in range(20):  # live samples: never stuck, however many
        samples = tuple(_imu(t + 0.005 * k, rng) for k in range(10))
        t += 0.05
        assert mon.check(fresh_inputs(t), SensorSnapshot(None, None, samples), t) == ()
    stuck = _imu(t)
    seen = []
    for _ in range(4):  # 10 identical samples a tick
        samples = tuple(ImuSample(t + 0.005 * k, stuck.gyro_radps, stuck.accel_mps2) for k in range(10))
        t += 0.05
        seen.append([f.reason for f in mon.check(fresh_inputs(t), SensorSnapshot(None, None, samples), t)])
    assert seen[0] == [] and seen[1][0].startswith("IMU stuck (20 samples in a row") and seen[3][0].startswith(
        "IMU stuck (40 samples")
    t += 0.05
    assert mon.check(fresh_inputs(t), SensorSnapshot(None, None, (_imu(t - 0.01, rng),)), t) == ()
    off = InputMonitor(InputsConfig(imu_stuck_samples=0), planner_range_m=6.0, uses_lidar=False, uses_imu=True)
    same = tuple(ImuSample(2.0 + 0.005 * k, stuck.gyro_radps, stuck.accel_mps2) for k in range(30))
    assert off.check(fresh_inputs(2.15), SensorSnapshot(None, None, same), 2.15) == ()


def _base(now, odometry, speed):
    return BaseInputs(now, False, True, True, 0, speed, 0.0, odometry)


def test_wheel_distances_that_stop_while_the_base_reports_motion_are_a_stuck_0x311():
    mon = InputMonitor(InputsConfig(), planner_range_m=6.0, uses_lidar=False, uses_imu=False)
    no_sensors = SensorSnapshot(None, None, ())
    d, t = 0.0, 0.0
    for _ in range(10):  # driving at 0.5 m/s: the distances move every tick
        t += 0.05
        d += 0.025
        assert mon.check(_base(t, (d, d), 0.5), no_sensors, t) == ()
    reasons = []
    for _ in range(8):  # 0x311 stuck: 0x221 still says 0.5 m/s
        t += 0.05
        reasons.append([f.reason for f in mon.check(_base(t, (d, d), 0.5), no_sensors, t)])
    # 0.25 s after the distances last changed, the speed accounting for 125 mm of travel
    assert reasons[:4] == [[]] * 4 and reasons[4][0].startswith("0x311 stuck (wheel distances unchanged for 0.25 s")
    t += 0.05  # stopped by the controller: still stuck (the distances have not changed)
    assert mon.check(_base(t, (d, d), 0.0), no_sensors, t)[0].reason.startswith("0x311 stuck")
    t += 0.05
    assert mon.check(_base(t, (d + 0.1, d + 0.1), 0.0), no_sensors, t) == ()  # they move again
    for _ in range(20):  # standing still: unchanged distances are right
        t += 0.05
        assert mon.check(_base(t, (d + 0.1, d + 0.1), 0.0), no_sensors, t) == ()
    # creeping stop-and-go in a tight gap (0.06 and 0.003 m/s on alternate ticks): the wheels turn,
    # the distances must follow; stuck once the speed accounts for 12.5 mm (about 0.4 s here)
    creeping = []
    for k in range(16):
        t += 0.05
        creeping.append(bool(mon.check(_base(t, (d + 0.1, d + 0.1), 0.06 if k % 2 == 0 else 0.003), no_sensors, t)))
    assert creeping.index(True) in range(6, 10) and all(creeping[creeping.index(True):])


def test_a_silent_0x311_is_stale_not_stuck():
    """0x311 silent while 0x221 still reports motion: the last distances do not change, but they
    are old, not frozen. The stop says stale; when fresh frames return with the robot stopped
    (the same distances), nothing is stuck: the robot drives again."""
    from dataclasses import replace

    mon = InputMonitor(InputsConfig(), planner_range_m=6.0, uses_lidar=False, uses_imu=False)
    no_sensors = SensorSnapshot(None, None, ())
    d, t = 0.0, 0.0
    for _ in range(10):
        t += 0.05
        d += 0.025
        assert mon.check(_base(t, (d, d), 0.5), no_sensors, t) == ()
    last = t
    for _ in range(8):  # silent: the last frame ages while the base still says 0.5 m/s
        t += 0.05
        faults = mon.check(replace(_base(t, (d, d), 0.5), odometry_age_s=t - last), no_sensors, t)
        assert all("stuck" not in f.reason for f in faults)
    assert any(f.reason.startswith("0x311 stale") for f in faults)
    for _ in range(10):  # back, the robot stopped meanwhile
        t += 0.05
        assert mon.check(_base(t, (d, d), 0.0), no_sensors, t) == ()


def test_a_base_back_in_standby_after_its_feedback_stopped_has_rebooted_and_needs_a_restart():
    from firmware_bridge import protocol

    mon = InputMonitor(InputsConfig(), planner_range_m=6.0, uses_lidar=False, uses_imu=False)
    none = SensorSnapshot(None, None, ())
    assert mon.check(fresh_inputs(0.0), none, 0.0) == () and not mon.base_rebooted
    silent = BaseInputs(1.0, True, True, True, 0, 0.0, 0.0, None, 0.5, 0.5, 0.5)
    assert {f.stream for f in mon.check(silent, none, 1.0)} == {"0x221", "0x311", "0x211"}
    standby = [BaseInputs(t, False, True, False, 0, 0.0, 0.0, (0.0, 0.0), control_mode=protocol.CONTROL_MODE_STANDBY)
               for t in (1.1, 1.15, 7.0)]
    (f,) = mon.check(standby[0], none, 1.1)
    assert f.reason.startswith("base restarted") and f.restart and not f.blocks_restart
    assert mon.base_rebooted and mon.base_rebooted_now  # the first tick back: the odometers restarted
    mon.check(standby[1], none, 1.15)
    assert mon.base_rebooted and not mon.base_rebooted_now
    # long after the silence, standby is not a reboot (someone switched it: a latched stop, not a restart)
    assert mon.check(standby[2], none, 7.0) == () and not mon.base_rebooted
    # standby while it kept talking is never a reboot
    talking = InputMonitor(InputsConfig(), planner_range_m=6.0, uses_lidar=False, uses_imu=False)
    assert talking.check(standby[0], none, 1.1) == () and not talking.base_rebooted
