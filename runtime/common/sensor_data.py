"""Sensor data types: lidar scans, camera images, IMU samples, and their validation.

These types do not depend on MuJoCo or on any driver: the simulator and the real sensor
drivers both produce them, and the controller checks them where they enter (`read()`).
Every check that fails raises a `SensorDataError` subclass whose `.name` is a snake_case
reason (`non_finite`, `bad_shape`, ...), and the data is not used.

Ownership: the constructors convert with `np.asarray` (no copy when dtype and layout already
match), but never keep a reference to a buffer the producer could still write to: a writeable
input that would be shared is copied once, and every stored array is made read-only. A
producer that hands over a fresh array and marks it read-only (`a.flags.writeable = False`)
gets a copy-free construction.

Empty scans: a `LidarScan` with no points is valid only when the sensor says so
(`nothing_seen=True`, e.g. a lidar in an empty field beyond its max range). An empty scan
without that flag is an `EmptyScanError`: a driver that lost its points must not look like
free space to the planner.

Stamps: `LidarScan.stamp_s` is the start of the frame; point i was measured at
`stamp_s + point_time_offsets_s[i]`. `SensorStampChecker` rejects, per stream,
non-increasing, stale and future stamps.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

# Sanity limits (module constants so that drivers and tests can read them).
MAX_LIDAR_POINTS = 200_000
MAX_LIDAR_COORD_M = 1_000.0           # |x|, |y|, |z| of a lidar point
MAX_FRAME_DURATION_S = 1.0
MAX_IMAGE_SIDE_PX = 8192
ALLOWED_DISTORTION_LENGTHS = (0, 4, 5, 8, 12, 14)   # OpenCV's distortion models
MAX_GYRO_RADPS = 2000.0 * math.pi / 180.0           # a +-2000 deg/s MEMS gyro
MAX_ACCEL_MPS2 = 16.0 * 9.80665                      # a +-16 g MEMS accelerometer


class SensorDataError(ValueError):
    """Sensor data failed a check where it entered; `.name` is the snake_case reason."""

    default_name = "invalid_sensor_data"

    def __init__(self, message: str, *, name: str | None = None, field_name: str | None = None) -> None:
        self.name = name or self.default_name
        self.field_name = field_name
        where = f"{field_name}: " if field_name else ""
        super().__init__(f"[{self.name}] {where}{message}")


class NonFiniteError(SensorDataError):
    default_name = "non_finite"


class ShapeError(SensorDataError):
    default_name = "bad_shape"


class DtypeError(SensorDataError):
    default_name = "bad_dtype"


class RangeError(SensorDataError):
    default_name = "out_of_range"


class EmptyScanError(SensorDataError):
    default_name = "empty_scan"


class StampError(SensorDataError):
    """A bad stamp; names: `non_finite_stamp`, `non_monotonic_stamp`, `stale_stamp`, `future_stamp`."""

    default_name = "bad_stamp"


# ----------------------------------------------------------------------------- helpers


def _may_change(a: np.ndarray) -> bool:
    """True when someone else could still write into `a`'s memory (a or a base is writeable)."""
    obj: Any = a
    while obj is not None:
        if isinstance(obj, np.ndarray):
            if obj.flags.writeable:
                return True
            obj = obj.base
        else:
            return not isinstance(obj, bytes)   # an mmap, a bytearray, ...: mutable
    return False


def _owned_array(value: Any, dtype: np.dtype | type, what: str, *, accept_kinds: str,
                 exact: bool = False) -> np.ndarray:
    """`value` as a read-only C-contiguous array of `dtype` sharing no writeable buffer with the caller.

    accept_kinds: numpy dtype kinds accepted on input ('f' float, 'u' unsigned, 'i' int);
    integer inputs must fit the target integer type (no silent wrap-around).
    exact: the input dtype must already be `dtype`.
    """
    created_here = not isinstance(value, np.ndarray)
    try:
        src = np.asarray(value)
    except (ValueError, TypeError) as exc:
        raise ShapeError(f"cannot be read as an array: {exc}", field_name=what) from exc
    target = np.dtype(dtype)
    if src.dtype.kind not in accept_kinds or (exact and src.dtype != target):
        raise DtypeError(f"dtype {src.dtype} not accepted (expected {target.name})", field_name=what)
    if target.kind in "iu" and src.dtype != target and src.size:
        info = np.iinfo(target)
        lo, hi = int(src.min()), int(src.max())
        if lo < info.min or hi > info.max:
            raise RangeError(f"values [{lo}, {hi}] do not fit {target.name}", field_name=what)
    with np.errstate(over="ignore", invalid="ignore"):
        out = np.ascontiguousarray(src, dtype=target)
    shared = np.shares_memory(out, src)
    if shared and (_may_change(src) if not created_here else (src.base is not None and _may_change(src))):
        out = out.copy()        # the producer may reuse its buffer: take our own copy
    out.flags.writeable = False
    return out


