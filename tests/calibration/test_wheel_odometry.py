"""Wheel odometry calibration: the fit recovers a known effective track and wheel scale from
synthetic skid-steer runs, refuses runs that cannot determine them, and its values reach the
calibration file and the run-time wheel odometry."""
from __future__ import annotations

import datetime as dt
import math

import numpy as np
import pytest
import yaml

from calibration.calibration_file import load_calibration, make_calibration, save_calibration
from calibration.errors import ConfigFileError
from calibration.robot_description import load_robot_description
from calibration.wheel_odometry import (WheelCalibrationError, fit_wheel_odometry, wheel_params,
                                        window_increments)
from runtime.odometry import WheelOdometry

from .wheel_runs import DEFAULT_SCHEDULE, schedule_speeds, simulate_run

LIMO_TRACK_M = 0.175


def _fit(run, **kw):
    return fit_wheel_odometry(run, geometric_track_m=LIMO_TRACK_M, **kw)


# ---------------------------------------------------------------------------- recovers the truth
@pytest.mark.parametrize("track_m, scale", [(0.525, 0.97), (0.18, 1.0), (0.80, 1.15), (0.35, 0.85)])
def test_noise_free_runs_give_the_exact_values(track_m, scale):
    run = simulate_run(track_m, scale, ref_noise_m=0.0, ref_noise_yaw_rad=0.0, quantum_m=0.0, lateral_slip_m=0.03)
    fit = _fit(run)
    assert fit.wheel_scale == pytest.approx(scale, rel=1e-9)
    assert fit.effective_track_m == pytest.approx(track_m, rel=1e-9)
    assert fit.residual_distance_rms_m < 1e-9 and fit.residual_yaw_rms_rad < 1e-9
    assert fit.yaw_factor == pytest.approx(track_m / LIMO_TRACK_M)


@pytest.mark.parametrize("seed", range(5))
def test_noisy_runs_recover_the_values_within_one_percent(seed):
    """ICP-like reference noise (5 mm, 0.17 deg per pose), millimetre wheel counts, sideways slip."""
    run = simulate_run(0.525, 0.97, seed=seed, lateral_slip_m=0.03)
    fit = _fit(run)
    assert fit.wheel_scale == pytest.approx(0.97, rel=0.01)
    assert fit.effective_track_m == pytest.approx(0.525, rel=0.01)
    # Residuals are the reference noise of a window's two end poses (sqrt(2) x per pose), not model error.
    assert 0.5 * math.sqrt(2) * 0.005 < fit.residual_distance_rms_m < 1.5 * math.sqrt(2) * 0.005
    assert 0.5 * math.sqrt(2) * 0.003 < fit.residual_yaw_rms_rad < 1.5 * math.sqrt(2) * 0.003


def test_noise_averages_out_over_seeds():
    fits = [_fit(simulate_run(0.525, 0.97, seed=s)) for s in range(10, 20)]
    assert np.mean([f.wheel_scale for f in fits]) == pytest.approx(0.97, rel=0.002)
    assert np.mean([f.effective_track_m for f in fits]) == pytest.approx(0.525, rel=0.002)


def test_reversing_only_run_calibrates_the_scale():
    schedule = ((-0.3, 0.0, 4.0), (0.0, 0.6, 3.0), (-0.25, -0.3, 4.0), (0.0, -0.5, 3.0))
    fit = _fit(simulate_run(0.5, 1.05, schedule=schedule, ref_noise_m=0.0, ref_noise_yaw_rad=0.0, quantum_m=0.0))
    assert fit.wheel_scale == pytest.approx(1.05, rel=1e-9) and fit.effective_track_m == pytest.approx(0.5, rel=1e-9)


