"""Lidar odometry on a recorded sequence, measured against its reference poses.

A sequence is what users have from their own robots, in the simplest form every tool exports:

* a folder of scans, one `.pcd` or `.ply` file per sweep (`calibration.pointcloud_io` reads
  them), taken in natural name order: `scan_2` before `scan_10`, `000009` before `000010`;
* a poses file in KITTI format: one line per scan, 12 numbers, the top three rows of the 4x4
  pose of the scanner in a world frame with z up, row-major (`r11 r12 r13 tx r21 r22 r23 ty r31
  r32 r33 tz`), so that `p_world = T p_scan`. Blank lines and lines starting with `#` are
  skipped; anything else must be 12 finite numbers whose rotation is orthonormal (within
  `metrics.ROTATION_TOLERANCE`) with determinant +1;
* optionally a times file: one time per line (seconds), strictly increasing, one per scan. It is
  checked and reported (duration, mean speed); the registration itself does not need it.

Points: non-finite ones and those exactly at (0, 0, 0) are dropped; most drivers write an
invalid return (no echo) as a zero point, e.g. about 5k of the 70k points of each HDL-32 scan in
tests/data/real/hdl32_pair_small_gicp.

Per-point times (deskew): a scan's per-point time field is the first of POINT_TIME_FIELDS it
has. KISS-ICP normalises the times of a frame over their [min, max] and deskews every point to
the time of the frame's last point, with the constant-velocity motion of the previous step,
so only the order of the times within the sweep matters, not their unit or origin:

  `t`            Ouster (uint32 ns since the start of the sweep), also KISS-ICP's own choice
  `time`         Velodyne drivers (float32 s relative to the sweep start or end)
  `timestamp`    Hesai / many exporters (float64 s, absolute)
  `timestamps`   KISS-ICP's generic reader's alternative name
  `offset_time`  Livox CustomMsg converted to PCD (uint32 ns since the packet's timebase)

The field must span the sweep: a field whose values are all equal carries no time, and a
sequence whose first scan has no usable time field is registered WITHOUT deskew (the result
says so, `deskew: false` with the reason) rather than with invented times, which make drift
worse (docs/decisions/odometry-deskew-times.md). Every later scan must then agree with the first.

Which time the poses are compared at: the estimate of scan i is KISS-ICP's `last_pose` after
registering it, the pose at the time of its last point when deskewed. Reference poses are
taken as given, one per scan; a reference stamped at the start of the sweep differs from
that by one sweep's motion, which both trajectories share after they are expressed relative
to their first pose, so the metrics barely see it.
"""
from __future__ import annotations

import math
import re
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np

from runtime.odometry.icp_config import IcpConfig, new_kiss_icp
from runtime.odometry.icp_settings import RangeGate
from runtime.odometry.metrics import rotation_problem, trajectory_errors

#: Per-point time fields, in the order they are looked for (see the module doc).
POINT_TIME_FIELDS = ("t", "time", "timestamp", "timestamps", "offset_time")
SCAN_SUFFIXES = (".pcd", ".ply")

#: progress(done, total): called after each registered frame.
Progress = Callable[[int, int], None]


class SequenceInputError(ValueError):
    """A sequence's folder, scan, poses or times file is missing or malformed; the message is
    one line naming the file (and line) and what is wrong."""


# ---------------------------------------------------------------------------- files
def natural_key(name: str) -> tuple:
    """Sort key reading runs of digits as numbers: scan_2 < scan_10, case-insensitive."""
    return tuple((0, int(part), part) if part.isdigit() else (1, 0, part.lower())
                 for part in re.split(r"(\d+)", name) if part)


def list_scans(folder: str | Path) -> list[Path]:
    """The `.pcd` / `.ply` files of `folder` in natural name order (see natural_key)."""
    d = Path(folder)
    if not d.exists():
        raise SequenceInputError(f"scan folder {d} does not exist")
    if not d.is_dir():
        raise SequenceInputError(f"scan folder {d} is not a folder")
    scans = [p for p in d.iterdir() if p.suffix.lower() in SCAN_SUFFIXES and p.is_file()]
    if not scans:
        raise SequenceInputError(f"scan folder {d} has no .pcd or .ply file")
    return sorted(scans, key=lambda p: natural_key(p.name))


