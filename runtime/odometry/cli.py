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


EVAL_HELP = """Drift, APE and RPE of the lidar odometry against a reference.

Two modes, exactly one of them:

\b
--scans PATH --poses FILE [--times FILE] [--frames A:B]
    a recorded sequence. PATH is a folder of scans (.pcd/.ply, or KITTI velodyne .bin:
    float32 x y z intensity; natural name order: scan_2 before scan_10), or a ROS 2 bag
    (a rosbag2 folder with metadata.yaml, .db3 or .mcap storage, or one .mcap file) with
    --lidar-topic (sensor_msgs/msg/PointCloud2 or livox_ros_driver2/msg/CustomMsg,
    decoded and checked as the controller does; a scan's time is its header stamp) and
    optionally --imu-topic (sensor_msgs/msg/Imu: checked, counted and reported; KISS-ICP
    uses no IMU). FILE: reference poses, KITTI (12 numbers a line, one line per scan) or
    TUM (t x y z qx qy qz qw, matched to the scan times within --max-time-diff),
    detected unless --poses-format says. --times: one time (s) per scan. --frames A:B
    (Python slice) takes part of the sequence: pass the whole files, scans, poses and
    times are sliced together. Counts, times (strictly increasing, and the scans' own
    times against --times) are checked first. Points at exactly (0,0,0) and non-finite
    ones are dropped. Scans with per-point times are deskewed. The voxel, range gate and
    iteration cap are derived from the first scan's ranges unless given (the output says
    what was chosen, and what share of the points the range gate dropped). If the reference does not move like the registered scans (another stretch
    of the recording?), a warning says so and the exit status is 1, the JSON written.
--scenario NAME_OR_PATH [--seed N]
    a simulated scenario: ICP alone, wheels+IMU alone and the fused stream.

The JSON has the figures of each stream (`icp`, ...: length_m, drift_percent,
rpe_percent, rpe_deg_per_m, yaw_drift_deg, end_error_m, ...), with --scans also `evo`
(APE with and without SE(3) alignment, RPE per frame, 1 m and 10 m, as evo computes them;
needs `pip install dct-controller[eval]`) and `reference_consistency`, and `stage_ms`
(p50, p99 of the registration time per frame); a short summary goes to stdout.
"""

#: The --scans options that --scenario refuses: (option, parameter name).
SCANS_ONLY = (("--poses", "poses_file"), ("--times", "times_file"), ("--voxel-size", "voxel_size"),
              ("--max-range", "max_range"), ("--min-range", "min_range"), ("--trajectory", "trajectory_path"),
              ("--frames", "frames"), ("--lidar-topic", "lidar_topic"), ("--imu-topic", "imu_topic"),
              ("--max-time-diff", "max_time_diff"), ("--plot", "plot_path"), ("--max-iterations", "max_iterations"))


def _positive(ctx, param, value):
    if value is not None and not (math.isfinite(value) and value > 0):
        raise click.BadParameter(f"must be a time > 0 in seconds, got {value}")
    return value


@odom_group.command("eval", help=EVAL_HELP)
@click.option("--scans", type=click.Path(path_type=Path), default=None, metavar="PATH",
              help="folder of .pcd/.ply/.bin scans, rosbag2 folder or .mcap file (a recorded sequence)")
@click.option("--poses", "poses_file", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="reference poses, KITTI or TUM (with --scans)")
@click.option("--poses-format", type=click.Choice(["auto", "kitti", "tum"]), default="auto", show_default=True,
              help="the format of --poses (auto: 12 numbers a line is KITTI, 8 is TUM)")
@click.option("--times", "times_file", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="scan times, one per line in seconds (with --scans; optional)")
@click.option("--frames", default=None, metavar="A:B", help="use scans A..B-1 (Python slice of the whole sequence)")
@click.option("--lidar-topic", default=None, metavar="TOPIC", help="the bag's lidar topic (PointCloud2 or CustomMsg)")
@click.option("--imu-topic", default=None, metavar="TOPIC", help="the bag's IMU topic (checked and reported)")
@click.option("--max-time-diff", type=float, default=None, callback=_positive,
              help="TUM poses: largest scan-to-pose time difference (s) [default: 0.01, evo's]")
@click.option("--scenario", default=None, metavar="NAME_OR_PATH", help="a scenario of the library, or a YAML file")
@click.option("--seed", type=click.IntRange(0, 2**32 - 1), default=None, help="scenario seed [default: 0]")
@click.option("--json", "json_path", type=click.Path(dir_okay=False, path_type=Path), required=True,
              help="write the figures here (checked before the run, written atomically after it)")
@click.option("--force", is_flag=True, help="overwrite existing output files")
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
@click.option("--plot", "plot_path", type=click.Path(dir_okay=False, path_type=Path), default=None, metavar="FILE.png",
              help="also draw the reference and the estimate, top view (with --scans)")
def eval_command(**opts) -> None:
    """See EVAL_HELP."""
    scans, scenario = opts["scans"], opts["scenario"]
    if (scans is None) == (scenario is None):
        raise InputError("dct odom eval: give exactly one of --scans PATH or --scenario NAME_OR_PATH (see --help)")
    if scenario is not None:
        given = [name for name, key in SCANS_ONLY if opts[key] is not None]
        given += [name for name, key, default in (("--deskew", "deskew", "auto"), ("--poses-format", "poses_format",
                                                                                    "auto")) if opts[key] != default]
        if given:
            raise InputError(f"dct odom eval: {', '.join(given)} go with --scans, not --scenario "
                             f"(the scenario's controller config sets the odometry)")
        seed = opts["seed"]
        _eval_scenario(scenario, 0 if seed is None else seed, opts["json_path"], opts["force"], opts["record_path"])
        return
    _scans_mode(opts)


def _scans_mode(opts: dict) -> None:
    from runtime.odometry.cli_scans import ScansRequest, eval_scans
    from runtime.odometry.evo_eval import DEFAULT_MAX_TIME_DIFF_S

    if opts["seed"] is not None:
        raise InputError("dct odom eval: --seed goes with --scenario (a recorded sequence has no seed)")
    if opts["record_path"] is not None:
        raise InputError("dct odom eval: --record goes with --scenario (it records the simulated run's wheels, "
                         "gyro and ground truth)")
    if opts["poses_file"] is None:
        raise InputError("dct odom eval: --scans needs --poses FILE (the reference poses, KITTI or TUM)")
    req = ScansRequest(scans=opts["scans"], poses_file=opts["poses_file"], times_file=opts["times_file"],
                       poses_format=opts["poses_format"], frames=opts["frames"], lidar_topic=opts["lidar_topic"],
                       imu_topic=opts["imu_topic"],
                       max_time_diff_s=opts["max_time_diff"] or DEFAULT_MAX_TIME_DIFF_S,
                       json_path=opts["json_path"], trajectory_path=opts["trajectory_path"],
                       plot_path=opts["plot_path"], force=opts["force"])
    config = _icp_config(opts["voxel_size"], opts["max_range"], opts["min_range"],
                          max_iterations=opts["max_iterations"])
    eval_scans(req, config, {"auto": None, "on": True, "off": False}[opts["deskew"]])


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
    settings_lines((odo.get("icp_settings") or {}).get("icp"), odo.get("icp_range_gate"), odo.get("icp_iteration_cap"))
    click.echo(f"-> {json_path}")


def settings_lines(icp: dict | None, gate: dict | None, caps: list | None = None) -> None:
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