def _check_finite(a: np.ndarray, what: str) -> None:
    if a.size and not np.isfinite(a).all():
        bad = np.argwhere(~np.isfinite(a))[0]
        raise NonFiniteError(f"non-finite value at index {tuple(int(i) for i in bad)}", field_name=what)


def _check_camera_matrix(K: np.ndarray) -> None:
    """A pinhole camera matrix: 3x3, finite, positive focal lengths, upper triangular, K[2,2] = 1."""
    if K.shape != (3, 3):
        raise ShapeError(f"expected (3, 3), got {K.shape}", field_name="K")
    _check_finite(K, "K")
    if not (K[0, 0] > 0 and K[1, 1] > 0):
        raise RangeError(f"focal lengths must be positive, got fx={K[0, 0]}, fy={K[1, 1]}", field_name="K")
    if K[1, 0] != 0 or K[2, 0] != 0 or K[2, 1] != 0 or K[2, 2] != 1:
        raise RangeError("K must be upper triangular with K[2,2] = 1", field_name="K")


def _check_stamp(stamp_s: Any, what: str = "stamp_s") -> float:
    try:
        s = float(stamp_s)
    except (TypeError, ValueError) as exc:
        raise StampError(f"not a number: {stamp_s!r}", name="non_finite_stamp", field_name=what) from exc
    if not math.isfinite(s):
        raise StampError(f"not finite: {s}", name="non_finite_stamp", field_name=what)
    if s < 0.0:
        raise StampError(f"negative stamp {s}", name="negative_stamp", field_name=what)
    return s


def _check_frame_id(frame_id: Any) -> str:
    if not isinstance(frame_id, str) or not frame_id.strip():
        raise SensorDataError(f"frame_id must be a non-empty string, got {frame_id!r}", name="bad_frame_id",
                              field_name="frame_id")
    return frame_id


# ----------------------------------------------------------------------------- lidar


