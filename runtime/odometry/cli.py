"""`dct odom`: evaluate the lidar odometry on a recorded sequence or a simulated scenario, and
register one scan against another.

Rules (as in `dct calibrate`): an input error is ONE line on stderr and exit status 2, nothing
is written; an output path is checked before the work, an existing file is refused unless
--force, and the JSON is written atomically after the work succeeded.

`--scenario` runs in the simulator, which `runtime` must not import (the package layering of
docs/architecture.md): its evaluation is found through the entry point group "dct.odom_scenario" (name "evaluate", in
pyproject.toml: hil_sim.eval.odometry:evaluate_scenario) and loaded only when asked for. Its
contract: `evaluate_scenario(scenario: str, seed: int, progress: Callable[[float, float], None])
-> dict` (JSON-ready: `icp`, `wheels_imu`, `fused`, `stage_ms`, ...; progress(done, total) in
any unit); bad input raises calibration.errors.ConfigFileError (exit 2).
"""
from __future__ import annotations

import math
from pathlib import Path

import click

from calibration.cli_support import OneLineGroup
from runtime.common.cli_support import InputError, scenario_evaluator
from runtime.common.cli_support import ProgressBar as _Bar
from runtime.common.cli_support import checked_output as _checked_output

#: The entry point group (and name) of the scenario evaluation (module doc).
SCENARIO_EVAL_GROUP = "dct.odom_scenario"
SCENARIO_EVAL_NAME = "evaluate"


# (The one-line errors, output checks and progress bar are runtime.common.cli_support's, shared with `dct vpp`.)
@click.group(name="odom", cls=OneLineGroup)
def odom_group() -> None:
    """Lidar odometry (KISS-ICP): drift on recorded sequences and scenarios, scan-pair registration."""


def _length(ctx, param, value):
    if value is not None and not (math.isfinite(value) and value >= 0):
        raise click.BadParameter(f"must be a length >= 0 in metres, got {value}")
    return value


def _icp_config(voxel_size: float | None, max_range: float | None, min_range: float | None, base=None,
                max_iterations: int | None = None):
    """IcpConfig (base: its defaults) with the command line's overrides; one-line error if invalid."""
    from pydantic import ValidationError

    from calibration.errors import format_validation_error
    from runtime.odometry.icp_config import IcpConfig

    base = base if base is not None else IcpConfig()
    overrides = {k: v for k, v in (("voxel_size_m", voxel_size), ("max_range_m", max_range),
                                   ("min_range_m", min_range), ("max_iterations", max_iterations)) if v is not None}
    try:
        return IcpConfig.model_validate({**base.model_dump(), **overrides})
    except ValidationError as exc:
        raise InputError(f"--voxel-size/--max-range/--min-range: {format_validation_error(exc)}") from None


def _fmt(value, spec: str, unit: str = "") -> str:
    return "n/a" if value is None else f"{value:{spec}}{unit}"


def summary_lines(name: str, e: dict) -> str:
    """One line per stream: the figures of trajectory_errors."""
    segs = ",".join(f"{s:g}" for s in e.get("rpe_segments_m", [])) or "none"
    return (f"{name}: length {e['length_m']:.2f} m, drift {_fmt(e['drift_percent'], '.2f', '%')} "
            f"(end error {e['end_error_m'] * 100:.1f} cm), yaw drift {e['yaw_drift_deg']:.2f} deg, "
            f"RPE {_fmt(e['rpe_percent'], '.2f', '%')} / {_fmt(e['rpe_deg_per_m'], '.3f', ' deg/m')} "
            f"(segments {segs} m)")