def test_counts_standstill_windows_and_wrapped_reference_yaw():
    run = simulate_run()
    assert np.abs(np.diff(run.ref_pose[:, 2])).max() > math.pi  # the reference yaw wraps around +-pi
    fit = _fit(run)
    # DEFAULT_SCHEDULE (25.5 s) stops from 11 to 12.5 s: 3 windows of 0.5 s in each of the two stops of 60 s.
    assert (fit.windows_total, fit.windows_used) == (120, 114)
    assert window_increments(run, 0.5)["standstill"].sum() == 6
    v, w = schedule_speeds(DEFAULT_SCHEDULE, 60.0, 0.05)
    assert fit.distance_m == pytest.approx(np.abs(v[:-1]).sum() * 0.05, rel=0.01)
    assert fit.rotation_rad == pytest.approx(np.abs(w[:-1]).sum() * 0.05, rel=0.01)
    longer = _fit(run, window_s=1.0)
    assert longer.windows_total == 60 and longer.effective_track_m == pytest.approx(0.525, rel=0.01)


# ---------------------------------------------------------------------------- refused
def test_a_straight_run_cannot_determine_the_track_even_with_reference_noise():
    run = simulate_run(schedule=((0.4, 0.0, 5.0), (-0.4, 0.0, 5.0)), ref_noise_yaw_rad=0.005)
    with pytest.raises(WheelCalibrationError, match=r"too little motion.* deg of turning \(at least 90 deg\)"):
        _fit(run)


def test_spinning_in_place_cannot_determine_the_scale():
    with pytest.raises(WheelCalibrationError, match=r"too little motion to determine the values: 0\.\d\d m of travel"):
        _fit(simulate_run(schedule=((0.0, 0.6, 5.0), (0.0, -0.6, 5.0))))


def test_a_short_run_is_refused_and_says_how_much_it_had():
    with pytest.raises(WheelCalibrationError, match=r"too little motion to determine the values: 1\.\d\d m of travel \(at least 2\.0 m\).* over 12 moving windows"):
        _fit(simulate_run(duration_s=6.0, schedule=((0.3, 0.5, 6.0),)))


def test_standing_still_is_refused():
    with pytest.raises(WheelCalibrationError, match="the wheels moved in 0 of its 20 windows"):
        _fit(simulate_run(duration_s=10.0, schedule=((0.0, 0.0, 1.0),)))


def test_values_below_the_geometric_track_are_implausible():
    with pytest.raises(WheelCalibrationError, match=r"effective track 0\.120 m is outside \[0\.175, 0\.875\]"):
        _fit(simulate_run(0.12, 1.0, seed=1))


def test_values_beyond_five_times_the_track_are_implausible():
    with pytest.raises(WheelCalibrationError, match=r"effective track 1\.0\d\d m is outside"):
        _fit(simulate_run(1.05, 1.0, seed=1))


def test_an_implausible_scale_is_refused():
    with pytest.raises(WheelCalibrationError, match=r"wheel scale 1\.\d\d\d is outside \[0\.8, 1\.2\]"):
        _fit(simulate_run(0.5, 1.3, seed=1))


def test_swapped_wheels_are_named():
    run = simulate_run()
    swapped = type(run)(**{**run.__dict__, "left_wheel_m": run.right_wheel_m, "right_wheel_m": run.left_wheel_m})
    with pytest.raises(WheelCalibrationError, match="turns against the wheels.*swapped"):
        _fit(swapped)


@pytest.mark.parametrize("kw, fragment", [({"window_s": 0.0}, "window"), ({"window_s": math.nan}, "window"),
                                          ({"geometric_track_m": -0.1}, "geometric track")])
def test_bad_parameters(kw, fragment):
    kw = {"geometric_track_m": LIMO_TRACK_M, **kw}
    with pytest.raises(WheelCalibrationError, match=fragment):
        fit_wheel_odometry(simulate_run(), **kw)


def test_a_window_longer_than_the_run_is_refused():
    with pytest.raises(WheelCalibrationError, match="moved in 0 of its 0 windows"):
        _fit(simulate_run(duration_s=20.0), window_s=30.0)


# ---------------------------------------------------------------------------- the calibration file
def _cal():
    return make_calibration("limo", np.array([[336.0, 0, 319.5], [0, 336.0, 239.5], [0, 0, 1]]), np.zeros(5),
                            640, 480, None, method="test")


