"""Where sensor data enters the controller: validated, stamped, newest kept.

Sensor drivers (on the robot) or the simulator (in HIL) call `put_*` from their own thread
or step; the tick's read() calls `take()` and gets the newest scan and image, every IMU
sample since the last tick, and every rejection since the last tick. Everything is validated
on the way in: a scan, image or sample that fails its checks (sensor_data.py), arrives with a
non-monotonic stamp, or repeats the previous lidar frame is counted by error name, remembered
as the last error, handed to the tick as a `Rejection`, and dropped. It never reaches the
planner, and the tick knows that the stream delivered something it could not use (a frozen
lidar is not the same as a silent one, and both are named in the stop reason).

A frozen lidar: a frame whose points are identical to the previous frame's (with the same stamp,
or a new one) is rejected as `frozen_frame`. Real range noise makes two live frames differ in
every point; a repeated buffer is a driver or network fault.

The camera driver's intrinsics (`put_camera_info`, sensor_msgs/CameraInfo) are kept newest-only
beside the image: what the camera says it is, for the calibration check
(runtime.perception.calibration_monitor); they never reach the projection.

Bounded: one pending scan, one pending image, one pending camera info, at most `max_imu_samples` IMU samples (the
oldest are dropped and counted when the tick falls behind), at most `max_rejections` pending
rejections (the rest only counted).

`delivered` counts every piece of data that reached the inbox (accepted or refused), in the same
critical section as its effect, and `take()` hands the count over with the snapshot: a recording
(runtime.io.recording) notes it per tick, so that a replay hands the tick exactly the data the
live tick had (docs/decisions/replay.md).
"""
from __future__ import annotations

import threading
from collections import deque
from dataclasses import dataclass

import numpy as np

from runtime.common.sensor_data import (
    CameraImage, CameraInfo, ImuSample, LidarScan, SensorDataError, SensorStampChecker,
)


@dataclass(frozen=True)
class Rejection:
    """One piece of sensor data refused at the inbox."""

    stream: str  # "lidar", "camera", "imu"
    name: str  # snake_case reason: non_finite, non_monotonic_stamp, frozen_frame, ...
    message: str
    stamp_s: float | None


@dataclass(frozen=True)
class SensorSnapshot:
    scan: LidarScan | None  # newest scan since the last take(), if any
    image: CameraImage | None  # newest image since the last take(), if any
    imu: tuple[ImuSample, ...]  # all samples since the last take(), oldest first
    rejected: tuple[Rejection, ...] = ()  # data refused since the last take(), oldest first
    #: How many pieces of data had reached the inbox (accepted or refused) when this was taken.
    delivered: int = 0
    #: The newest intrinsics the camera's driver reported since the last take(), if any.
    camera_info: CameraInfo | None = None


class FrozenFrameError(SensorDataError):
    default_name = "frozen_frame"


class SensorInbox:
    def __init__(self, max_imu_samples: int = 400, max_rejections: int = 64) -> None:
        self._lock = threading.Lock()
        self._scan: LidarScan | None = None
        self._image: CameraImage | None = None
        self._camera_info: CameraInfo | None = None
        self.camera_info_accepted = 0
        self._imu: deque[ImuSample] = deque(maxlen=max_imu_samples)
        self._rejections: deque[Rejection] = deque(maxlen=max_rejections)
        self._stamps = SensorStampChecker()
        self._last_scan: LidarScan | None = None  # the last accepted frame (frozen check)
        self.error_counts: dict[str, int] = {}
        self.last_error: str | None = None
        self.accepted = {"lidar": 0, "camera": 0, "imu": 0}
        self.overwritten = {"lidar": 0, "camera": 0, "imu": 0}
        self.delivered = 0  # put_* and refusals so far (module docstring)

    def _reject(self, stream: str, exc: SensorDataError, stamp_s: float | None) -> None:
        key = f"{stream}.{exc.name}"
        with self._lock:
            self.error_counts[key] = self.error_counts.get(key, 0) + 1
            self.last_error = f"{stream}: {exc}"
            self._rejections.append(Rejection(stream, exc.name, str(exc), stamp_s))
            self.delivered += 1

    @staticmethod
    def _stamp_of(item) -> float | None:
        try:
            return float(item.stamp_s)
        except (AttributeError, TypeError, ValueError):
            return None

    def _check_not_frozen(self, scan: LidarScan) -> None:
        last = self._last_scan
        if last is None or last.num_points != scan.num_points or scan.num_points == 0:
            return
        if scan.points_m is last.points_m or np.array_equal(scan.points_m, last.points_m):
            same_stamp = scan.stamp_s == last.stamp_s
            raise FrozenFrameError(
                f"frame at {scan.stamp_s:.6f} s repeats the previous frame's {scan.num_points} points"
                + (" and its stamp" if same_stamp else ""),
                field_name="points_m",
            )

    def put_scan(self, scan: LidarScan) -> bool:
        try:
            scan.validate()
            self._check_not_frozen(scan)
            self._stamps.check("lidar", scan.stamp_s)
        except SensorDataError as exc:
            self._reject("lidar", exc, self._stamp_of(scan))
            return False
        with self._lock:
            if self._scan is not None:
                self.overwritten["lidar"] += 1
            self._scan = scan
            self._last_scan = scan
            self.accepted["lidar"] += 1
            self.delivered += 1
        return True

    def put_image(self, image: CameraImage) -> bool:
        try:
            image.validate()
            self._stamps.check("camera", image.stamp_s)
        except SensorDataError as exc:
            self._reject("camera", exc, self._stamp_of(image))
            return False
        with self._lock:
            if self._image is not None:
                self.overwritten["camera"] += 1
            self._image = image
            self.accepted["camera"] += 1
            self.delivered += 1
        return True

    def put_camera_info(self, info: CameraInfo) -> bool:
        """The camera driver's intrinsics (newest kept; no stamp order: it repeats what it says)."""
        try:
            info.validate()
        except SensorDataError as exc:
            self._reject("camera_info", exc, self._stamp_of(info))
            return False
        with self._lock:
            self._camera_info = info
            self.camera_info_accepted += 1
            self.delivered += 1
        return True

    def put_imu(self, sample: ImuSample) -> bool:
        try:
            sample.validate()
            self._stamps.check("imu", sample.stamp_s)
        except SensorDataError as exc:
            self._reject("imu", exc, self._stamp_of(sample))
            return False
        with self._lock:
            if len(self._imu) == self._imu.maxlen:
                self.overwritten["imu"] += 1
            self._imu.append(sample)
            self.accepted["imu"] += 1
            self.delivered += 1
        return True

    def take(self) -> SensorSnapshot:
        with self._lock:
            snap = SensorSnapshot(self._scan, self._image, tuple(self._imu), tuple(self._rejections),
                                  delivered=self.delivered, camera_info=self._camera_info)
            self._scan = None
            self._image = None
            self._camera_info = None
            self._imu.clear()
            self._rejections.clear()
        return snap
