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
every point; a repeated buffer is a driver or network fault. Frames in which no ray returned
(every point at (0, 0, 0), as a Livox reports them) are alike without being frozen: they pass
here, and the input monitor judges them blind.

The camera driver's intrinsics (`put_camera_info`, sensor_msgs/CameraInfo) are kept newest-only
beside the image: what the camera says it is, for the calibration check
(runtime.perception.calibration_monitor); they never reach the projection.

Bounded: one pending scan, one pending image, one pending camera info, at most `max_imu_samples` IMU samples (the
oldest are dropped and counted when the tick falls behind), at most `max_rejections` pending
rejections (the rest only counted).

The system clock stepped (NTP, a person's `date -s`): sensor stamps are ROS time, the system
clock, and the drivers stamp with it, while the loop runs on a clock that never jumps
(runtime.loop.clocks.EpochMonotonicClock: the system clock's offset read once, at start). Given that
clock (`stamp_clock`), the inbox reads how far the system clock has stepped since (its
`system_step_s()`, a step being a change of at least CLOCK_STEP_MIN_S) and puts every stamp back onto
the loop's clock before any check, so a step neither makes every frame stale (a step back) nor
every frame "from the future" (forward), and a stream that stops is still seen to stop. Each step
is counted, logged and kept (`clock_steps`, `last_clock_step`). Data stamped before the step that
arrives after it (in flight) is told apart for STAMPED_BEFORE_STEP_S: its stamp put back with
the step before lies nearer the loop's now than with the step after (a step is 50 ms or more, a
driver's latency a few ms). Beyond that, a stamp more than FUTURE_REFUSED_S ahead of the loop's
clock is refused here (`future_stamp`), one behind the last as out of order.

`delivered` counts every piece of data that reached the inbox (accepted or refused), in the same
critical section as its effect, and `take()` hands the count over with the snapshot: a recording
(runtime.io.recording) notes it per tick, so that a replay hands the tick exactly the data the
live tick had (docs/decisions/replay.md).
"""
from __future__ import annotations

import logging
import threading
from collections import deque
from dataclasses import dataclass, replace
from typing import Protocol

import numpy as np

from runtime.common.sensor_data import (
    CameraImage, CameraInfo, ImuSample, LidarScan, SensorDataError, SensorStampChecker, StampError,
)

log = logging.getLogger(__name__)

#: A change of the system clock against the loop's clock at least this large is a step. NTP
#: slews smaller offsets (chrony and ntpd step only above 0.1-0.128 s), and slewing moves the
#: monotonic clock with it, so below this the offset does not change.
CLOCK_STEP_MIN_S = 0.05
#: For this long after a step (s), data whose stamp fits the clock before the step better than
#: the clock after it was stamped before the step (it was in flight) and is put back with that.
STAMPED_BEFORE_STEP_S = 1.0
#: With a stamp clock, data stamped further than this ahead of the loop's clock is refused at the
#: inbox (the watchdogs judge the finer future tolerance per stream, runtime.safety.input_monitor).
FUTURE_REFUSED_S = 0.1


class StampClock(Protocol):
    """The loop's clock as the inbox reads it (runtime.loop.clocks.EpochMonotonicClock; a
    lockstep episode's clock emulates the system clock's steps)."""

    def now(self) -> float: ...

    def system_step_s(self) -> float:
        """How far the system clock (the stamps' clock) has stepped against the loop's since start."""


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
    def __init__(self, max_imu_samples: int = 400, max_rejections: int = 64,
                 stamp_clock: StampClock | None = None) -> None:
        self._lock = threading.Lock()
        #: The loop's clock: stamps are put back onto it across steps of the system clock, and data
        #: stamped ahead of it refused (module docstring). None: stamps are taken as they come.
        self.stamp_clock = stamp_clock
        self.clock_step_s = 0.0  # the system clock's step in force (s), what the stamps are moved back by
        self.clock_steps = 0
        self.last_clock_step: str | None = None
        self._step_before: float | None = None  # the step in force before the last one
        self._stepped_at_s = -1e18
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
            if not np.any(scan.points_m):
                return  # every ray without a return (a Livox's (0, 0, 0)): a blind frame, judged as one
            same_stamp = scan.stamp_s == last.stamp_s
            raise FrozenFrameError(
                f"frame at {scan.stamp_s:.6f} s repeats the previous frame's {scan.num_points} points"
                + (" and its stamp" if same_stamp else ""),
                field_name="points_m",
            )

    def _on_loop_clock(self, item):
        """(item with its stamp on the loop's clock, the loop's now); (item, None) without a stamp clock."""
        clock = self.stamp_clock
        if clock is None:
            return item, None
        step = clock.system_step_s()
        now = clock.now()
        if abs(step - self.clock_step_s) >= CLOCK_STEP_MIN_S:
            self._clock_stepped(step, now)
        stamp = item.stamp_s - self.clock_step_s
        if self._step_before is not None and now - self._stepped_at_s < STAMPED_BEFORE_STEP_S:
            before = item.stamp_s - self._step_before  # stamped before the step, arrived after it
            if abs(now - before) < abs(now - stamp):
                stamp = before
        if stamp != item.stamp_s:
            item = replace(item, stamp_s=stamp)
        return item, now

    def _clock_stepped(self, step: float, now_s: float) -> None:
        said = (f"the system clock stepped {step - self.clock_step_s:+.3f} s (now {step:+.3f} s from the loop's "
                "clock): sensor stamps are moved back onto the loop's clock")
        with self._lock:
            self._step_before, self._stepped_at_s = self.clock_step_s, now_s
            self.clock_step_s = step
            self.clock_steps += 1
            self.last_clock_step = said
        log.warning("sensor inbox: %s", said)

    def _check_stamp(self, stream: str, stamp_s: float, now_s: float | None) -> None:
        """After the previous stamp of the stream and, with a stamp clock, not far ahead of it."""
        if now_s is not None and stamp_s > now_s + FUTURE_REFUSED_S:
            raise StampError(f"stamp {stamp_s:.6f} s is {stamp_s - now_s:.3f} s ahead of the controller's clock",
                             name="future_stamp", field_name=f"{stream}.stamp_s")
        self._stamps.check(stream, stamp_s)

    def put_scan(self, scan: LidarScan) -> bool:
        try:
            scan, now = self._on_loop_clock(scan)
            scan.validate()
            self._check_not_frozen(scan)
            self._check_stamp("lidar", scan.stamp_s, now)
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
            image, now = self._on_loop_clock(image)
            image.validate()
            self._check_stamp("camera", image.stamp_s, now)
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
            sample, now = self._on_loop_clock(sample)
            sample.validate()
            self._check_stamp("imu", sample.stamp_s, now)
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