def test_the_section_round_trips_through_the_file(tmp_path):
    fit = _fit(simulate_run(0.525, 0.97, seed=3))
    cal = _cal().model_copy(update={"wheel_odometry": fit.calibration_section(dt.datetime(2025, 1, 2, 10, 0))})
    save_calibration(cal, tmp_path / "cal.yaml")
    back = load_calibration(tmp_path / "cal.yaml").wheel_odometry
    assert back.effective_track_m == fit.effective_track_m and back.wheel_scale == fit.wheel_scale
    assert back.fit.reference == "icp" and back.fit.source == "synthetic seed 3" and back.fit.windows == 114
    assert back.fit.rotation_deg == pytest.approx(fit.rotation_deg)
    assert back.fit.residual_yaw_rms_deg == pytest.approx(fit.residual_yaw_rms_deg)
    assert back.fit.date == dt.datetime(2025, 1, 2, 10, 0)


def test_a_file_without_the_section_still_loads(tmp_path):
    save_calibration(_cal(), tmp_path / "cal.yaml")
    assert "wheel_odometry" not in (tmp_path / "cal.yaml").read_text()
    assert load_calibration(tmp_path / "cal.yaml").wheel_odometry is None


GOOD_SECTION = {"effective_track_m": 0.52, "wheel_scale": 0.98,
                "fit": {"reference": "icp", "source": "hall", "windows": 100, "window_s": 0.5, "distance_m": 10.0,
                        "rotation_deg": 600.0, "residual_distance_rms_m": 0.004, "residual_yaw_rms_deg": 0.3,
                        "date": "2025-01-02T10:00:00"}}


@pytest.mark.parametrize("path, value, fragment", [
    (("effective_track_m",), -0.5, "greater than 0"),
    (("effective_track_m",), 175.0, "less than or equal to 15"),
    (("effective_track_m",), ".nan", "finite"),
    (("wheel_scale",), 1.5, "less than or equal to 1.2"),
    (("wheel_scale",), "1.0", "valid number"),
    (("fit", "reference"), "gps", "'ground_truth' or 'icp'"),
    (("fit", "windows"), 0, "greater than or equal to 1"),
    (("fit", "residual_yaw_rms_deg"), -1.0, "greater than or equal to 0"),
    (("fit", "date"), "yesterday", "datetime"),
    (("fit", "extra"), 1, "Extra inputs"),
    (("fit",), None, "fit"),
])
def test_bad_sections_name_the_field(tmp_path, path, value, fragment):
    data = yaml.safe_load(yaml.safe_dump(_cal().model_dump(mode="json", exclude_none=True)))
    section = yaml.safe_load(yaml.safe_dump(GOOD_SECTION))
    target = section
    for key in path[:-1]:
        target = target[key]
    if value is None:
        del target[path[-1]]
    else:
        target[path[-1]] = value
    data["wheel_odometry"] = section
    text = yaml.safe_dump(data).replace("'.nan'", ".nan")
    (tmp_path / "cal.yaml").write_text(text)
    with pytest.raises(ConfigFileError) as exc:
        load_calibration(tmp_path / "cal.yaml")
    msg = str(exc.value)
    assert f"wheel_odometry.{'.'.join(path)}" in msg and fragment in msg and "\n" not in msg, msg


# ---------------------------------------------------------------------------- at run time
def test_wheel_params_prefer_the_calibration_file():
    limo = load_robot_description()
    track, scale, source = wheel_params(limo, None)
    assert (track, scale) == (pytest.approx(0.525), 1.0) and "skid_steer_yaw_factor 3.0" in source
    assert wheel_params(limo, _cal()).effective_track_m == pytest.approx(0.525)
    cal = _cal().model_copy(update={"wheel_odometry": _fit(simulate_run(0.56, 0.95)).calibration_section()})
    params = wheel_params(limo, cal)
    assert params.effective_track_m == pytest.approx(0.56, rel=0.01) and params.wheel_scale == pytest.approx(0.95, rel=0.01)
    assert "against icp (synthetic seed 0)" in params.source


