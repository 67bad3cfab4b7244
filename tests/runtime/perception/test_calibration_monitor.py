"""The calibration check's cadence: the floor needs fits in a row (one good fit starts the count
again), a busy slack delays it, a mismatch is said once and kept."""
from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np

from calibration.robot_description import load_robot_description
from calibration.sensor_calibration import nominal_sensors
from runtime.perception.calibration_monitor import CalibrationCheckConfig, CalibrationMonitor

SENSORS = nominal_sensors(load_robot_description())  # lidar 0.2 m up, level


def scan(tilt_deg: float, seed: int = 0):
    """A level floor seen by the nominal lidar, the lidar pitched by tilt_deg (what the nominal
    mount then gets wrong)."""
    rng = np.random.default_rng(seed)
    n = 4000
    az, d = rng.uniform(-math.pi, math.pi, n), rng.uniform(1.7, 3.5, n)
    p = np.column_stack([d * np.cos(az), d * np.sin(az), np.full(n, -0.2)])
    c, s = math.cos(math.radians(tilt_deg)), math.sin(math.radians(tilt_deg))
    R = np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])  # lidar frame seen from a pitched lidar
    return SimpleNamespace(points_m=(p @ R).astype(np.float32))


def test_fits_in_a_row_make_a_mismatch_and_a_good_fit_starts_the_count_again():
    mon = CalibrationMonitor(CalibrationCheckConfig(floor_confirmations=3), SENSORS)
    said = []
    for t, tilt in enumerate([3.0, 3.0, 0.0, 3.0, 3.0, 3.0, 3.0]):
        mon.observe(None, scan(tilt, seed=t))
        said.append(mon.slack(float(t))[0])
    assert said[:5] == [None] * 5 and said[6] is None  # said once, at the third fit in a row
    assert said[5].startswith("lidar mount: robot description 'limo' sensors.lidar.mount (nominal): the floor seen "
                              "through it is tilted 3.0 deg") and said[5].endswith("(3 fits in a row)")
    assert mon.mismatch == said[5] and mon.mismatch_at_s == 5.0 and mon.floor_fits == 7


def test_a_busy_slack_delays_the_floor_fit_by_at_most_a_period():
    mon = CalibrationMonitor(CalibrationCheckConfig(floor_check_period_s=1.0), SENSORS)
    mon.observe(None, scan(0.0))
    assert mon.slack(0.0, busy=True)[1] and mon.floor_fits == 1  # the first one runs
    for t in (1.0, 1.5, 1.95):
        mon.observe(None, scan(0.0))
        assert mon.slack(t, busy=True) == (None, False)
    mon.observe(None, scan(0.0))
    assert mon.slack(2.0, busy=True)[1] and mon.floor_fits == 2  # a whole period overdue: runs anyway
    assert mon.describe()["floor_last"]["tilt_deg"] < 0.1
