"""`dct calibrate wheels`: fit the effective track width and wheel scale to a recorded run.

The fit and the calibration file are calibration's (calibration.wheel_odometry,
calibration.calibration_file); the command lives here because it reads a recorded run
(runtime.odometry.run_log) and calibration must not import runtime. It joins the `dct calibrate`
group through the "dct.calibrate" entry point, as hil_sim's `hil-check` does.
"""
from __future__ import annotations

import math
from pathlib import Path

import click

from calibration.cli_support import OneLineCommand, OneLineError, checked_output
from calibration.wheel_odometry import (DEFAULT_WINDOW_S, MAX_TRACK_FACTOR, MIN_DISTANCE_M, MIN_ROTATION_DEG,
                                        SCALE_RANGE)

#: Exit status for input the user must fix (a file, an option, a run that cannot determine the values).
EXIT_BAD_INPUT = 2


def _bad_input(message: str) -> OneLineError:
    err = OneLineError(message)
    err.exit_code = EXIT_BAD_INPUT
    return err


def _positive_seconds(ctx, param, value: float) -> float:
    if not (math.isfinite(value) and value > 0):
        raise click.BadParameter(f"must be a positive duration in seconds, got {value}")
    return value


WHEELS_HELP = f"""Fit the effective track width and wheel scale to a recorded run; store them in a calibration file.

RUN.npz is a recorded odometry run (`dct odom eval --record`, or the robot's recorder) with a
reference pose (ground truth or ICP) per tick. The run is cut into windows of --window-s; the
wheel scale s and effective track b are the least-squares fit of, per moving window:
reference distance = s (dL + dR) / 2, reference yaw change = s (dR - dL) / b.

The run must drive at least {MIN_DISTANCE_M:g} m and turn at least {MIN_ROTATION_DEG:g} deg in total (forward and
reverse, both directions of turn, make a better fit). A fit outside the plausible ranges (track
from 1 to {MAX_TRACK_FACTOR:g} x the robot description's track_m, scale from {SCALE_RANGE[0]} to {SCALE_RANGE[1]}) is refused.

The calibration file is an input too (its robot, camera and extrinsic are kept): the result is
written to --output when given (an existing file there only with --force), else back to
--calibration, and there only when it has no wheel_odometry section yet or --force is given.
Writes are atomic. Exit 2 on bad input (a file, an option, a run that cannot determine the
values), 1 when the output cannot be written.
"""


@click.command("wheels", cls=OneLineCommand, help=WHEELS_HELP)
@click.option("--run", "run_path", type=click.Path(exists=True, dir_okay=False, path_type=Path), required=True,
              help="recorded odometry run (.npz)")
@click.option("--calibration", "cal_path", type=click.Path(exists=True, dir_okay=False, path_type=Path),
              required=True, help="the robot's calibration YAML (an input; replaced only as described above)")
@click.option("--output", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="write the calibration here instead of back to --calibration")
@click.option("--force", is_flag=True,
              help="replace an existing --output, or an existing wheel_odometry section in --calibration")
@click.option("--window-s", type=float, default=DEFAULT_WINDOW_S, show_default=True, callback=_positive_seconds,
              help="fit window length in seconds")
@click.option("--robot-description", type=click.Path(exists=True, dir_okay=False, path_type=Path), default=None,
              help="for the geometric track (default: the shipped LIMO description)")
def wheels_command(run_path: Path, cal_path: Path, output: Path | None, force: bool, window_s: float,
                   robot_description: Path | None) -> None:
    """See WHEELS_HELP."""
    from calibration.calibration_file import load_calibration, save_calibration
    from calibration.errors import ConfigFileError
    from calibration.robot_description import load_robot_description
    from calibration.wheel_odometry import WheelCalibrationError, fit_wheel_odometry
    from runtime.odometry.run_log import RunLogError, load_run_log

    def checked(path: Path, **kw) -> Path:
        try:
            return checked_output(path, "calibration file", **kw)
        except OneLineError as exc:
            raise _bad_input(exc.message) from None

    out = (checked(output, inputs=[run_path, cal_path, robot_description], overwrite=force) if output is not None
           else checked(cal_path, inputs=[run_path, robot_description]))
    try:
        desc = load_robot_description(robot_description)
        cal = load_calibration(cal_path)
        run = load_run_log(run_path)
    except (ConfigFileError, RunLogError) as exc:
        raise _bad_input(str(exc)) from None
    previous = cal.wheel_odometry
    if output is None and previous is not None and not force:
        raise _bad_input(f"calibration file {cal_path} already has a wheel_odometry section (fitted "
                         f"{previous.fit.date.isoformat()}); pass --force to replace it, or --output to write "
                         f"another file")
    if run.robot != cal.robot:
        raise _bad_input(f"odometry run {run_path} is of robot '{run.robot}', calibration file {cal_path} of "
                         f"'{cal.robot}'")
    try:
        fit = fit_wheel_odometry(run, window_s, geometric_track_m=desc.drive.track_m)
    except WheelCalibrationError as exc:
        raise _bad_input(f"odometry run {run_path}: {exc}") from None

    click.echo(f"run {run_path}: robot {run.robot}, {len(run)} ticks over {run.duration_s:.1f} s, "
               f"reference {run.reference} ({run.source or 'no source given'})")
    click.echo(f"windows of {fit.window_s:g} s: {fit.windows_used} used, "
               f"{fit.windows_total - fit.windows_used} standstill left out")
    click.echo(f"motion explained: {fit.distance_m:.2f} m of travel, {fit.rotation_deg:.0f} deg of turning")
    click.echo(f"wheel_scale          {fit.wheel_scale:.4f}")
    click.echo(f"effective_track_m    {fit.effective_track_m:.4f} m (yaw factor {fit.yaw_factor:.3f} x the "
               f"geometric {fit.geometric_track_m} m; the description says {desc.drive.skid_steer_yaw_factor:g})")
    click.echo(f"residual RMS         {fit.residual_distance_rms_m * 1000:.1f} mm distance, "
               f"{fit.residual_yaw_rms_deg:.2f} deg yaw per window")
    new = cal.model_copy(update={"wheel_odometry": fit.calibration_section()})
    try:
        save_calibration(new, out)
    except (ConfigFileError, OSError) as exc:
        raise OneLineError(f"{out}: not written: {exc}") from None
    note = ""
    if previous is not None:
        note = (f" (replaces the section fitted {previous.fit.date.isoformat()}: track "
                f"{previous.effective_track_m:.4f} m, scale {previous.wheel_scale:.4f})")
    click.echo(f"wheel_odometry -> {out}{note}")


__all__ = ["wheels_command"]
