"""Scans of a recorded sequence from a folder of files: `.pcd`, `.ply` or KITTI velodyne `.bin`.

* `.pcd`, `.ply`: read by `calibration.pointcloud_io` (any field layout, ascii or binary).
* `.bin`: KITTI's velodyne format, float32 little endian x, y, z, intensity per point, nothing
  else: the file size must be a multiple of 16 bytes. It has no per-point time.

The folder's scans are taken in natural name order: `scan_2` before `scan_10`, `000009` before
`000010`. Points: non-finite ones and those exactly at (0, 0, 0) are dropped; most drivers write
an invalid return (no echo) as a zero point, e.g. about 5k of the 70k points of each HDL-32 scan
in tests/data/real/hdl32_pair_small_gicp.

Per-point times (deskew): a scan's per-point time field is the first of POINT_TIME_FIELDS it
has. KISS-ICP normalises the times of a frame over their [min, max] and deskews every point to
the time of the frame's last point, so only the order of the times within the sweep matters,
not their unit or origin:

  `t`            Ouster (uint32 ns since the start of the sweep), also KISS-ICP's own choice
  `time`         Velodyne drivers (float32 s relative to the sweep start or end)
  `timestamp`    Hesai / many exporters (float64 s, absolute)
  `timestamps`   KISS-ICP's generic reader's alternative name
  `offset_time`  Livox CustomMsg converted to PCD (uint32 ns since the packet's timebase)

A field whose values are all equal carries no time (`times_note` says so). Absolute per-point
times are recognised by magnitude (ABSOLUTE_TIME_UNITS: a median of at least 1e9 read as s,
at least 1e17 as ns, i.e. after 2001): such a scan carries its own time span (`own_span_s`),
which must agree with a times file (`check_scan_time`). Relative times (a sweep is under a
second, under 1e9 in ns) carry none.
"""
from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator

import numpy as np

from runtime.odometry.pose_files import SequenceInputError

#: Per-point time fields, in the order they are looked for (see the module doc).
POINT_TIME_FIELDS = ("t", "time", "timestamp", "timestamps", "offset_time")
SCAN_SUFFIXES = (".pcd", ".ply", ".bin")
#: (lowest median, highest median, seconds per unit) of absolute per-point times.
ABSOLUTE_TIME_UNITS = ((1e9, 1e11, 1.0), (1e17, 1e20, 1e-9))
#: A scan's own time and the times file's may differ by this much (s) beyond the scan's span:
#: rounding and driver latency, not a sweep (50-100 ms) nor another clock.
TIME_AGREEMENT_TOLERANCE_S = 0.02


@dataclass(frozen=True)
class Scan:
    """One sweep's valid points, (M,3) float64, and their per-point times (M,) or None."""

    points: np.ndarray
    times: np.ndarray | None
    time_field: str | None
    #: How many points were dropped (non-finite, exactly zero, non-finite time).
    dropped: int
    #: Why `times` is None although the scan has a time field (e.g. constant values).
    times_note: str | None = None
    #: The scan's own absolute time span (s): absolute per-point times, a bag's header stamp.
    own_span_s: tuple[float, float] | None = None
    #: What gave own_span_s ("absolute per-point field 'timestamp'", "header stamp", ...).
    own_time_source: str | None = None


# ---------------------------------------------------------------------------- the folder
def natural_key(name: str) -> tuple:
    """Sort key reading runs of digits as numbers: scan_2 < scan_10, case-insensitive."""
    return tuple((0, int(part), part) if part.isdigit() else (1, 0, part.lower())
                 for part in re.split(r"(\d+)", name) if part)


def list_scans(folder: str | Path) -> list[Path]:
    """The scan files of `folder` (SCAN_SUFFIXES) in natural name order (see natural_key)."""
    d = Path(folder)
    if not d.exists():
        raise SequenceInputError(f"scan folder {d} does not exist")
    if not d.is_dir():
        raise SequenceInputError(f"scan folder {d} is not a folder")
    scans = [p for p in d.iterdir() if p.suffix.lower() in SCAN_SUFFIXES and p.is_file()]
    if not scans:
        raise SequenceInputError(f"scan folder {d} has no .pcd, .ply or .bin file")
    return sorted(scans, key=lambda p: natural_key(p.name))


# ---------------------------------------------------------------------------- one scan
def read_kitti_bin(path: str | Path) -> dict[str, np.ndarray]:
    """The fields x, y, z, intensity (float32) of a KITTI velodyne .bin file."""
    p = Path(path)
    try:
        data = p.read_bytes()
    except OSError as exc:
        raise SequenceInputError(f"{p}: cannot read file: {exc.strerror or exc}") from None
    if len(data) == 0 or len(data) % 16:
        raise SequenceInputError(f"{p}: {len(data)} bytes is not a whole number of KITTI .bin points (16 bytes "
                                 f"each: float32 x, y, z, intensity)" + (" (the file is empty)" if not data else ""))
    rec = np.frombuffer(data, dtype="<f4").reshape(-1, 4)
    return {k: rec[:, i].astype(np.float32) for i, k in enumerate(("x", "y", "z", "intensity"))}


