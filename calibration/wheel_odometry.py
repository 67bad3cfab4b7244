"""Wheel odometry calibration: the effective track width and the wheel scale, fitted to a recorded run.

A four-wheel skid-steer base (the LIMO) slips sideways whenever it turns, so the difference of its
wheel distances overstates the turn: the track that turns wheel distances into yaw is much wider
than the 0.175 m between the wheels (about 3x on the HIL LIMO). Wheel radius and tyre wear make
the distances themselves a little off. The model, with measured wheel distance increments dL, dR::

    distance = s * (dL + dR) / 2          s: wheel_scale
    yaw      = s * (dR - dL) / b          b: effective_track_m

The run (runtime.odometry.run_log, read here through its fields only: calibration must not import
runtime) is cut into windows of `window_s`; each window where the wheels moved gives one equation
per line above, with the reference's motion on the left. Two linear least-squares fits with one
unknown each: s from the distances, k = s / b from the yaws, then b = s / k.

The reference distance of a window is its signed arc length: the reference displacement along the
window's mean heading, divided by sinc(dyaw / 2) (a chord of a constant-curvature arc is shorter
than the arc). The sign says forward or reverse, so reversing calibrates too; sideways slip
(perpendicular to the heading) is not wheel distance and is left out.

Refused (WheelCalibrationError): a run with less than MIN_DISTANCE_M of travel or MIN_ROTATION_DEG
of total turning (the values are not determined), and fitted values outside the plausible ranges
(track in [geometric, MAX_TRACK_FACTOR x geometric]: slip only widens it; scale in SCALE_RANGE).
"""
from __future__ import annotations

import datetime as _dt
import math
from dataclasses import dataclass
from typing import NamedTuple, Protocol

import numpy as np

from calibration.calibration_file import WHEEL_SCALE_RANGE, CalibrationFile, WheelOdometryCalibration
from calibration.errors import ConfigFileError
from calibration.robot_description import RobotDescription

#: A run must cover at least this much travel and this much total turning (|yaw change|).
MIN_DISTANCE_M = 2.0
MIN_ROTATION_DEG = 90.0
#: Plausible fitted values: the effective track lies in [1, MAX_TRACK_FACTOR] x the geometric one,
#: the wheel scale in SCALE_RANGE. Outside them the run (or the reference) is wrong, not the robot.
MAX_TRACK_FACTOR = 5.0
SCALE_RANGE = WHEEL_SCALE_RANGE
#: A window in which neither wheel moved more than this is standstill and left out: the reference's
#: jitter there says nothing about the wheels (0x311 reports millimetres).
STANDSTILL_WHEEL_M = 0.002
DEFAULT_WINDOW_S = 0.5


class WheelCalibrationError(ValueError):
    """The run cannot determine the wheel odometry values, or the values found are implausible."""


class RecordedRun(Protocol):
    """What the fit reads of a recorded run (runtime.odometry.run_log.OdometryRunLog)."""

    t_s: np.ndarray
    left_wheel_m: np.ndarray
    right_wheel_m: np.ndarray
    ref_pose: np.ndarray
    reference: str
    source: str


@dataclass(frozen=True)
class WheelOdometryFit:
    """The fitted values, how well the model explains the run, and how much the run contained.

    distance_m and rotation_rad are the reference motion the fit explains over the windows used
    (sums of |s * distance| and |s * (dR - dL) / b|): summing the reference's own per-window
    changes would count its noise as motion (0.3 deg of ICP jitter per window adds up to tens of
    degrees over a straight run).
    """

    wheel_scale: float
    effective_track_m: float
    geometric_track_m: float
    residual_distance_rms_m: float  # per window
    residual_yaw_rms_rad: float  # per window
    windows_used: int
    windows_total: int
    distance_m: float
    rotation_rad: float
    window_s: float
    reference: str
    source: str

    @property
    def yaw_factor(self) -> float:
        """Effective over geometric track: the robot description's skid_steer_yaw_factor."""
        return self.effective_track_m / self.geometric_track_m

    @property
    def rotation_deg(self) -> float:
        return math.degrees(self.rotation_rad)

    @property
    def residual_yaw_rms_deg(self) -> float:
        return math.degrees(self.residual_yaw_rms_rad)

    def calibration_section(self, date: _dt.datetime | None = None) -> WheelOdometryCalibration:
        """The calibration file's wheel_odometry section for this fit (dated now unless given)."""
        return WheelOdometryCalibration.model_validate({
            "effective_track_m": self.effective_track_m,
            "wheel_scale": self.wheel_scale,
            "fit": {
                "reference": self.reference,
                "source": self.source or "(not given)",
                "windows": self.windows_used,
                "window_s": self.window_s,
                "distance_m": self.distance_m,
                "rotation_deg": self.rotation_deg,
                "residual_distance_rms_m": self.residual_distance_rms_m,
                "residual_yaw_rms_deg": self.residual_yaw_rms_deg,
                "date": date or _dt.datetime.now().replace(microsecond=0),
            },
        })