def _text_lines(path: Path, what: str) -> list[tuple[int, str]]:
    """(line number, stripped text) of the lines that are not blank or comments."""
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise SequenceInputError(f"{what} {path}: cannot read file: {exc.strerror or exc}") from None
    try:
        text = data.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        raise SequenceInputError(f"{what} {path}: not UTF-8 text (byte offset {exc.start})") from None
    lines = [(i, ln.strip()) for i, ln in enumerate(text.splitlines(), start=1)]
    return [(i, ln) for i, ln in lines if ln and not ln.startswith("#")]


def _numbers(path: Path, what: str, lineno: int, text: str, count: int) -> list[float]:
    parts = text.split()
    if len(parts) != count:
        raise SequenceInputError(f"{what} {path} line {lineno}: expected {count} number{'s' * (count > 1)}, "
                                 f"got {len(parts)}")
    values = []
    for p in parts:
        try:
            v = float(p)
        except ValueError:
            raise SequenceInputError(f"{what} {path} line {lineno}: {p[:40]!r} is not a number") from None
        if not math.isfinite(v):
            raise SequenceInputError(f"{what} {path} line {lineno}: {p!r} is not a finite number")
        values.append(v)
    return values


def read_kitti_poses(path: str | Path) -> np.ndarray:
    """Poses from a KITTI-format file (module doc) as (N,4,4); SequenceInputError naming the
    file and line on any problem."""
    path = Path(path)
    lines = _text_lines(path, "poses file")
    if not lines:
        raise SequenceInputError(f"poses file {path}: no poses (the file is empty)")
    poses = np.zeros((len(lines), 4, 4))
    poses[:, 3, 3] = 1.0
    for k, (lineno, text) in enumerate(lines):
        poses[k, :3, :] = np.array(_numbers(path, "poses file", lineno, text, 12)).reshape(3, 4)
        problem = rotation_problem(poses[k, :3, :3])
        if problem:
            raise SequenceInputError(f"poses file {path} line {lineno}: the {problem}")
    return poses


def read_transform(path: str | Path, what: str = "transform file") -> np.ndarray:
    """A 4x4 rigid transform from a text file: 4 numbers on each of 4 lines (or the top 3)."""
    path = Path(path)
    lines = _text_lines(path, what)
    if len(lines) not in (3, 4):
        raise SequenceInputError(f"{what} {path}: expected a 4x4 matrix (4 numbers on each of 4 lines, or the top 3), "
                                 f"got {len(lines)} lines")
    T = np.eye(4)
    T[:len(lines)] = [_numbers(path, what, n, text, 4) for n, text in lines]
    if np.abs(T[3] - (0.0, 0.0, 0.0, 1.0)).max() > 1e-9:
        raise SequenceInputError(f"{what} {path} line {lines[3][0]}: the last row must be 0 0 0 1")
    problem = rotation_problem(T[:3, :3])
    if problem:
        raise SequenceInputError(f"{what} {path}: the top-left 3x3 is not a rotation: {problem}")
    return T


def format_kitti_poses(poses: np.ndarray) -> str:
    """(N,4,4) poses as KITTI lines (12 numbers, %.9e: orthonormal to 1e-9 when read back)."""
    return "".join(" ".join(f"{v:.9e}" for v in T[:3, :].ravel()) + "\n" for T in np.asarray(poses))


def read_times(path: str | Path) -> np.ndarray:
    """Scan times (s) from a file with one number per line, strictly increasing."""
    path = Path(path)
    lines = _text_lines(path, "times file")
    if not lines:
        raise SequenceInputError(f"times file {path}: no times (the file is empty)")
    times = np.array([_numbers(path, "times file", n, text, 1)[0] for n, text in lines])
    for k in range(1, len(times)):
        if not times[k] > times[k - 1]:
            raise SequenceInputError(f"times file {path} line {lines[k][0]}: {float(times[k])!r} is not after the "
                                     f"previous time {float(times[k - 1])!r} (times must be strictly increasing)")
    return times