@dataclass(frozen=True, eq=False)
class LidarScan:
    """One lidar frame: points in the lidar frame, each with its time within the frame.

    stamp_s: start of the frame (s). points_m: (N, 3) float32, lidar frame, metres.
    point_time_offsets_s: (N,) float32 in [0, frame_duration_s]: point i was measured at
    stamp_s + offset[i]. nothing_seen: the sensor reports an empty field of view; required
    for N == 0 and forbidden for N > 0.
    """

    stamp_s: float
    points_m: np.ndarray
    point_time_offsets_s: np.ndarray
    frame_duration_s: float
    frame_id: str = "lidar"
    nothing_seen: bool = False

    def __post_init__(self) -> None:
        set_ = object.__setattr__
        set_(self, "stamp_s", _check_stamp(self.stamp_s))
        set_(self, "frame_id", _check_frame_id(self.frame_id))
        set_(self, "points_m", _owned_array(self.points_m, np.float32, "points_m", accept_kinds="f"))
        set_(self, "point_time_offsets_s",
             _owned_array(self.point_time_offsets_s, np.float32, "point_time_offsets_s", accept_kinds="f"))
        self.validate()

    @property
    def num_points(self) -> int:
        return int(self.points_m.shape[0])

    def point_stamps_s(self) -> np.ndarray:
        """Absolute time of each point (float64)."""
        return self.stamp_s + self.point_time_offsets_s.astype(np.float64)

    def validate(self) -> None:
        """Check shapes, dtypes, finiteness and ranges; raise a SensorDataError on the first failure."""
        d = self.frame_duration_s
        if not isinstance(d, (int, float)) or not math.isfinite(d) or not (0.0 < d <= MAX_FRAME_DURATION_S):
            raise RangeError(f"must be in (0, {MAX_FRAME_DURATION_S}] s, got {d!r}", field_name="frame_duration_s")
        p, t = self.points_m, self.point_time_offsets_s
        if p.dtype != np.float32 or t.dtype != np.float32:
            raise DtypeError("points_m and point_time_offsets_s must be float32", field_name="points_m")
        if p.ndim != 2 or p.shape[1] != 3:
            raise ShapeError(f"expected (N, 3), got {p.shape}", field_name="points_m")
        n = p.shape[0]
        if t.shape != (n,):
            raise ShapeError(f"expected ({n},) to match points_m, got {t.shape}", field_name="point_time_offsets_s")
        if n > MAX_LIDAR_POINTS:
            raise RangeError(f"{n} points, more than {MAX_LIDAR_POINTS}", name="too_many_points", field_name="points_m")
        if n == 0 and not self.nothing_seen:
            raise EmptyScanError("no points and the sensor did not report nothing_seen", field_name="points_m")
        if n > 0 and self.nothing_seen:
            raise SensorDataError(f"nothing_seen is set but the scan has {n} points", name="inconsistent_empty_flag",
                                  field_name="nothing_seen")
        _check_finite(p, "points_m")
        _check_finite(t, "point_time_offsets_s")
        if n:
            big = np.abs(p).max()
            if big > MAX_LIDAR_COORD_M:
                raise RangeError(f"coordinate {float(big):.1f} m beyond {MAX_LIDAR_COORD_M} m", field_name="points_m")
            lo, hi = float(t.min()), float(t.max())
            if lo < 0.0 or hi > np.float32(d):
                raise RangeError(f"offsets span [{lo}, {hi}] s, outside [0, {d}] s",
                                 field_name="point_time_offsets_s")


# ----------------------------------------------------------------------------- camera


@dataclass(frozen=True, eq=False)
class CameraImage:
    """An RGB image with the intrinsics it was taken with.

    pixels: (H, W, 3) uint8, RGB. K: 3x3 pinhole matrix (pixel centres at integer coordinates,
    OpenCV convention). distortion: OpenCV coefficients, length 0, 4, 5, 8, 12 or 14.
    segmentation: optional (H, W) int32 ground-truth ids from the simulator, -1 = background.
    """

    stamp_s: float
    pixels: np.ndarray
    K: np.ndarray
    distortion: np.ndarray = field(default_factory=lambda: np.zeros(0))
    frame_id: str = "camera"
    segmentation: np.ndarray | None = None

    def __post_init__(self) -> None:
        set_ = object.__setattr__
        set_(self, "stamp_s", _check_stamp(self.stamp_s))
        set_(self, "frame_id", _check_frame_id(self.frame_id))
        set_(self, "pixels", _owned_array(self.pixels, np.uint8, "pixels", accept_kinds="u", exact=True))
        set_(self, "K", _owned_array(self.K, np.float64, "K", accept_kinds="fiu"))
        set_(self, "distortion", _owned_array(self.distortion, np.float64, "distortion", accept_kinds="fiu"))
        if self.segmentation is not None:
            set_(self, "segmentation", _owned_array(self.segmentation, np.int32, "segmentation", accept_kinds="iu"))
        self.validate()

    @property
    def height(self) -> int:
        return int(self.pixels.shape[0])

    @property
    def width(self) -> int:
        return int(self.pixels.shape[1])

    def validate(self) -> None:
        px = self.pixels
        if px.dtype != np.uint8:
            raise DtypeError(f"expected uint8, got {px.dtype}", field_name="pixels")
        if px.ndim != 3 or px.shape[2] != 3:
            raise ShapeError(f"expected (H, W, 3), got {px.shape}", field_name="pixels")
        h, w = px.shape[:2]
        if not (0 < h <= MAX_IMAGE_SIDE_PX and 0 < w <= MAX_IMAGE_SIDE_PX):
            raise RangeError(f"image size {w}x{h} outside 1..{MAX_IMAGE_SIDE_PX}", field_name="pixels")
        K = self.K
        _check_camera_matrix(K)
        if not (0.0 <= K[0, 2] <= w and 0.0 <= K[1, 2] <= h):
            raise RangeError(f"principal point ({K[0, 2]}, {K[1, 2]}) outside the {w}x{h} image", field_name="K")
        dist = self.distortion
        if dist.ndim != 1 or dist.shape[0] not in ALLOWED_DISTORTION_LENGTHS:
            raise ShapeError(f"expected length in {ALLOWED_DISTORTION_LENGTHS}, got shape {dist.shape}",
                             field_name="distortion")
        _check_finite(dist, "distortion")
        seg = self.segmentation
        if seg is not None:
            if seg.shape != (h, w):
                raise ShapeError(f"expected ({h}, {w}) to match pixels, got {seg.shape}", field_name="segmentation")
            if seg.size and int(seg.min()) < -1:
                raise RangeError(f"ids must be >= -1, got {int(seg.min())}", field_name="segmentation")