def window_increments(run: RecordedRun, window_s: float) -> dict[str, np.ndarray]:
    """Per window of `window_s` (full windows only): wheel distance (dL + dR) / 2, wheel difference
    dR - dL, the reference's signed arc length and yaw change. Keys: wheel_distance_m,
    wheel_difference_m, ref_distance_m, ref_yaw_rad, standstill (bool)."""
    t = np.asarray(run.t_s, dtype=float)
    n_windows = int(math.floor((t[-1] - t[0]) / window_s + 1e-9))
    edges = np.unique(np.searchsorted(t, t[0] + window_s * np.arange(n_windows + 1), side="left"))
    edges = edges[edges < len(t)]
    i0, i1 = edges[:-1], edges[1:]
    left, right = np.asarray(run.left_wheel_m, float), np.asarray(run.right_wheel_m, float)
    d_left, d_right = left[i1] - left[i0], right[i1] - right[i0]
    pose = np.asarray(run.ref_pose, float)
    yaw = np.unwrap(pose[:, 2])  # ticks are short: no turn of pi between two of them
    d_yaw = yaw[i1] - yaw[i0]
    mid = 0.5 * (yaw[i0] + yaw[i1])
    along = np.cos(mid) * (pose[i1, 0] - pose[i0, 0]) + np.sin(mid) * (pose[i1, 1] - pose[i0, 1])
    arc = along / np.sinc(d_yaw / (2.0 * np.pi))  # np.sinc(x) = sin(pi x) / (pi x)
    return {
        "wheel_distance_m": 0.5 * (d_left + d_right),
        "wheel_difference_m": d_right - d_left,
        "ref_distance_m": arc,
        "ref_yaw_rad": d_yaw,
        "standstill": np.maximum(np.abs(d_left), np.abs(d_right)) < STANDSTILL_WHEEL_M,
    }


def fit_wheel_odometry(run: RecordedRun, window_s: float = DEFAULT_WINDOW_S, *,
                       geometric_track_m: float) -> WheelOdometryFit:
    """Fit wheel_scale and effective_track_m to `run` (see the module doc); WheelCalibrationError
    when the run cannot determine them or the values found are implausible."""
    if not (math.isfinite(window_s) and window_s > 0):
        raise WheelCalibrationError(f"window must be a positive duration in seconds, got {window_s}")
    if not (math.isfinite(geometric_track_m) and geometric_track_m > 0):
        raise WheelCalibrationError(f"geometric track must be a positive length in metres, got {geometric_track_m}")
    duration_s = float(run.t_s[-1] - run.t_s[0])
    w = window_increments(run, window_s)
    moving = ~w["standstill"]
    n_total, n_used = len(moving), int(moving.sum())
    what = f"run ({run.source or 'no source'}, {duration_s:.1f} s)"
    if n_used < 2:
        raise WheelCalibrationError(f"{what}: the wheels moved in {n_used} of its {n_total} windows of {window_s} s; "
                                    f"record a run that drives at least {MIN_DISTANCE_M} m and turns "
                                    f"{MIN_ROTATION_DEG:g} deg")
    d_wheel, diff = w["wheel_distance_m"][moving], w["wheel_difference_m"][moving]
    d_ref, yaw_ref = w["ref_distance_m"][moving], w["ref_yaw_rad"][moving]
    scale = _fit_through_origin(d_wheel, d_ref)
    k = _fit_through_origin(diff, yaw_ref)  # yaw per metre of wheel difference = scale / track
    distance_m = float(np.abs(scale * d_wheel).sum())
    rotation_rad = float(np.abs(k * diff).sum())
    if distance_m < MIN_DISTANCE_M or math.degrees(rotation_rad) < MIN_ROTATION_DEG:
        raise WheelCalibrationError(
            f"{what}: too little motion to determine the values: {distance_m:.2f} m of travel "
            f"(at least {MIN_DISTANCE_M} m) and {math.degrees(rotation_rad):.0f} deg of turning "
            f"(at least {MIN_ROTATION_DEG:g} deg) over {n_used} moving windows")
    if not k > 0:
        raise WheelCalibrationError(f"{what}: the reference turns against the wheels (yaw per metre of wheel "
                                    f"difference {k:.3g} rad/m); left and right wheel swapped, or the wrong reference?")
    track = scale / k
    lo, hi = geometric_track_m, MAX_TRACK_FACTOR * geometric_track_m
    problems = []
    if not lo <= track <= hi:
        problems.append(f"effective track {track:.3f} m is outside [{lo:.3f}, {hi:.3f}] m "
                        f"(1 to {MAX_TRACK_FACTOR:g} x the geometric {geometric_track_m} m)")
    if not SCALE_RANGE[0] <= scale <= SCALE_RANGE[1]:
        problems.append(f"wheel scale {scale:.3f} is outside [{SCALE_RANGE[0]}, {SCALE_RANGE[1]}]")
    if problems:
        raise WheelCalibrationError(f"{what}: implausible fit: {'; '.join(problems)}; check the run and its reference")
    return WheelOdometryFit(
        wheel_scale=scale,
        effective_track_m=track,
        geometric_track_m=geometric_track_m,
        residual_distance_rms_m=_rms(d_ref - scale * d_wheel),
        residual_yaw_rms_rad=_rms(yaw_ref - k * diff),
        windows_used=n_used,
        windows_total=n_total,
        distance_m=distance_m,
        rotation_rad=rotation_rad,
        window_s=window_s,
        reference=run.reference,
        source=run.source,
    )