# ---------------------------------------------------------------------------- scans
@dataclass(frozen=True)
class Scan:
    """One sweep's valid points, (M,3) float64, and their per-point times (M,) or None."""

    points: np.ndarray
    times: np.ndarray | None
    time_field: str | None
    #: How many points were dropped (non-finite, exactly zero, non-finite time).
    dropped: int
    #: Why `times` is None although the file has a time field (e.g. constant values).
    times_note: str | None = None


def load_scan(path: str | Path) -> Scan:
    """Read one scan (module doc: which points are kept, which time field is used)."""
    from calibration.pointcloud_io import PointCloudFormatError, finite_xyz, load_point_cloud

    where = str(path)
    try:
        cloud = load_point_cloud(path)
        finite_xyz(cloud, where)  # its one-line errors for an empty or all-NaN cloud
    except PointCloudFormatError as exc:
        raise SequenceInputError(str(exc)) from None
    xyz = cloud.xyz
    keep = np.isfinite(xyz).all(axis=1) & (xyz != 0.0).any(axis=1)
    time_field = next((f for f in POINT_TIME_FIELDS if f in cloud.fields), None)
    times, note = None, None
    if time_field is not None:
        t = np.asarray(cloud.fields[time_field])
        if t.ndim != 1:
            raise SequenceInputError(f"{where}: time field {time_field!r} has {t.shape[1]} values per point, expected 1")
        t = t.astype(np.float64)
        keep &= np.isfinite(t)
        if keep.any() and np.ptp(t[keep]) > 0:
            times = t[keep]
        else:
            note = f"time field {time_field!r} has the same value for every point (no time span)"
    if not keep.any():
        raise SequenceInputError(f"{where}: none of its {len(xyz)} points is valid (all are NaN/inf or exactly 0,0,0)")
    return Scan(points=np.ascontiguousarray(xyz[keep]), times=times, time_field=time_field if times is not None else None,
                dropped=int(len(xyz) - keep.sum()), times_note=note)


# ---------------------------------------------------------------------------- the sequence
@dataclass(frozen=True)
class Sequence:
    """A validated sequence: scan files (read when registered), reference poses, optional times."""

    scans: list[Path]
    poses: np.ndarray
    times: np.ndarray | None = None
    sources: dict = field(default_factory=dict)


def load_sequence(scans_dir: str | Path, poses_file: str | Path, times_file: str | Path | None = None) -> Sequence:
    """List the scans and read the poses (and times); every count and value is checked here,
    before any scan is registered. The scans themselves are read one at a time later."""
    scans = list_scans(scans_dir)
    poses = read_kitti_poses(poses_file)
    if len(poses) != len(scans):
        raise SequenceInputError(f"poses file {poses_file} has {len(poses)} poses, scan folder {scans_dir} has "
                                 f"{len(scans)} scans (one pose line per scan)")
    if len(scans) < 2:
        raise SequenceInputError(f"scan folder {scans_dir}: 1 scan; odometry needs at least 2")
    times = None
    if times_file is not None:
        times = read_times(times_file)
        if len(times) != len(scans):
            raise SequenceInputError(f"times file {times_file} has {len(times)} times, scan folder {scans_dir} has "
                                     f"{len(scans)} scans (one time per scan)")
    sources = {"scans": str(scans_dir), "poses": str(poses_file), "times": None if times_file is None else str(times_file)}
    return Sequence(scans=scans, poses=poses, times=times, sources=sources)


@dataclass(frozen=True)
class SequenceRun:
    """KISS-ICP's trajectory over a sequence: pose i after registering scan i."""

    poses: np.ndarray
    #: Wall-clock time of each register_frame call (ms).
    frame_ms: np.ndarray
    deskew: bool
    time_field: str | None
    #: Why deskew is off, or which field it used.
    deskew_note: str
    points_per_scan: float
    #: The settings used (auto ones resolved from the first scan) and what the range gate dropped.
    settings: IcpConfig | None = None
    derivation: dict | None = None
    gate: RangeGate | None = None
    iteration_caps: tuple[int, int] | None = None  # (min, max) of the per-scan iteration caps