# ----------------------------------------------------------------------------- camera info


#: Distortion models a CameraInfo may name (sensor_msgs/distortion_models.hpp); "" when the
#: driver gives none. Only plumb_bob and rational_polynomial are OpenCV's pinhole model.
CAMERA_INFO_MODELS = ("plumb_bob", "rational_polynomial", "equidistant", "")


@dataclass(frozen=True, eq=False)
class CameraInfo:
    """The intrinsics the camera's driver reports (sensor_msgs/CameraInfo): what the camera says
    it is, to hold against the calibration the controller projects with. K and the image size
    as in CameraImage; distortion in the order of `distortion_model`."""

    stamp_s: float
    width_px: int
    height_px: int
    K: np.ndarray
    distortion: np.ndarray = field(default_factory=lambda: np.zeros(0))
    distortion_model: str = "plumb_bob"
    frame_id: str = "camera"

    def __post_init__(self) -> None:
        set_ = object.__setattr__
        set_(self, "stamp_s", _check_stamp(self.stamp_s))
        set_(self, "frame_id", _check_frame_id(self.frame_id))
        set_(self, "K", _owned_array(self.K, np.float64, "K", accept_kinds="fiu"))
        set_(self, "distortion", _owned_array(self.distortion, np.float64, "distortion", accept_kinds="fiu"))
        self.validate()

    def validate(self) -> None:
        w, h = self.width_px, self.height_px
        if not all(isinstance(v, (int, np.integer)) and 0 < v <= MAX_IMAGE_SIDE_PX for v in (w, h)):
            raise RangeError(f"image size {w}x{h} outside 1..{MAX_IMAGE_SIDE_PX}", field_name="width_px")
        K = self.K
        _check_camera_matrix(K)
        dist = self.distortion
        if dist.ndim != 1 or dist.shape[0] > 14:
            raise ShapeError(f"expected at most 14 coefficients, got shape {dist.shape}", field_name="distortion")
        _check_finite(dist, "distortion")
        if self.distortion_model not in CAMERA_INFO_MODELS:
            raise SensorDataError(f"{self.distortion_model!r} is not one of {CAMERA_INFO_MODELS}",
                                  name="bad_distortion_model", field_name="distortion_model")


# ----------------------------------------------------------------------------- IMU


