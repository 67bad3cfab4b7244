"""A recorded odometry run: one row per controller tick of wheel distances, gyro and a reference pose.

Written by `dct odom eval --record RUN.npz` (HIL, reference = the simulator's ground truth; a
recorder on the robot, with KISS-ICP as the reference, comes with the controller process of
roadmap step 7); read by `dct calibrate wheels` to fit the effective track width and the wheel
scale (calibration.wheel_odometry).

File format: an .npz (numpy zip) holding only plain arrays, so it loads with allow_pickle=False
(a run file from elsewhere cannot run code when it is read):

==================  ==========  ===================================================================
member              shape       meaning
==================  ==========  ===================================================================
format_version      ()  int     FORMAT_VERSION
t_s                 (N,) float  tick time, s, strictly increasing
left_wheel_m        (N,) float  cumulative left wheel distance (0x311), m
right_wheel_m       (N,) float  cumulative right wheel distance (0x311), m
gyro_z_radps        (N,) float  mean gyro z over the tick, rad/s; NaN where the tick had no sample
ref_pose            (N,3) float reference x (m), y (m), yaw (rad) in a fixed frame
reference           ()  text    "ground_truth" or "icp"
robot               ()  text    robot name (the calibration file's `robot`)
source              ()  text    where the run comes from (scenario and seed, recording name)
==================  ==========  ===================================================================

Float arrays may be float32 or float64 (held as float64). Every number must be finite except the
NaN of a tick without gyro samples; N >= 2. Any other member is refused (a typo, or a newer
format this code does not know). Every problem raises RunLogError, one line naming the file, the
member and what was wrong; loading never raises anything else, whatever the bytes.
"""
from __future__ import annotations

import io
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from calibration.outputs import atomic_write_bytes, check_output_path

FORMAT_VERSION = 1
REFERENCES = ("ground_truth", "icp")
ARRAY_FIELDS = ("t_s", "left_wheel_m", "right_wheel_m", "gyro_z_radps", "ref_pose")
TEXT_FIELDS = ("reference", "robot", "source")
#: Text members longer than this are refused (a name or a one-line description, not a document).
MAX_TEXT_CHARS = 1000


class RunLogError(ValueError):
    """A recorded odometry run that is missing, unreadable or invalid; one line naming file and field."""


@dataclass(frozen=True)
class OdometryRunLog:
    """One row per controller tick (see the module doc for the fields). Validated on construction;
    the arrays are float64 copies that cannot be written to."""

    t_s: np.ndarray
    left_wheel_m: np.ndarray
    right_wheel_m: np.ndarray
    gyro_z_radps: np.ndarray
    ref_pose: np.ndarray
    reference: str
    robot: str
    source: str

    def __post_init__(self) -> None:
        for name, value in _validated(self, "odometry run").items():
            object.__setattr__(self, name, value)

    def __len__(self) -> int:
        return len(self.t_s)

    @property
    def duration_s(self) -> float:
        return float(self.t_s[-1] - self.t_s[0])

    def save(self, path: str | Path, *, overwrite: bool = False) -> Path:
        """Write the run to `path` (.npz) atomically; an existing file is refused unless overwrite=True.

        OutputPathError (calibration.outputs) when the path cannot or must not be written.
        """
        p = check_output_path(path, what="odometry run", overwrite=overwrite)
        buf = io.BytesIO()
        members = {name: getattr(self, name) for name in ARRAY_FIELDS}
        members.update({name: np.array(getattr(self, name), dtype=np.str_) for name in TEXT_FIELDS})
        np.savez_compressed(buf, format_version=np.array(FORMAT_VERSION, dtype=np.int64), **members)
        return atomic_write_bytes(p, buf.getvalue())

    @classmethod
    def load(cls, path: str | Path) -> "OdometryRunLog":
        return load_run_log(path)


def load_run_log(path: str | Path) -> OdometryRunLog:
    """Read and validate a run file; any problem (whatever the bytes) raises RunLogError."""
    where = f"odometry run {path}"
    raw = _read_members(Path(path), where)
    version = raw.pop("format_version", None)
    if version is None:
        raise RunLogError(f"{where}: format_version: missing (not a recorded odometry run?)")
    if version.shape != () or version.dtype.kind not in "iu" or int(version) != FORMAT_VERSION:
        raise RunLogError(f"{where}: format_version: must be the integer {FORMAT_VERSION} "
                          f"(got {_show(version)}); a newer recorder wrote it, or it is not a run file")
    unknown = sorted(set(raw) - set(ARRAY_FIELDS) - set(TEXT_FIELDS))
    if unknown:
        shown = ", ".join(ascii(name) for name in unknown[:5]) + (f" and {len(unknown) - 5} more" if len(unknown) > 5 else "")
        raise RunLogError(f"{where}: unknown member(s) {shown} (expected {', '.join(ARRAY_FIELDS + TEXT_FIELDS)})")
    missing = [name for name in ARRAY_FIELDS + TEXT_FIELDS if name not in raw]
    if missing:
        raise RunLogError(f"{where}: {', '.join(missing)}: missing")
    values = {}
    for name in TEXT_FIELDS:
        a = raw[name]
        if a.shape != () or a.dtype.kind != "U":
            raise RunLogError(f"{where}: {name}: must be a text value (got an array of {a.dtype} with shape {a.shape})")
        values[name] = str(a)
    for name in ARRAY_FIELDS:
        values[name] = raw[name]
    try:
        return OdometryRunLog(**values)
    except RunLogError as exc:  # name the file instead of "odometry run"
        raise RunLogError(f"{where}: {str(exc).removeprefix('odometry run: ')}") from None