EVAL_HELP = """Drift and relative pose error of the lidar odometry against a reference.

Two modes, exactly one of them:

\b
--scans DIR --poses FILE [--times FILE]
    a recorded sequence: DIR holds one .pcd/.ply scan per sweep (natural name order:
    scan_2 before scan_10), FILE the reference poses in KITTI format (one line of 12
    numbers per scan: the top 3 rows of the 4x4 scanner pose, row-major, z up), the
    optional times file one time (s) per scan. Points at exactly (0,0,0) and non-finite
    ones are dropped. Scans with a per-point time field (t, time, timestamp,
    timestamps, offset_time) are deskewed; without one they are registered as they are
    (the output says which). The voxel, range gate and iteration cap are derived from
    the first scan's ranges unless given (the output says what was chosen, and what
    share of the points the range gate dropped).
--scenario NAME_OR_PATH [--seed N]
    a simulated scenario: ICP alone, wheels+IMU alone and the fused stream.

The JSON has the figures of each stream (`icp`, ...: length_m, drift_percent,
rpe_percent, rpe_deg_per_m, yaw_drift_deg, end_error_m, ...) and `stage_ms` (p50, p99
of the registration time per frame); a short summary goes to stdout.
"""


@odom_group.command("eval", help=EVAL_HELP)
@click.option("--scans", "scans_dir", type=click.Path(file_okay=False, path_type=Path), default=None,
              help="folder of .pcd/.ply scans (a recorded sequence)")
@click.option("--poses", "poses_file", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="reference poses, KITTI format (with --scans)")
@click.option("--times", "times_file", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="scan times, one per line in seconds (with --scans; optional)")
@click.option("--scenario", default=None, metavar="NAME_OR_PATH", help="a scenario of the library, or a YAML file")
@click.option("--seed", type=click.IntRange(0, 2**32 - 1), default=None, help="scenario seed [default: 0]")
@click.option("--json", "json_path", type=click.Path(dir_okay=False, path_type=Path), required=True,
              help="write the figures here (checked before the run, written atomically after it)")
@click.option("--force", is_flag=True, help="overwrite an existing --json file")
@click.option("--voxel-size", type=float, default=None, callback=_length,
              help="KISS-ICP voxel (m) [default: auto, from the first scan's ranges]")
@click.option("--max-range", type=float, default=None, callback=_length, help="farthest point used (m) [default: auto]")
@click.option("--min-range", type=float, default=None, callback=_length, help="nearest point used (m) [default: auto]")
@click.option("--max-iterations", type=click.IntRange(1, 500), default=None,
              help="ICP iteration cap per scan [default: auto, what the iteration budget pays for]")
@click.option("--deskew", type=click.Choice(["auto", "on", "off"]), default="auto", show_default=True,
              help="auto: deskew when the scans have per-point times; on: require them")
@click.option("--record", "record_path", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="with --scenario: also write the run (wheels, gyro, ground truth) as an .npz for "
                   "`dct calibrate wheels`")
@click.option("--trajectory", "trajectory_path", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="also write the estimated poses here (KITTI format; with --scans)")
def eval_command(*, scans_dir: Path | None, poses_file: Path | None, times_file: Path | None, scenario: str | None,
                 seed: int | None, json_path: Path, force: bool, voxel_size: float | None, max_range: float | None,
                 min_range: float | None, deskew: str, trajectory_path: Path | None, record_path: Path | None = None,
                 max_iterations: int | None = None) -> None:
    """See EVAL_HELP."""
    if (scans_dir is None) == (scenario is None):
        raise InputError("dct odom eval: give exactly one of --scans DIR or --scenario NAME_OR_PATH (see --help)")
    if scenario is not None:
        given = [name for name, v in (("--poses", poses_file), ("--times", times_file), ("--voxel-size", voxel_size),
                                      ("--max-range", max_range), ("--min-range", min_range),
                                      ("--max-iterations", max_iterations), ("--trajectory", trajectory_path))
                 if v is not None]
        if deskew != "auto":
            given.append("--deskew")
        if given:
            raise InputError(f"dct odom eval: {', '.join(given)} go with --scans, not --scenario "
                             f"(the scenario's controller config sets the odometry)")
        _eval_scenario(scenario, 0 if seed is None else seed, json_path, force, record_path)
        return
    if seed is not None:
        raise InputError("dct odom eval: --seed goes with --scenario (a recorded sequence has no seed)")
    if record_path is not None:
        raise InputError("dct odom eval: --record goes with --scenario (it records the simulated run's wheels, "
                         "gyro and ground truth)")
    if poses_file is None:
        raise InputError("dct odom eval: --scans needs --poses FILE (the reference poses, KITTI format)")
    _eval_scans(scans_dir, poses_file, times_file, json_path, force,
                _icp_config(voxel_size, max_range, min_range, max_iterations=max_iterations),
                {"auto": None, "on": True, "off": False}[deskew], trajectory_path)


