"""Where sensor data enters the controller: validated, stamped, newest kept.

Sensor drivers (on the robot) or the simulator (in HIL) call `put_*` from their own thread
or step; the tick's read() calls `take()` and gets the newest scan and image and every IMU
sample since the last tick. Everything is validated on the way in: a scan, image or sample
that fails its checks (sensor_data.py) or arrives with a non-monotonic stamp is counted by
error name, remembered as the last error, and dropped. It never reaches the planner.

Bounded: one pending scan, one pending image, and at most `max_imu_samples` IMU samples
(the oldest are dropped and counted when the tick falls behind).
"""
from __future__ import annotations

import threading
from collections import deque
from dataclasses import dataclass

from runtime.sensor_data import CameraImage, ImuSample, LidarScan, SensorDataError, SensorStampChecker


@dataclass(frozen=True)
class SensorSnapshot:
    scan: LidarScan | None  # newest scan since the last take(), if any
    image: CameraImage | None  # newest image since the last take(), if any
    imu: tuple[ImuSample, ...]  # all samples since the last take(), oldest first


class SensorInbox:
    def __init__(self, max_imu_samples: int = 400) -> None:
        self._lock = threading.Lock()
        self._scan: LidarScan | None = None
        self._image: CameraImage | None = None
        self._imu: deque[ImuSample] = deque(maxlen=max_imu_samples)
        self._stamps = SensorStampChecker()
        self.error_counts: dict[str, int] = {}
        self.last_error: str | None = None
        self.accepted = {"lidar": 0, "camera": 0, "imu": 0}
        self.overwritten = {"lidar": 0, "camera": 0, "imu": 0}

    def _reject(self, stream: str, exc: SensorDataError) -> None:
        key = f"{stream}.{exc.name}"
        self.error_counts[key] = self.error_counts.get(key, 0) + 1
        self.last_error = f"{stream}: {exc}"

    def put_scan(self, scan: LidarScan) -> bool:
        try:
            scan.validate()
            self._stamps.check("lidar", scan.stamp_s)
        except SensorDataError as exc:
            self._reject("lidar", exc)
            return False
        with self._lock:
            if self._scan is not None:
                self.overwritten["lidar"] += 1
            self._scan = scan
            self.accepted["lidar"] += 1
        return True

    def put_image(self, image: CameraImage) -> bool:
        try:
            image.validate()
            self._stamps.check("camera", image.stamp_s)
        except SensorDataError as exc:
            self._reject("camera", exc)
            return False
        with self._lock:
            if self._image is not None:
                self.overwritten["camera"] += 1
            self._image = image
            self.accepted["camera"] += 1
        return True

    def put_imu(self, sample: ImuSample) -> bool:
        try:
            sample.validate()
            self._stamps.check("imu", sample.stamp_s)
        except SensorDataError as exc:
            self._reject("imu", exc)
            return False
        with self._lock:
            if len(self._imu) == self._imu.maxlen:
                self.overwritten["imu"] += 1
            self._imu.append(sample)
            self.accepted["imu"] += 1
        return True

    def take(self) -> SensorSnapshot:
        with self._lock:
            snap = SensorSnapshot(self._scan, self._image, tuple(self._imu))
            self._scan = None
            self._image = None
            self._imu.clear()
        return snap