def _fit_through_origin(x: np.ndarray, y: np.ndarray) -> float:
    """Least-squares c of y = c x (0 when x carries nothing)."""
    if not np.any(x):
        return 0.0
    (c,), *_ = np.linalg.lstsq(x[:, None], y, rcond=None)
    return float(c)


def _rms(r: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.square(r))))


# ---------------------------------------------------------------------------- for the run time
class WheelParams(NamedTuple):
    """What wheel odometry needs: WheelOdometry(effective_track_m, wheel_scale=wheel_scale)."""

    effective_track_m: float
    wheel_scale: float
    source: str  # where the values come from, for logs and telemetry


def wheel_params(robot: RobotDescription, calibration: CalibrationFile | None) -> WheelParams:
    """The calibration file's fitted values when it has them, else the robot description's nominal
    ones (track_m x skid_steer_yaw_factor, scale 1.0).

    A fitted track outside [1, MAX_TRACK_FACTOR] x the description's track means the file belongs
    to another robot (or was edited by hand): ConfigFileError, rather than driving on it.
    """
    drive = robot.drive
    section = calibration.wheel_odometry if calibration is not None else None
    if section is None:
        why = "no calibration file" if calibration is None else "calibration file has no wheel_odometry section"
        return WheelParams(drive.track_m * drive.skid_steer_yaw_factor, 1.0,
                           f"robot description '{robot.name}': track_m {drive.track_m} x skid_steer_yaw_factor "
                           f"{drive.skid_steer_yaw_factor} ({why})")
    if calibration.robot != robot.name:
        raise ConfigFileError(f"calibration is for robot '{calibration.robot}', the robot description is "
                              f"'{robot.name}': its wheel_odometry section does not apply")
    lo, hi = drive.track_m, MAX_TRACK_FACTOR * drive.track_m
    if not lo <= section.effective_track_m <= hi:
        raise ConfigFileError(f"calibration for robot '{calibration.robot}': wheel_odometry.effective_track_m "
                              f"{section.effective_track_m} m is outside [{lo}, {hi:.3f}] m for robot description "
                              f"'{robot.name}' (track_m {drive.track_m}); is it this robot's calibration?")
    fit = section.fit
    return WheelParams(section.effective_track_m, section.wheel_scale,
                       f"calibration file of '{calibration.robot}': fitted {fit.date.isoformat()} against "
                       f"{fit.reference} ({fit.source})")


__all__ = ["WheelOdometryFit", "WheelCalibrationError", "WheelParams", "fit_wheel_odometry", "wheel_params",
           "window_increments", "RecordedRun", "MIN_DISTANCE_M", "MIN_ROTATION_DEG", "MAX_TRACK_FACTOR",
           "SCALE_RANGE", "STANDSTILL_WHEEL_M", "DEFAULT_WINDOW_S"]