def _eval_scans(scans_dir: Path, poses_file: Path, times_file: Path | None, json_path: Path, force: bool, config,
                deskew: bool | None, trajectory_path: Path | None) -> None:
    from calibration.outputs import atomic_write_json, atomic_write_text
    from runtime.odometry.sequence import SequenceInputError, evaluate_sequence, format_kitti_poses, load_sequence

    try:
        seq = load_sequence(scans_dir, poses_file, times_file)
    except SequenceInputError as exc:
        raise InputError(str(exc)) from None
    inputs = [poses_file, times_file, *seq.scans]
    _checked_output(json_path, "--json", inputs, force)
    _checked_output(trajectory_path, "--trajectory", inputs + [json_path], force)
    bar = _Bar(f"registering {len(seq.scans)} scans")
    try:
        report, run = evaluate_sequence(seq, config, deskew=deskew, progress=bar)
    except SequenceInputError as exc:
        raise InputError(str(exc)) from None
    finally:
        bar.close()
    atomic_write_json(json_path, report)
    if trajectory_path is not None:
        atomic_write_text(trajectory_path, format_kitti_poses(run.poses))
    click.echo(summary_lines("icp", report["icp"]))
    click.echo(f"{report['frames']} frames, {report['points_per_scan']:.0f} points per scan, registration "
               f"p50 {report['stage_ms']['p50']:.1f} ms p99 {report['stage_ms']['p99']:.1f} ms; {report['deskew_note']}")
    _settings_lines(report.get("config"), report.get("range_gate"), report.get("iteration_caps"))
    click.echo(f"-> {json_path}" + (f", {trajectory_path}" if trajectory_path is not None else ""))


def _scenario_evaluator():
    """hil_sim's evaluate_scenario, through its entry point (module doc)."""
    return scenario_evaluator(SCENARIO_EVAL_GROUP, SCENARIO_EVAL_NAME, "dct odom eval")


def _eval_scenario(scenario: str, seed: int, json_path: Path, force: bool, record_path: Path | None = None) -> None:
    from calibration.errors import ConfigFileError
    from calibration.outputs import atomic_write_json

    evaluate = _scenario_evaluator()
    inputs = [Path(scenario)] if Path(scenario).is_file() else []
    _checked_output(json_path, "--json", inputs, force)
    if record_path is not None:
        _checked_output(record_path, "--record", inputs + [json_path], force)
    bar = _Bar(f"{scenario}")
    record: dict | None = {} if record_path is not None else None
    try:
        extra = {"record": record} if record is not None else {}
        report = evaluate(scenario, seed=seed, progress=bar, **extra)
    except ConfigFileError as exc:  # a scenario that cannot run (no route, robot does not fit, ...)
        raise InputError(str(exc)) from None
    finally:
        bar.close()
    if record_path is not None:
        from runtime.odometry.run_log import OdometryRunLog

        OdometryRunLog(t_s=record["t_s"], left_wheel_m=record["left_wheel_m"], right_wheel_m=record["right_wheel_m"],
                       gyro_z_radps=record["gyro_z_radps"], ref_pose=record["ref_pose"], reference="ground_truth",
                       robot=record["robot"], source=record["source"]).save(record_path, overwrite=force)
    atomic_write_json(json_path, report)
    for stream in ("icp", "wheels_imu", "fused"):
        if isinstance(report.get(stream), dict) and "length_m" in report[stream]:
            click.echo(summary_lines(stream, report[stream]))
    if isinstance(report.get("stage_ms"), dict):
        click.echo(f"odometry stage p50 {report['stage_ms'].get('p50', float('nan')):.1f} ms "
                   f"p99 {report['stage_ms'].get('p99', float('nan')):.1f} ms")
    odo = report.get("odometry") if isinstance(report.get("odometry"), dict) else {}
    _settings_lines((odo.get("icp_settings") or {}).get("icp"), odo.get("icp_range_gate"), odo.get("icp_iteration_cap"))
    click.echo(f"-> {json_path}")


