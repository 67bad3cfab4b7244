"""Lidar odometry on a recorded sequence, measured against its reference poses.

A sequence is what users have from their own robots or public datasets:

* scans: a folder of `.pcd` / `.ply` / KITTI `.bin` files, one per sweep, in natural name order
  (scan_files.py), or the lidar topic of a ROS 2 bag, PointCloud2 or Livox CustomMsg, decoded
  and validated by the controller's own decoders (bag_scans.py);
* reference poses, KITTI (one line per scan) or TUM (stamped, matched to the scans by time) in
  the scanner's world frame with z up (pose_files.py);
* optionally a times file, one time (s) per scan.

`load_sequence` checks everything it can before any scan is registered, each failure one line:

* the counts: a KITTI poses file and a times file have as many lines as there are scans (the
  whole files: `frames` then slices scans, poses and times together);
* the times: a times file strictly increases (pose_files.py names the first line that does not);
  so do a bag's header stamps;
* the scans' own times (a bag's header stamps, absolute per-point times) agree with a times file
  (scan_files.check_scan_time; a folder's per-point times are checked as each scan is read);
* a TUM reference is associated with the scan times (times file, else the bag's stamps) by
  evo's nearest-time matching within `max_time_diff_s`; the unmatched scans are named in
  `association` and left out of the figures (they are still registered: odometry cannot skip a
  scan), and at least 2 scans must match.

Per-point times (deskew): see scan_files.py. A sequence whose first scan has no usable time
field is registered WITHOUT deskew (the result says so, `deskew: false` with the reason) rather
than with invented times (docs/decisions/odometry-deskew-times.md); every later scan must then
agree with the first.

Which time the poses are compared at: the estimate of scan i is KISS-ICP's `last_pose` after
registering it, the pose at the time of its last point when deskewed. Reference poses are
taken as given; a reference stamped at the start of the sweep differs from that by one sweep's
motion, which both trajectories share after they are expressed relative to their first pose, so
the metrics barely see it.

`evaluate_sequence` reports the project's metrics (metrics.trajectory_errors), evo's APE and RPE
(evo_eval.py) and whether the reference moves like the scans (reference_check.py).
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np

from runtime.odometry.bag_scans import BagScans, is_bag
from runtime.odometry.icp_config import IcpConfig, new_kiss_icp
from runtime.odometry.icp_settings import RangeGate
from runtime.odometry.metrics import trajectory_errors
from runtime.odometry.pose_files import (
    SequenceInputError, detect_poses_format, format_kitti_poses, frame_indices, read_kitti_poses, read_times,
    read_transform, read_tum_poses,
)
from runtime.odometry.scan_files import (
    POINT_TIME_FIELDS, FolderScans, Scan, check_scan_time, list_scans, load_scan, natural_key,
)

#: progress(done, total): called after each registered frame.
Progress = Callable[[int, int], None]


# ---------------------------------------------------------------------------- the sequence
@dataclass(frozen=True)
class Sequence:
    """A validated sequence: where the scans are (read when registered), which of them are used,
    and the reference pose of each scan that has one."""

    source: FolderScans | BagScans
    #: The scans registered (after --frames), indices into the source.
    indices: np.ndarray
    #: Reference poses (M,4,4), one per matched scan.
    poses: np.ndarray
    #: Positions in `indices` of the scans with a reference pose (all of them for KITTI).
    matched: np.ndarray
    #: Scan times (s) of `indices`: the times file, else the scans' own (bag stamps), else None.
    times: np.ndarray | None = None
    #: Where `times` came from: "times file", "header stamps" or None.
    times_source: str | None = None
    association: dict | None = None
    sources: dict = field(default_factory=dict)
    imu: dict | None = None


def open_scans(scans: str | Path, lidar_topic: str | None = None, imu_topic: str | None = None):
    """A FolderScans or, for a rosbag2 folder or .mcap file, a BagScans of `lidar_topic`."""
    p = Path(scans)
    if is_bag(p):
        return BagScans.open(p, lidar_topic)
    given = [o for o, v in (("--lidar-topic", lidar_topic), ("--imu-topic", imu_topic)) if v is not None]
    if given:
        raise SequenceInputError(f"{' and '.join(given)} go with a ROS 2 bag (a rosbag2 folder with metadata.yaml or "
                                 f"a .mcap file); {p} is not one")
    if p.is_file():
        raise SequenceInputError(f"scans {p}: a file that is not a .mcap bag; --scans takes a folder of "
                                 f".pcd/.ply/.bin scans, a rosbag2 folder or a .mcap file")
    return FolderScans.open(p)


def _reference(poses_file: Path, poses_format: str) -> tuple[str, np.ndarray | None, np.ndarray]:
    """(format, times or None, poses) of the poses file."""
    fmt = detect_poses_format(poses_file) if poses_format == "auto" else poses_format
    if fmt == "tum":
        times, poses = read_tum_poses(poses_file)
        return fmt, times, poses
    if fmt != "kitti":
        raise SequenceInputError(f"--poses-format {poses_format!r}: expected auto, kitti or tum")
    return fmt, None, read_kitti_poses(poses_file)


def _same_count(what: str, count: int, source, unit: str) -> None:
    if count != len(source):
        raise SequenceInputError(f"{what} has {count} {unit}, {source.what} has {len(source)} scans (one per scan; "
                                 f"--frames A:B slices both)")


def _scan_times(source, idx: np.ndarray, file_times: np.ndarray | None, times_file) -> tuple[np.ndarray | None, str | None]:
    """The scan times of `idx` and where they came from; a bag's stamps checked against a times file."""
    own = source.own_times(idx)
    if own is not None and file_times is not None:
        stamps, spans = own
        for n, i in enumerate(idx):
            check_scan_time(int(i), source.name(int(i)), float(file_times[i]), tuple(spans[n]),
                            "header stamp and point times", str(times_file))
    if file_times is not None:
        return file_times[idx], "times file"
    return (own[0], "header stamps") if own is not None else (None, None)