def run_sequence(sequence: Sequence, config: IcpConfig, deskew: bool | None = None,
                 progress: Progress | None = None) -> SequenceRun:
    """Register every scan with one KISS-ICP pipeline (`new_kiss_icp(config, deskew=...)`).

    deskew: None decides from the first scan (deskew when it has a usable time field, module
    doc); True requires per-point times in every scan; False registers without them.
    """
    first = load_scan(sequence.scans[0])
    if deskew is None:
        deskew = first.times is not None
    if deskew and first.times is None:
        why = first.times_note or f"it has none of the per-point time fields {', '.join(POINT_TIME_FIELDS)}"
        raise SequenceInputError(f"{sequence.scans[0]}: deskew was asked for but {why}")
    if deskew:
        note = f"deskewed with the per-point field {first.time_field!r}"
    elif first.times is not None:
        note = f"deskew turned off (the scans have the per-point field {first.time_field!r})"
    else:
        note = ("no deskew: " + (first.times_note or "the scans have no per-point time field "
                                 f"({', '.join(POINT_TIME_FIELDS)})"))
    icp = new_kiss_icp(config.model_copy(update={"deskew": "kiss" if deskew else "off"}), deskew=deskew)
    n = len(sequence.scans)
    poses = np.zeros((n, 4, 4))
    frame_ms = np.zeros(n)
    points = 0
    no_times = np.zeros(0)
    for i, path in enumerate(sequence.scans):
        scan = first if i == 0 else load_scan(path)
        if deskew and scan.time_field != first.time_field:
            have = scan.time_field or scan.times_note or "no per-point time field"
            raise SequenceInputError(f"{path}: per-point times differ from the first scan's ({first.time_field!r}): "
                                     f"{have}; a sequence must be consistent (or register with deskew off)")
        points += len(scan.points)
        t0 = time.perf_counter()
        icp.register_frame(scan.points, scan.times if deskew else no_times)
        frame_ms[i] = (time.perf_counter() - t0) * 1e3
        poses[i] = icp.last_pose
        if progress is not None:
            progress(i + 1, n)
    return SequenceRun(poses=poses, frame_ms=frame_ms, deskew=bool(deskew), time_field=first.time_field if deskew else None,
                       deskew_note=note, points_per_scan=points / n, settings=icp.settings, derivation=icp.derivation,
                       gate=icp.gate_total, iteration_caps=icp.cap_range)


def stage_ms(frame_ms: np.ndarray) -> dict:
    """p50 / p99 / max of per-frame times (ms)."""
    return {"p50": float(np.percentile(frame_ms, 50)), "p99": float(np.percentile(frame_ms, 99)),
            "max": float(np.max(frame_ms))}


def evaluate_sequence(sequence: Sequence, config: IcpConfig, deskew: bool | None = None,
                      progress: Progress | None = None) -> tuple[dict, SequenceRun]:
    """Run KISS-ICP over the sequence and measure it against the reference poses.

    Returns the JSON-ready report ({"icp": trajectory_errors(...), "stage_ms": {p50, p99, max},
    "frames", "deskew", "deskew_note", "config", "inputs", ...}) and the run (the estimated poses).
    """
    run = run_sequence(sequence, config, deskew=deskew, progress=progress)
    report = {
        "icp": trajectory_errors(run.poses, sequence.poses),
        "stage_ms": stage_ms(run.frame_ms),
        "frames": len(sequence.scans),
        "points_per_scan": run.points_per_scan,
        "deskew": run.deskew,
        "time_field": run.time_field,
        "deskew_note": run.deskew_note,
        "config": (run.settings or config).model_copy(update={"deskew": "kiss" if run.deskew else "off"}).model_dump(),
        "config_given": config.model_dump(),
        "settings_derivation": run.derivation,
        "range_gate": run.gate.to_dict() if run.gate is not None else None,
        "iteration_caps": None if run.iteration_caps is None else list(run.iteration_caps),
        "inputs": dict(sequence.sources),
    }
    if sequence.times is not None:
        duration = float(sequence.times[-1] - sequence.times[0])
        report["duration_s"] = duration
        report["mean_speed_mps"] = report["icp"]["length_m"] / duration
    return report, run


__all__ = [
    "POINT_TIME_FIELDS", "Progress", "Scan", "Sequence", "SequenceInputError", "SequenceRun", "evaluate_sequence",
    "format_kitti_poses", "list_scans", "load_scan", "load_sequence", "natural_key", "read_kitti_poses", "read_times", "read_transform",
    "run_sequence", "stage_ms",
]