def _settings_lines(icp: dict | None, gate: dict | None, caps: list | None = None) -> None:
    """The ICP settings used (auto ones resolved), the iteration caps, and what the range gate
    dropped (a warning line on stderr above a quarter)."""
    from runtime.odometry.icp_settings import gate_lines

    if icp:
        cap = icp["max_iterations"]
        if cap == "auto" and caps:
            cap = f"auto ({caps[0]}-{caps[1]} per scan)" if caps[0] != caps[1] else f"auto ({caps[0]})"
        click.echo(f"ICP settings: voxel {icp['voxel_size_m']:g} m, range {icp['min_range_m']:g}-{icp['max_range_m']:g} m, "
                   f"iteration cap {cap}, initial threshold {icp['initial_threshold_m']:g} m")
    for k, line in enumerate(gate_lines(gate)):
        click.echo(line, err=k > 0)


# ---------------------------------------------------------------------------- register
REGISTER_HELP = """Register SOURCE onto TARGET (two .pcd/.ply scans) with the odometry's KISS-ICP.

Prints T_target<-source (p_target = T p_source) as a 4x4 matrix. With --reference (a text
file holding a 4x4 matrix in the same convention, e.g. T_target_source.txt) also the
translation (cm) and rotation (deg) differences. Defaults: the outdoor settings measured on
an HDL-32 pair (voxel 0.5 m, range 60 m; runtime.odometry.pair); override them for other
sensors.
"""


@odom_group.command("register", help=REGISTER_HELP)
@click.argument("source", type=click.Path(exists=True, dir_okay=False, path_type=Path))
@click.argument("target", type=click.Path(exists=True, dir_okay=False, path_type=Path))
@click.option("--reference", type=click.Path(exists=True, dir_okay=False, path_type=Path), default=None,
              help="4x4 T_target<-source to compare with")
@click.option("--json", "json_path", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="write the transform (and differences) here, atomically")
@click.option("--force", is_flag=True, help="overwrite an existing --json file")
@click.option("--voxel-size", type=float, default=None, callback=_length, help="KISS-ICP voxel (m) [default: 0.5]")
@click.option("--max-range", type=float, default=None, callback=_length, help="farthest point used (m) [default: 60]")
@click.option("--min-range", type=float, default=None, callback=_length, help="nearest point used (m) [default: 0]")
def register_command(*, source: Path, target: Path, reference: Path | None, json_path: Path | None, force: bool,
                     voxel_size: float | None, max_range: float | None, min_range: float | None) -> None:
    """See REGISTER_HELP."""
    import numpy as np

    from calibration.outputs import atomic_write_json
    from runtime.odometry.pair import OUTDOOR_PAIR_CONFIG, register_pair, transform_difference
    from runtime.odometry.sequence import SequenceInputError, load_scan, read_transform

    config = _icp_config(voxel_size, max_range, min_range, base=OUTDOOR_PAIR_CONFIG)
    _checked_output(json_path, "--json", [source, target, reference], force)
    try:
        ref = read_transform(reference, "--reference") if reference is not None else None
        src, tgt = load_scan(source), load_scan(target)
    except SequenceInputError as exc:
        raise InputError(str(exc)) from None
    T = register_pair(src.points, tgt.points, config)
    with np.printoptions(precision=6, suppress=True):
        click.echo(f"T_target<-source ({len(src.points)} source / {len(tgt.points)} target points):\n{T}")
    report = {"T_target_source": T.tolist(), "source": str(source), "target": str(target),
              "source_points": len(src.points), "target_points": len(tgt.points), "config": config.model_dump()}
    if ref is not None:
        dt, dr = transform_difference(T, ref)
        click.echo(f"against {reference}: translation {dt * 100:.2f} cm, rotation {dr:.3f} deg")
        report.update(reference=str(reference), translation_difference_m=dt, rotation_difference_deg=dr)
    if json_path is not None:
        atomic_write_json(json_path, report)
        click.echo(f"-> {json_path}")


__all__ = ["odom_group", "summary_lines", "SCENARIO_EVAL_GROUP", "SCENARIO_EVAL_NAME"]