@dataclass(frozen=True, eq=False)
class ImuSample:
    """One IMU sample in the IMU frame: angular rate (rad/s) and specific force (m/s^2).

    At rest with z up, accel_mps2 reads about (0, 0, +9.81).
    saturated: at least one component hit the sensor's range and was clipped to it, as a real
    MEMS part does (values within +-MAX_GYRO_RADPS / +-MAX_ACCEL_MPS2, the limit included, are
    valid; beyond it a sample is out_of_range with or without the flag: a clipping sensor never
    reports more than its range). The true rate or acceleration was at least that large.
    """

    stamp_s: float
    gyro_radps: np.ndarray
    accel_mps2: np.ndarray
    saturated: bool = False

    def __post_init__(self) -> None:
        set_ = object.__setattr__
        set_(self, "stamp_s", _check_stamp(self.stamp_s))
        set_(self, "gyro_radps", _owned_array(self.gyro_radps, np.float64, "gyro_radps", accept_kinds="fiu"))
        set_(self, "accel_mps2", _owned_array(self.accel_mps2, np.float64, "accel_mps2", accept_kinds="fiu"))
        if isinstance(self.saturated, np.bool_):
            set_(self, "saturated", bool(self.saturated))
        self.validate()

    def validate(self) -> None:
        if not isinstance(self.saturated, bool):
            raise SensorDataError(f"must be a bool, got {self.saturated!r}", name="bad_flag", field_name="saturated")
        for what, v, limit in (("gyro_radps", self.gyro_radps, MAX_GYRO_RADPS),
                               ("accel_mps2", self.accel_mps2, MAX_ACCEL_MPS2)):
            if v.shape != (3,):
                raise ShapeError(f"expected (3,), got {v.shape}", field_name=what)
            _check_finite(v, what)
            big = float(np.abs(v).max())
            if big > limit:
                raise RangeError(f"|component| {big:.3g} beyond the sensor range {limit:.3g}", field_name=what)


# ----------------------------------------------------------------------------- stamps


class SensorStampChecker:
    """Per-stream stamp gate: stamps must increase strictly, be no older than max_age_s and
    no later than now + future_tolerance_s. A rejected stamp leaves the stream's state unchanged.

    max_age_s: one age for every stream, or a dict per stream name (streams not in the dict
    get no age check; `None` disables it).
    """

    def __init__(self, max_age_s: float | dict[str, float] | None = None, future_tolerance_s: float = 0.005) -> None:
        if isinstance(max_age_s, dict):
            ages = dict(max_age_s)
        else:
            ages = max_age_s
        for v in (ages.values() if isinstance(ages, dict) else [ages]):
            if v is not None and (not math.isfinite(v) or v <= 0):
                raise ValueError(f"max_age_s must be positive and finite, got {v!r}")
        if not math.isfinite(future_tolerance_s) or future_tolerance_s < 0:
            raise ValueError(f"future_tolerance_s must be >= 0 and finite, got {future_tolerance_s!r}")
        self._ages = ages
        self._future_tol_s = float(future_tolerance_s)
        self._last: dict[str, float] = {}

    def _max_age(self, stream: str) -> float | None:
        if isinstance(self._ages, dict):
            return self._ages.get(stream)
        return self._ages

    def last_stamp(self, stream: str) -> float | None:
        return self._last.get(stream)

    def check(self, stream: str, stamp_s: float, now_s: float | None = None) -> float:
        """Accept `stamp_s` for `stream` or raise StampError; returns the stamp as float.

        now_s: the receiver's clock, for the stale/future checks (skipped when None).
        """
        s = _check_stamp(stamp_s, f"{stream}.stamp_s")
        last = self._last.get(stream)
        if last is not None and s <= last:
            raise StampError(f"stamp {s:.6f} s not after the previous {last:.6f} s", name="non_monotonic_stamp",
                             field_name=f"{stream}.stamp_s")
        if now_s is not None:
            now = float(now_s)
            if s > now + self._future_tol_s:
                raise StampError(f"stamp {s:.6f} s is {s - now:.6f} s in the future", name="future_stamp",
                                 field_name=f"{stream}.stamp_s")
            age_max = self._max_age(stream)
            if age_max is not None and now - s > age_max:
                raise StampError(f"stamp {s:.6f} s is {now - s:.6f} s old (max {age_max} s)", name="stale_stamp",
                                 field_name=f"{stream}.stamp_s")
        self._last[stream] = s
        return s

    def reset(self, stream: str | None = None) -> None:
        """Forget the last stamp of one stream (or all), e.g. after a driver restart."""
        if stream is None:
            self._last.clear()
        else:
            self._last.pop(stream, None)


__all__ = [
    "SensorDataError", "NonFiniteError", "ShapeError", "DtypeError", "RangeError", "EmptyScanError", "StampError",
    "LidarScan", "CameraImage", "CameraInfo", "ImuSample", "SensorStampChecker", "CAMERA_INFO_MODELS",
    "MAX_LIDAR_POINTS", "MAX_LIDAR_COORD_M", "MAX_GYRO_RADPS", "MAX_ACCEL_MPS2",
]
