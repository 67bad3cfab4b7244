"""`dct odom eval --scans`: the recorded-sequence mode of the command (cli.py declares the options).

Order of the work, so that a mistake costs nothing: evo must import (else one line with the
pip command, exit 2); the inputs are read and checked (sequence.load_sequence: counts, times,
bag messages, TUM association); the outputs (--json, --trajectory, --plot) are checked; then
the scans are registered, the figures computed and the outputs written atomically. When the
reference does not move like the scans (reference_check.py), a warning line goes to stderr and
the exit status is 1, with the JSON written (`reference_consistency`).
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import click

from runtime.common.cli_support import InputError
from runtime.common.cli_support import ProgressBar as _Bar
from runtime.common.cli_support import checked_output as _checked_output


@dataclass(frozen=True)
class ScansRequest:
    """What `dct odom eval --scans` was asked for (the command line's values)."""

    scans: Path
    poses_file: Path
    times_file: Path | None
    poses_format: str
    frames: str | None
    lidar_topic: str | None
    imu_topic: str | None
    max_time_diff_s: float
    json_path: Path
    trajectory_path: Path | None
    plot_path: Path | None
    force: bool


def _load(req: ScansRequest):
    from runtime.odometry.evo_eval import require_evo
    from runtime.odometry.pose_files import SequenceInputError, parse_frames
    from runtime.odometry.sequence import load_sequence

    try:
        require_evo()
        frames = parse_frames(req.frames) if req.frames is not None else slice(None)
        return load_sequence(req.scans, req.poses_file, req.times_file, poses_format=req.poses_format, frames=frames,
                             lidar_topic=req.lidar_topic, imu_topic=req.imu_topic, max_time_diff_s=req.max_time_diff_s)
    except SequenceInputError as exc:
        raise InputError(str(exc)) from None


def _check_outputs(req: ScansRequest, seq) -> None:
    if req.plot_path is not None and req.plot_path.suffix.lower() != ".png":
        raise InputError(f"--plot {req.plot_path}: the plot is a PNG image; name it FILE.png")
    inputs = [req.poses_file, req.times_file, req.scans, *seq.source.input_files()]
    _checked_output(req.json_path, "--json", inputs, req.force)
    _checked_output(req.trajectory_path, "--trajectory", inputs + [req.json_path], req.force)
    _checked_output(req.plot_path, "--plot", inputs + [req.json_path, req.trajectory_path], req.force)


def eval_scans(req: ScansRequest, config, deskew: bool | None) -> None:
    """Load, check, register, measure and write (module doc)."""
    from calibration.outputs import atomic_write_bytes, atomic_write_json, atomic_write_text
    from runtime.odometry.evo_eval import plot_png
    from runtime.odometry.pose_files import SequenceInputError, format_kitti_poses
    from runtime.odometry.sequence import evaluate_sequence

    seq = _load(req)
    _check_outputs(req, seq)
    bar = _Bar(f"registering {len(seq.indices)} scans")
    try:
        report, run = evaluate_sequence(seq, config, deskew=deskew, progress=bar)
    except SequenceInputError as exc:
        raise InputError(str(exc)) from None
    finally:
        bar.close()
    if req.plot_path is not None:
        title = f"{req.scans.name}: {len(seq.matched)} scans, reference {req.poses_file.name}"
        atomic_write_bytes(req.plot_path, plot_png(run.poses[seq.matched], seq.poses, title))
    atomic_write_json(req.json_path, report)
    if req.trajectory_path is not None:
        atomic_write_text(req.trajectory_path, format_kitti_poses(run.poses))
    _print_summary(report, req)
    warning = report["reference_consistency"]["warning"]
    if warning is not None:
        click.echo(f"Warning: {warning}", err=True)
        click.get_current_context().exit(1)


def _stats_text(figure: dict) -> str:
    if "skipped" in figure:
        return f"skipped ({figure['skipped']})"
    return f"rmse {figure['rmse'] * 100:.1f} cm, median {figure['median'] * 100:.1f} cm, max {figure['max'] * 100:.1f} cm"


def _print_summary(report: dict, req: ScansRequest) -> None:
    from runtime.odometry.cli import settings_lines, summary_lines

    click.echo(summary_lines("icp", report["icp"]))
    ape, rpe = report["evo"]["ape"], report["evo"]["rpe"]
    click.echo(f"evo APE aligned (SE(3)): {_stats_text(ape['aligned'])}; unaligned: {_stats_text(ape['unaligned'])}")
    click.echo("evo RPE " + "; ".join(f"{k.replace('_', ' ')}: {_stats_text(v)}" for k, v in rpe.items()))
    assoc = report.get("association")
    if assoc is not None:
        un = assoc["unmatched_scans"]
        shown = ", ".join(map(str, un[:10])) + (", ..." if len(un) > 10 else "")
        click.echo(f"{assoc['matched']} of {assoc['scans']} scans matched a TUM pose within {assoc['max_diff_s']:g} s"
                   + (f"; without one (left out): {shown}" if un else ""))
    imu = report.get("imu")
    if imu is not None:
        click.echo(f"IMU {imu['topic']}: {imu['messages']} messages valid ({imu['within_scans']} during the scans), "
                   f"{imu['used']}")
    click.echo(f"{report['frames']} frames, {report['points_per_scan']:.0f} points per scan, registration "
               f"p50 {report['stage_ms']['p50']:.1f} ms p99 {report['stage_ms']['p99']:.1f} ms; {report['deskew_note']}")
    settings_lines(report.get("config"), report.get("range_gate"), report.get("iteration_caps"))
    outs = [p for p in (req.json_path, req.trajectory_path, req.plot_path) if p is not None]
    click.echo("-> " + ", ".join(map(str, outs)))


__all__ = ["ScansRequest", "eval_scans"]