def _read_fields(path: Path) -> dict[str, np.ndarray]:
    from calibration.pointcloud_io import PointCloudFormatError, load_point_cloud

    if path.suffix.lower() == ".bin":
        return read_kitti_bin(path)
    try:
        return load_point_cloud(path).fields
    except PointCloudFormatError as exc:
        raise SequenceInputError(str(exc)) from None


def absolute_span(times: np.ndarray) -> tuple[float, float] | None:
    """(earliest, latest) in s of per-point times that are absolute (module doc), else None."""
    median = float(np.median(times))
    for lo, hi, unit in ABSOLUTE_TIME_UNITS:
        if lo <= median < hi:
            return float(times.min()) * unit, float(times.max()) * unit
    return None


def scan_from_fields(fields: dict[str, np.ndarray], where: str) -> Scan:
    """The valid points and per-point times of a cloud's fields (module doc)."""
    xyz = np.stack([np.asarray(fields[k], dtype=np.float64) for k in ("x", "y", "z")], axis=1)
    if len(xyz) == 0:
        raise SequenceInputError(f"{where}: the point cloud is empty (0 points)")
    keep = np.isfinite(xyz).all(axis=1) & (xyz != 0.0).any(axis=1)
    time_field = next((f for f in POINT_TIME_FIELDS if f in fields), None)
    times, note, span = None, None, None
    if time_field is not None:
        t = np.asarray(fields[time_field])
        if t.ndim != 1:
            raise SequenceInputError(f"{where}: time field {time_field!r} has {t.shape[1]} values per point, expected 1")
        t = t.astype(np.float64)
        keep &= np.isfinite(t)
        if keep.any() and np.ptp(t[keep]) > 0:
            times = t[keep]
            span = absolute_span(times)
        else:
            note = f"time field {time_field!r} has the same value for every point (no time span)"
    if not keep.any():
        raise SequenceInputError(f"{where}: none of its {len(xyz)} points is valid (all are NaN/inf or exactly 0,0,0)")
    return Scan(points=np.ascontiguousarray(xyz[keep]), times=times, time_field=time_field if times is not None else None,
                dropped=int(len(xyz) - keep.sum()), times_note=note, own_span_s=span,
                own_time_source=None if span is None else f"absolute per-point field {time_field!r}")


def load_scan(path: str | Path) -> Scan:
    """Read one scan file (module doc: which points are kept, which time field is used)."""
    p = Path(path)
    fields = _read_fields(p)
    missing = [k for k in ("x", "y", "z") if k not in fields]
    if missing:
        raise SequenceInputError(f"{p}: no {'/'.join(missing)} field")
    return scan_from_fields(fields, str(p))


def check_scan_time(index: int, name: str, given_s: float, span_s: tuple[float, float] | None, source: str | None,
                    times_file: str) -> None:
    """SequenceInputError unless the times file's time of scan `index` is within the scan's own
    span (TIME_AGREEMENT_TOLERANCE_S either side); nothing to check for a scan without one."""
    if span_s is None:
        return
    lo, hi = float(span_s[0]), float(span_s[1])
    tol = TIME_AGREEMENT_TOLERANCE_S
    if not (lo - tol <= given_s <= hi + tol):
        own = f"{lo!r}" if lo == hi else f"{lo!r} to {hi!r}"
        raise SequenceInputError(f"times file {times_file} index {index}: {given_s!r} s, but scan {index} ({name}) "
                                 f"carries {own} s ({source}); they must agree within {tol:g} s")


# ---------------------------------------------------------------------------- the source
@dataclass(frozen=True)
class FolderScans:
    """The scans of a folder, read one at a time when registered."""

    folder: Path
    files: list[Path]

    @classmethod
    def open(cls, folder: str | Path) -> "FolderScans":
        return cls(Path(folder), list_scans(folder))

    def __len__(self) -> int:
        return len(self.files)

    def name(self, i: int) -> str:
        return str(self.files[i])

    @property
    def what(self) -> str:
        return f"scan folder {self.folder}"

    def own_times(self, indices: np.ndarray) -> None:
        """None: a folder's scans carry a time only in absolute per-point fields, which are read
        (and checked against a times file) as each scan is registered."""
        return None

    def iter_scans(self, indices: np.ndarray) -> Iterator[tuple[int, Scan]]:
        for i in indices:
            yield int(i), load_scan(self.files[int(i)])

    def input_files(self) -> list[Path]:
        return list(self.files)

    def describe(self) -> dict:
        return {"scans": str(self.folder), "scans_kind": "folder"}


__all__ = [
    "ABSOLUTE_TIME_UNITS", "POINT_TIME_FIELDS", "SCAN_SUFFIXES", "TIME_AGREEMENT_TOLERANCE_S", "FolderScans", "Scan",
    "absolute_span", "check_scan_time", "list_scans", "load_scan", "natural_key", "read_kitti_bin",
    "scan_from_fields",
]