def test_wheel_params_refuse_a_track_that_does_not_fit_the_robot():
    from calibration.calibration_file import WheelOdometryCalibration

    section = WheelOdometryCalibration.model_validate({**GOOD_SECTION, "effective_track_m": 2.0})
    cal = _cal().model_copy(update={"wheel_odometry": section})
    with pytest.raises(ConfigFileError, match=r"effective_track_m 2.0 m is outside \[0.175, 0.875\]"):
        wheel_params(load_robot_description(), cal)


def _dead_reckon(run, track_m: float, scale: float) -> np.ndarray:
    odo = WheelOdometry(track_m, wheel_scale=scale)
    start = run.ref_pose[0]
    for left, right in zip(run.left_wheel_m, run.right_wheel_m):
        pose = odo.update(left, right)
    c, s = math.cos(start[2]), math.sin(start[2])
    return np.array([start[0] + c * pose.x_m - s * pose.y_m, start[1] + s * pose.x_m + c * pose.y_m])


def test_fitted_values_make_wheel_odometry_follow_the_reference():
    """Truth 0.56 m / 0.95: the description's nominal 0.525 m / 1.0 drifts, the fitted values do not."""
    calibration_run = simulate_run(0.56, 0.95, seed=4)
    params = wheel_params(load_robot_description(), _cal().model_copy(
        update={"wheel_odometry": _fit(calibration_run).calibration_section()}))
    test_run = simulate_run(0.56, 0.95, seed=5, ref_noise_m=0.0, ref_noise_yaw_rad=0.0, quantum_m=0.0, duration_s=30.0)
    end = test_run.ref_pose[-1, :2]
    nominal_err = np.linalg.norm(_dead_reckon(test_run, 0.525, 1.0) - end)
    fitted_err = np.linalg.norm(_dead_reckon(test_run, params.effective_track_m, params.wheel_scale) - end)
    assert nominal_err > 0.15 and fitted_err < 0.03, (nominal_err, fitted_err)


def test_wheel_scale_multiplies_the_wheel_distances():
    odo = WheelOdometry(0.5, wheel_scale=0.9)
    odo.update(0.0, 0.0)
    pose = odo.update(1.0, 1.0)
    assert (pose.x_m, odo.distance_travelled_m) == (pytest.approx(0.9), pytest.approx(0.9))
    pose = odo.update(1.0, 1.5)  # 0.5 m of difference x 0.9 over a 0.5 m track
    assert pose.yaw_rad == pytest.approx(0.9)
    with pytest.raises(ValueError, match="wheel scale"):
        WheelOdometry(0.5, wheel_scale=0.0)
    assert WheelOdometry(0.175, 3.0).wheel_scale == 1.0


def test_wheel_gyro_odometry_scales_the_distance_and_takes_yaw_from_the_gyro():
    from runtime.odometry import WheelGyroOdometry
    from runtime.common.sensor_data import ImuSample

    odo = WheelGyroOdometry(0.175, 3.0, wheel_scale=1.1)
    imu = [ImuSample(stamp_s=0.01 * i, accel_mps2=(0.0, 0.0, 9.81), gyro_radps=(0.0, 0.0, 0.0)) for i in range(3)]
    odo.update_with_imu((0.0, 0.0), imu[:1])
    pose = odo.update_with_imu((1.0, 1.2), imu[1:])  # the wheels disagree, the gyro says straight
    assert (pose.x_m, pose.y_m, pose.yaw_rad) == (pytest.approx(1.21), 0.0, 0.0)


def test_wheel_params_refuse_another_robots_calibration():
    cal = _cal().model_copy(update={"robot": "scout", "wheel_odometry": _fit(simulate_run(0.56, 0.95)).calibration_section()})
    with pytest.raises(ConfigFileError, match="calibration is for robot 'scout'"):
        wheel_params(load_robot_description(), cal)