def _associate(poses_file: Path, ref_times: np.ndarray, ref_poses: np.ndarray, idx: np.ndarray,
               scan_times: np.ndarray | None, max_diff_s: float) -> tuple[np.ndarray, np.ndarray, dict]:
    """(matched positions in idx, their reference poses, the association's account)."""
    from runtime.odometry.evo_eval import associate

    if scan_times is None:
        raise SequenceInputError(f"poses file {poses_file} is TUM (stamped poses, matched to the scans by time): a "
                                 f"scan folder needs --times FILE")
    mine, theirs = associate(scan_times, ref_times, max_diff_s)
    unmatched = np.setdiff1d(np.arange(len(idx)), mine)
    if len(mine) < 2:
        raise SequenceInputError(f"poses file {poses_file}: {len(mine)} of {len(idx)} scans have a reference pose within "
                                 f"{max_diff_s:g} s (scan times {scan_times[0]:.6f}..{scan_times[-1]:.6f} s, poses "
                                 f"{ref_times[0]:.6f}..{ref_times[-1]:.6f} s); at least 2 must match")
    account = {"method": "evo.core.sync.matching_time_indices (nearest time)", "max_diff_s": max_diff_s,
               "matched": int(len(mine)), "scans": int(len(idx)),
               "unmatched_scans": [int(idx[k]) for k in unmatched],
               "max_abs_diff_s": float(np.max(np.abs(scan_times[mine] - ref_times[theirs])))}
    return mine, ref_poses[theirs], account


def load_sequence(scans: str | Path, poses_file: str | Path, times_file: str | Path | None = None, *,
                  poses_format: str = "auto", frames: slice = slice(None), lidar_topic: str | None = None,
                  imu_topic: str | None = None, max_time_diff_s: float = 0.01) -> Sequence:
    """Open the scans, read the poses (and times) and check them (module doc), before any scan is
    registered; a bag's chosen messages are decoded and validated here."""
    source = open_scans(scans, lidar_topic, imu_topic)
    poses_file = Path(poses_file)
    fmt, ref_times, ref_poses = _reference(poses_file, poses_format)
    if fmt == "kitti":
        _same_count(f"poses file {poses_file}", len(ref_poses), source, "poses")
    file_times = None
    if times_file is not None:
        file_times = read_times(times_file)
        _same_count(f"times file {times_file}", len(file_times), source, "times")
    idx = frame_indices(frames, len(source), source.what)
    times, times_source = _scan_times(source, idx, file_times, times_file)
    association = None
    if fmt == "kitti":
        matched, poses = np.arange(len(idx)), ref_poses[idx]
    else:
        matched, poses, association = _associate(poses_file, ref_times, ref_poses, idx, times, max_time_diff_s)
    imu = None
    if imu_topic is not None:
        span = (float(times[0]), float(times[-1]))
        imu = source.imu_summary(imu_topic, span)
    sources = {**source.describe(), "poses": str(poses_file), "poses_format": fmt,
               "times": None if times_file is None else str(times_file),
               "frames": {"start": int(idx[0]), "stop": int(idx[-1]) + 1, "of": len(source)}}
    return Sequence(source=source, indices=idx, poses=poses, matched=matched, times=times, times_source=times_source,
                    association=association, sources=sources, imu=imu)


# ---------------------------------------------------------------------------- the run
@dataclass(frozen=True)
class SequenceRun:
    """KISS-ICP's trajectory over a sequence: pose k after registering scan indices[k]."""

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


def _deskew_choice(first: Scan, name: str, deskew: bool | None) -> tuple[bool, str]:
    """(deskew, why) from the first scan (module doc)."""
    if deskew is None:
        deskew = first.times is not None
    if deskew and first.times is None:
        why = first.times_note or f"it has none of the per-point time fields {', '.join(POINT_TIME_FIELDS)}"
        raise SequenceInputError(f"{name}: deskew was asked for but {why}")
    if deskew:
        return True, f"deskewed with the per-point field {first.time_field!r}"
    if first.times is not None:
        return False, f"deskew turned off (the scans have the per-point field {first.time_field!r})"
    return False, "no deskew: " + (first.times_note or f"the scans have no per-point time field "
                                   f"({', '.join(POINT_TIME_FIELDS)})")


