"""The text inputs of a recorded sequence: reference poses (KITTI or TUM), scan times, a 4x4
transform, and the `--frames A:B` slice.

Poses, in one of two formats (`detect_poses_format` tells them apart by the count of numbers on
the first data line; `--poses-format` forces one):

* KITTI: one line per scan, 12 numbers, the top three rows of the 4x4 pose of the scanner in a
  world frame with z up, row-major (`r11 r12 r13 tx r21 r22 r23 ty r31 r32 r33 tz`), so that
  `p_world = T p_scan`. Line i is scan i: the poses carry no time.
* TUM: `t x y z qx qy qz qw` per line: a time (s), the position and the unit quaternion of the
  same pose (Hamilton, scalar last, as evo and the TUM RGB-D tools write it). The times must
  strictly increase; the poses are matched to the scans by time (sequence.py), not by line.

Blank lines and lines starting with `#` are skipped; anything else must be finite numbers, a
KITTI rotation orthonormal (within `metrics.ROTATION_TOLERANCE`) with determinant +1, a TUM
quaternion of norm 1 within QUATERNION_NORM_TOLERANCE (then normalised).

Times file: one time (s) per line, strictly increasing, one per scan.

Every problem is a SequenceInputError whose message is one line naming the file, the line (and
the index of the pose or time, counted from 0 over the data lines) and what is wrong.
"""
from __future__ import annotations

import math
import re
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from runtime.odometry.metrics import rotation_problem

#: What to install for the parts of `dct odom eval` that need the `eval` extra (evo, rosbags).
EVAL_EXTRA = "pip install dct-controller[eval]"
#: |q| may differ from 1 by this much (a quaternion written with 4 decimals is within 2e-4).
QUATERNION_NORM_TOLERANCE = 1e-3
POSES_FORMATS = ("kitti", "tum")
_FORMAT_WIDTH = {"kitti": 12, "tum": 8}


class SequenceInputError(ValueError):
    """A sequence's folder, scan, bag, poses or times file is missing, malformed or inconsistent;
    the message is one line naming the input (and line or index) and what is wrong."""


# ---------------------------------------------------------------------------- lines and numbers
def text_lines(path: Path, what: str) -> list[tuple[int, str]]:
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


def numbers(path: Path, what: str, lineno: int, text: str, count: int) -> list[float]:
    """The `count` finite numbers of one line (SequenceInputError naming the line otherwise)."""
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


def _increasing(path: Path, what: str, lines: list[tuple[int, str]], times: np.ndarray) -> None:
    """SequenceInputError naming the first line (and index) whose time is not after the previous."""
    bad = np.flatnonzero(~(np.diff(times) > 0))
    if len(bad):
        k = int(bad[0]) + 1
        raise SequenceInputError(f"{what} {path} line {lines[k][0]} (index {k}): {float(times[k])!r} is not after the "
                                 f"previous time {float(times[k - 1])!r} (times must be strictly increasing)")


# ---------------------------------------------------------------------------- poses
def detect_poses_format(path: str | Path) -> str:
    """"kitti" (12 numbers on the first data line) or "tum" (8); SequenceInputError otherwise."""
    path = Path(path)
    lines = text_lines(path, "poses file")
    if not lines:
        raise SequenceInputError(f"poses file {path}: no poses (the file is empty)")
    lineno, text = lines[0]
    width = len(text.split())
    for fmt, w in _FORMAT_WIDTH.items():
        if width == w:
            return fmt
    raise SequenceInputError(f"poses file {path} line {lineno}: {width} values, neither KITTI (12 numbers: 3x4 "
                             f"pose) nor TUM (8: t x y z qx qy qz qw); --poses-format names the format")


def read_kitti_poses(path: str | Path) -> np.ndarray:
    """Poses from a KITTI-format file (module doc) as (N,4,4)."""
    path = Path(path)
    lines = text_lines(path, "poses file")
    if not lines:
        raise SequenceInputError(f"poses file {path}: no poses (the file is empty)")
    poses = np.zeros((len(lines), 4, 4))
    poses[:, 3, 3] = 1.0
    for k, (lineno, text) in enumerate(lines):
        poses[k, :3, :] = np.array(numbers(path, "poses file", lineno, text, 12)).reshape(3, 4)
        problem = rotation_problem(poses[k, :3, :3])
        if problem:
            raise SequenceInputError(f"poses file {path} line {lineno}: the {problem}")
    return poses