# ---------------------------------------------------------------------------- reading and checks
def _read_members(path: Path, where: str) -> dict[str, np.ndarray]:
    """Every member of the .npz as an array. np.load on untrusted bytes raises a zoo of exception
    types (BadZipFile, zlib.error, EOFError, ValueError, OSError, NotImplementedError for an
    unknown compression, MemoryError for a header that claims a huge shape, ...): in this block
    all of them mean "not a readable run file" and become a RunLogError."""
    if not path.is_file():
        raise RunLogError(f"{where}: no such file" if not path.exists() else f"{where}: is not a file")
    try:
        with open(path, "rb") as f:
            magic = f.read(6)
    except OSError as exc:
        raise RunLogError(f"{where}: cannot read file: {exc.strerror or exc}") from None
    if magic == b"\x93NUMPY":
        raise RunLogError(f"{where}: is a single .npy array, not an .npz run file")
    if not magic.startswith(b"PK"):  # np.load would try it as a pickle and say so: misleading
        raise RunLogError(f"{where}: is not an .npz file (no zip signature at the start)")
    try:
        loaded = np.load(path, allow_pickle=False)
    except Exception as exc:  # noqa: BLE001 - see the docstring
        raise RunLogError(f"{where}: cannot be read as an .npz run file ({_exc_text(exc)})") from None
    if not isinstance(loaded, np.lib.npyio.NpzFile):
        raise RunLogError(f"{where}: is a single .npy array, not an .npz run file")
    try:
        with loaded as npz:
            members = {name: npz[name] for name in npz.files}
    except Exception as exc:  # noqa: BLE001 - see the docstring
        raise RunLogError(f"{where}: cannot be read as an .npz run file ({_exc_text(exc)})") from None
    for name, value in members.items():
        if not isinstance(value, np.ndarray):  # NpzFile hands out a member without the .npy header as bytes
            raise RunLogError(f"{where}: {ascii(name)[1:-1]}: is not a numpy array (no .npy header)")
    return members


def _exc_text(exc: BaseException) -> str:
    return " ".join(str(exc).split())[:200] or type(exc).__name__


def _show(a: np.ndarray) -> str:
    return np.array2string(np.asarray(a).ravel()[:3], threshold=3, precision=6)


def _validated(run: OdometryRunLog, where: str) -> dict:
    """The run's fields checked and normalised (float64, read-only); RunLogError naming the field."""
    out: dict = {}
    for name in TEXT_FIELDS:
        value = getattr(run, name)
        if not isinstance(value, str):
            raise RunLogError(f"{where}: {name}: must be text (got {type(value).__name__})")
        if len(value) > MAX_TEXT_CHARS:
            raise RunLogError(f"{where}: {name}: longer than {MAX_TEXT_CHARS} characters ({len(value)})")
        if name != "source" and not value.strip():
            raise RunLogError(f"{where}: {name}: must not be empty")
        out[name] = value
    if out["reference"] not in REFERENCES:
        raise RunLogError(f"{where}: reference: must be one of {', '.join(REFERENCES)} (got {out['reference']!r})")
    n = None
    for name in ARRAY_FIELDS:  # t_s first: it sets N
        a = np.asarray(getattr(run, name))
        if a.dtype.kind != "f" or a.dtype.itemsize < 4:
            raise RunLogError(f"{where}: {name}: must be float32 or float64 numbers (got {a.dtype})")
        if n is None:
            if a.ndim != 1:
                raise RunLogError(f"{where}: {name}: must be one value per tick, shape (N,) (got shape {a.shape})")
            if len(a) < 2:
                raise RunLogError(f"{where}: {name}: needs at least 2 ticks (got {len(a)})")
            n = len(a)
        want, want_text = ((n, 3), "(N, 3)") if name == "ref_pose" else ((n,), "(N,)")
        if a.shape != want:
            raise RunLogError(f"{where}: {name}: must have shape {want_text} with N = {n} ticks like t_s "
                              f"(got {a.shape})")
        a = np.array(a, dtype=np.float64)  # a copy: the caller's array may change later
        bad = np.isinf(a) if name == "gyro_z_radps" else ~np.isfinite(a)
        if bad.any():
            i = int(np.argwhere(bad)[0][0])
            what = "finite or NaN (a tick without gyro samples)" if name == "gyro_z_radps" else "finite"
            raise RunLogError(f"{where}: {name}: must be {what}, tick {i} is {a[i].tolist()}")
        a.setflags(write=False)
        out[name] = a
    steps = np.diff(out["t_s"])
    if (steps <= 0).any():
        i = int(np.argmax(steps <= 0))
        raise RunLogError(f"{where}: t_s: must be strictly increasing, tick {i + 1} ({out['t_s'][i + 1]!r} s) "
                          f"does not follow tick {i} ({out['t_s'][i]!r} s)")
    return out


__all__ = ["OdometryRunLog", "RunLogError", "load_run_log", "FORMAT_VERSION", "REFERENCES"]