def _checked(sequence: Sequence, k: int, i: int, scan: Scan, first: Scan | None, deskew: bool) -> None:
    """A scan's per-point times agree with the first scan's and its own time with the times file."""
    name = sequence.source.name(i)
    if first is not None and deskew and scan.time_field != first.time_field:
        have = scan.time_field or scan.times_note or "no per-point time field"
        raise SequenceInputError(f"{name}: per-point times differ from the first scan's ({first.time_field!r}): "
                                 f"{have}; a sequence must be consistent (or register with deskew off)")
    if sequence.times_source == "times file" and isinstance(sequence.source, FolderScans):
        check_scan_time(i, name, float(sequence.times[k]), scan.own_span_s, scan.own_time_source,
                        sequence.sources.get("times"))


def run_sequence(sequence: Sequence, config: IcpConfig, deskew: bool | None = None,
                 progress: Progress | None = None) -> SequenceRun:
    """Register every chosen scan with one KISS-ICP pipeline (`new_kiss_icp(config, deskew=...)`).

    deskew: None decides from the first scan (deskew when it has a usable time field, module
    doc); True requires per-point times in every scan; False registers without them.
    """
    n = len(sequence.indices)
    poses, frame_ms = np.zeros((n, 4, 4)), np.zeros(n)
    points, first, icp, note = 0, None, None, ""
    no_times = np.zeros(0)
    for k, (i, scan) in enumerate(sequence.source.iter_scans(sequence.indices)):
        if first is None:
            deskew, note = _deskew_choice(scan, sequence.source.name(i), deskew)
            icp = new_kiss_icp(config.model_copy(update={"deskew": "kiss" if deskew else "off"}), deskew=deskew)
        _checked(sequence, k, i, scan, first, deskew)
        first = first or scan
        points += len(scan.points)
        t0 = time.perf_counter()
        icp.register_frame(scan.points, scan.times if deskew else no_times)
        frame_ms[k] = (time.perf_counter() - t0) * 1e3
        poses[k] = icp.last_pose
        if progress is not None:
            progress(k + 1, n)
    return SequenceRun(poses=poses, frame_ms=frame_ms, deskew=bool(deskew), time_field=first.time_field if deskew else None,
                       deskew_note=note, points_per_scan=points / n, settings=icp.settings, derivation=icp.derivation,
                       gate=icp.gate_total, iteration_caps=icp.cap_range)


def stage_ms(frame_ms: np.ndarray) -> dict:
    """p50 / p99 / max of per-frame times (ms)."""
    return {"p50": float(np.percentile(frame_ms, 50)), "p99": float(np.percentile(frame_ms, 99)),
            "max": float(np.max(frame_ms))}


def evaluate_sequence(sequence: Sequence, config: IcpConfig, deskew: bool | None = None,
                      progress: Progress | None = None, with_evo: bool = True) -> tuple[dict, SequenceRun]:
    """Run KISS-ICP over the sequence and measure it against the reference poses.

    Returns the JSON-ready report ({"icp": trajectory_errors(...), "evo": evo_eval.evo_figures(...),
    "reference_consistency": reference_check.reference_consistency(...), "stage_ms", "frames",
    "deskew", "deskew_note", "config", "inputs", ...}) and the run (the estimated poses).
    """
    from runtime.odometry.reference_check import reference_consistency

    run = run_sequence(sequence, config, deskew=deskew, progress=progress)
    est = run.poses[sequence.matched]
    labels = sequence.indices[sequence.matched]
    report = {
        "icp": trajectory_errors(est, sequence.poses),
        "reference_consistency": reference_consistency(est, sequence.poses, scan_labels=labels),
        "stage_ms": stage_ms(run.frame_ms),
        "frames": len(sequence.indices),
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
        "scan_times": sequence.times_source,
        "association": sequence.association,
        "imu": sequence.imu,
    }
    if with_evo:
        from runtime.odometry.evo_eval import evo_figures, require_evo

        report["evo"] = {"version": require_evo(), **evo_figures(est, sequence.poses)}
    if sequence.times is not None:
        duration = float(sequence.times[-1] - sequence.times[0])
        report["duration_s"] = duration
        report["mean_speed_mps"] = report["icp"]["length_m"] / duration
    return report, run


__all__ = [
    "POINT_TIME_FIELDS", "Progress", "Scan", "Sequence", "SequenceInputError", "SequenceRun", "evaluate_sequence",
    "format_kitti_poses", "list_scans", "load_scan", "load_sequence", "natural_key", "open_scans", "read_kitti_poses",
    "read_times", "read_transform", "run_sequence", "stage_ms",
]