def read_tum_poses(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """(times (N,), poses (N,4,4)) from a TUM-format file (module doc)."""
    path = Path(path)
    lines = text_lines(path, "poses file")
    if not lines:
        raise SequenceInputError(f"poses file {path}: no poses (the file is empty)")
    rows = np.array([numbers(path, "poses file", n, text, 8) for n, text in lines])
    norms = np.linalg.norm(rows[:, 4:], axis=1)
    bad = np.flatnonzero(~(np.abs(norms - 1.0) <= QUATERNION_NORM_TOLERANCE))
    if len(bad):
        k = int(bad[0])
        raise SequenceInputError(f"poses file {path} line {lines[k][0]}: quaternion norm {norms[k]:.6g} is not 1 "
                                 f"(within {QUATERNION_NORM_TOLERANCE:g}); TUM lines are t x y z qx qy qz qw")
    _increasing(path, "poses file", lines, rows[:, 0])
    poses = np.repeat(np.eye(4)[None], len(rows), axis=0)
    poses[:, :3, :3] = Rotation.from_quat(rows[:, 4:] / norms[:, None]).as_matrix()
    poses[:, :3, 3] = rows[:, 1:4]
    return rows[:, 0], poses


def format_kitti_poses(poses: np.ndarray) -> str:
    """(N,4,4) poses as KITTI lines (12 numbers, %.9e: orthonormal to 1e-9 when read back)."""
    return "".join(" ".join(f"{v:.9e}" for v in T[:3, :].ravel()) + "\n" for T in np.asarray(poses))


def format_tum_poses(times: np.ndarray, poses: np.ndarray) -> str:
    """(N,) times and (N,4,4) poses as TUM lines (t x y z qx qy qz qw)."""
    q = Rotation.from_matrix(np.asarray(poses)[:, :3, :3]).as_quat()
    return "".join(f"{t:.9f} " + " ".join(f"{v:.9e}" for v in (*T[:3, 3], *qq)) + "\n"
                   for t, T, qq in zip(times, poses, q))


# ---------------------------------------------------------------------------- times, transform
def read_times(path: str | Path) -> np.ndarray:
    """Scan times (s) from a file with one number per line, strictly increasing."""
    path = Path(path)
    lines = text_lines(path, "times file")
    if not lines:
        raise SequenceInputError(f"times file {path}: no times (the file is empty)")
    times = np.array([numbers(path, "times file", n, text, 1)[0] for n, text in lines])
    _increasing(path, "times file", lines, times)
    return times


def read_transform(path: str | Path, what: str = "transform file") -> np.ndarray:
    """A 4x4 rigid transform from a text file: 4 numbers on each of 4 lines (or the top 3)."""
    path = Path(path)
    lines = text_lines(path, what)
    if len(lines) not in (3, 4):
        raise SequenceInputError(f"{what} {path}: expected a 4x4 matrix (4 numbers on each of 4 lines, or the top 3), "
                                 f"got {len(lines)} lines")
    T = np.eye(4)
    T[:len(lines)] = [numbers(path, what, n, text, 4) for n, text in lines]
    if np.abs(T[3] - (0.0, 0.0, 0.0, 1.0)).max() > 1e-9:
        raise SequenceInputError(f"{what} {path} line {lines[3][0]}: the last row must be 0 0 0 1")
    problem = rotation_problem(T[:3, :3])
    if problem:
        raise SequenceInputError(f"{what} {path}: the top-left 3x3 is not a rotation: {problem}")
    return T


# ---------------------------------------------------------------------------- --frames
_SLICE = re.compile(r"\s*([+-]?\d+)?\s*:\s*([+-]?\d+)?\s*")


def parse_frames(text: str) -> slice:
    """`A:B` (either optional, negative counts from the end) as slice(A, B): Python's semantics."""
    m = _SLICE.fullmatch(text or "")
    if m is None:
        raise SequenceInputError(f"--frames {text!r}: expected A:B (whole numbers, either optional, e.g. 200:320, "
                                 f"100: or :-10)")
    start, stop = (None if g is None else int(g) for g in m.groups())
    return slice(start, stop)


def frame_indices(frames: slice, count: int, what: str) -> np.ndarray:
    """The indices of `range(count)[frames]`; SequenceInputError when fewer than 2 remain."""
    idx = np.arange(count)[frames]
    if len(idx) < 2:
        shown = f"{'' if frames.start is None else frames.start}:{'' if frames.stop is None else frames.stop}"
        raise SequenceInputError(f"--frames {shown} keeps {len(idx)} of the {count} scans of {what}; odometry needs "
                                 f"at least 2")
    return idx


__all__ = [
    "EVAL_EXTRA", "POSES_FORMATS", "QUATERNION_NORM_TOLERANCE", "SequenceInputError", "detect_poses_format", "format_kitti_poses",
    "format_tum_poses", "frame_indices", "numbers", "parse_frames", "read_kitti_poses", "read_times",
    "read_transform", "read_tum_poses", "text_lines",
]
