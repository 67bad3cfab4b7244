"""Wheel odometry: dead reckoning from the base's cumulative wheel distances (0x311) and the gyro.

The odometry stage (runtime.odometry.stage) fuses it with KISS-ICP; the tick only asks for a pose.
"""
from __future__ import annotations

import math

from runtime.common.geometry import Pose2D, wrap_angle


#: Faster than this a wheel's distance cannot change between two readings (twice the base's top
#: speed): a bigger step is a counter that restarted (the base rebooted), not motion; the odometry
#: re-anchors on the new reading instead of integrating the jump. Plus a margin for one reading.
MAX_WHEEL_SPEED_MPS = 2.0
WHEEL_STEP_MARGIN_M = 0.1


#: Consecutive IMU samples further apart than this are not integrated (the IMU was lost, not
#: late): the yaw over such a gap is the wheels'.
MAX_GYRO_GAP_S = 0.1

#: Speeds below this count no travel in OdometerWatch: a millimetre odometer read at 50 Hz may
#: stay unchanged for a frame or more that slowly, and a still base's speed may carry noise.
ODOMETER_WATCH_SPEED_FLOOR_MPS = 0.02


class OdometerWatch:
    """Whether the wheel distances (0x311) follow the base's reported speed (0x221). Both come from
    the same encoders: distances that stay unchanged while the speed accounts for `travel_m` of
    wheel travel (each tick's |speed| over the time since the tick before: the speed a base
    reports after the distances last moved is what it did since) over at least `min_s` are
    frozen readings, not a
    robot standing still (speeds under ODOMETER_WATCH_SPEED_FLOOR_MPS count none). Travel, not a
    speed held throughout: a robot creeping stop-and-go in a tight gap reports 0.06 and 0.003 m/s
    on alternate ticks, and still turns its wheels."""

    def __init__(self, travel_m: float, min_s: float) -> None:
        self.travel_limit_m = float(travel_m)
        self.min_s = float(min_s)
        self.distances: tuple[float, float] | None = None  # the last reading
        self.unchanged_since_s: float | None = None  # when the distances last changed
        self.travel_m = 0.0  # what the speed accounts for since
        self._prev: tuple[float, float] | None = None  # (t, |speed|) of the last update with a speed

    def update(self, now_s: float, distances: tuple[float, float] | None, speed_mps: float | None) -> bool:
        """The tick's reading (None: none fresh) and speed (None: none fresh); True: frozen now. A
        tick without a fresh reading ends the spell: a silent 0x311 is stale, not stuck, and the
        next reading starts afresh."""
        if distances is None:
            self.distances, self.unchanged_since_s, self.travel_m, self._prev = None, None, 0.0, None
            return False
        speed = None if speed_mps is None else \
            (abs(speed_mps) if abs(speed_mps) >= ODOMETER_WATCH_SPEED_FLOOR_MPS else 0.0)
        if distances != self.distances:
            self.distances, self.unchanged_since_s, self.travel_m = distances, now_s, 0.0
            self._prev = None if speed is None else (now_s, speed)
            return False
        if speed is None:
            self._prev = None
            return False
        if self._prev is not None:
            self.travel_m += speed * (now_s - self._prev[0])
        self._prev = (now_s, speed)
        return self.travel_m >= self.travel_limit_m and now_s - self.unchanged_since_s >= self.min_s


class WheelOdometry:
    """Integrates left/right wheel distance increments (midpoint rule) into a pose in the odom frame.

    A wheel's distance jumping further than it could have moved since the reading before
    (MAX_WHEEL_SPEED_MPS over `gap_s`, given to `update_with_imu`) re-anchors instead (`jumps`
    counts them), and so does `reanchor()` (the base said it restarted).

    The wheel distances are multiplied by `wheel_scale` (true distance / reported distance) and
    their difference turns into yaw over track_m * effective_track_factor. Calibrated values
    (`dct calibrate wheels`) come from calibration.wheel_odometry.wheel_params:
    WheelOdometry(effective_track_m, wheel_scale=wheel_scale).
    """

    def __init__(self, track_m: float, effective_track_factor: float = 1.0, wheel_scale: float = 1.0) -> None:
        if track_m <= 0.0:
            raise ValueError(f"track must be positive, got {track_m} m")
        if not (math.isfinite(wheel_scale) and wheel_scale > 0.0):
            raise ValueError(f"wheel scale must be a positive number, got {wheel_scale}")
        self.effective_track_m = track_m * effective_track_factor
        self.wheel_scale = wheel_scale
        self._last: tuple[float, float] | None = None
        self._x = self._y = self._yaw = 0.0
        self.distance_travelled_m = 0.0
        self.jumps = 0

    def reanchor(self) -> None:
        """The next wheel reading starts afresh (the base's odometers restarted)."""
        self._last = None

    def _jumped(self, left_wheel_m: float, right_wheel_m: float, gap_s: float | None) -> bool:
        """The new reading is not reachable from the last one in gap_s (None: not judged)."""
        last = self._last
        if gap_s is None:
            return False
        step = MAX_WHEEL_SPEED_MPS * max(gap_s, 0.0) + WHEEL_STEP_MARGIN_M
        if abs(left_wheel_m - last[0]) <= step and abs(right_wheel_m - last[1]) <= step:
            return False
        self._last = (left_wheel_m, right_wheel_m)
        self.jumps += 1
        return True

    @property
    def pose(self) -> Pose2D:
        return Pose2D(self._x, self._y, self._yaw)

    def reset(self, pose: Pose2D = Pose2D(0.0, 0.0, 0.0)) -> None:
        self._x, self._y, self._yaw = pose.x_m, pose.y_m, pose.yaw_rad
        self._last = None

    def update(self, left_wheel_m: float, right_wheel_m: float) -> Pose2D:
        """Feed the cumulative wheel distances (m); returns the new pose."""
        if self._last is None:
            self._last = (left_wheel_m, right_wheel_m)
            return self.pose
        d_left = (left_wheel_m - self._last[0]) * self.wheel_scale
        d_right = (right_wheel_m - self._last[1]) * self.wheel_scale
        self._last = (left_wheel_m, right_wheel_m)
        return self._advance(0.5 * (d_left + d_right), (d_right - d_left) / self.effective_track_m)

    def _advance(self, d_center: float, d_yaw: float) -> Pose2D:
        """Move by d_center along the mid-step heading and turn by d_yaw (midpoint rule)."""
        mid_yaw = self._yaw + 0.5 * d_yaw
        self._x += d_center * math.cos(mid_yaw)
        self._y += d_center * math.sin(mid_yaw)
        self._yaw = wrap_angle(self._yaw + d_yaw)
        self.distance_travelled_m += abs(d_center)
        return self.pose


class WheelGyroOdometry(WheelOdometry):
    """Wheel distance for translation, the IMU gyro for yaw.

    A four-wheel skid-steer base slips sideways whenever it turns, so yaw from the wheel
    speed difference is badly wrong (the HIL LIMO turns about a third of what its wheels
    say); the gyro is not. The gyro bias is estimated while the robot stands still before
    it is activated (`calibrate_bias`). Without IMU samples the wheel yaw is used.
    """

    def __init__(self, track_m: float, effective_track_factor: float = 1.0, wheel_scale: float = 1.0) -> None:
        super().__init__(track_m, effective_track_factor, wheel_scale)
        self.gyro_bias_radps = 0.0
        self._bias_sum = 0.0
        self._bias_n = 0
        self._last_imu_stamp: float | None = None
        self._last_rate = 0.0
        self._last_raw = 0.0
        self.imu_samples_used = 0
        #: The integral of the raw gyro z rate (rad, unwrapped) and the time it covers (s): what
        #: the online bias estimate observes (runtime.odometry.gyro_bias), never reset.
        self.raw_gyro_yaw_rad = 0.0
        self.gyro_covered_s = 0.0
        #: The wheels' yaw put in by updates without an IMU sample since the newest sample: the
        #: gyro's samples of that time may still come (late, not lost), and then they are the yaw.
        self._wheel_yaw_since_sample = 0.0
        self.late_imu_yaw_replaced_rad = 0.0  # counter: the wheel yaw given back to late samples

    @property
    def yaw_rate_radps(self) -> float:
        """The latest bias-corrected gyro yaw rate (0 before any sample)."""
        return self._last_rate

    def calibrate_bias(self, imu_samples) -> None:
        """Accumulate gyro z while the robot is known to stand still."""
        for s in imu_samples:
            self._bias_sum += float(s.gyro_radps[2])
            self._bias_n += 1
            self._last_imu_stamp = s.stamp_s
            self._last_raw = float(s.gyro_radps[2])
        if self._bias_n:
            self.gyro_bias_radps = self._bias_sum / self._bias_n

    def update_with_imu(self, wheels: tuple[float, float] | None, imu_samples,
                        fallback_distance_m: float | None = None, gap_s: float | None = None) -> Pose2D:
        """wheels: the cumulative wheel distances (0x311), None when they are not fresh.
        fallback_distance_m: without fresh wheel distances, the distance travelled since the last
        update from the base's reported speed (0x221 x dt); the wheel distances then re-anchor
        when they return (their jump over the gap is not counted twice). None: no translation.
        gap_s: seconds since the wheel reading before this one (a bigger jump re-anchors)."""
        d_yaw = 0.0
        have_imu = False
        for s in imu_samples:
            raw = float(s.gyro_radps[2])
            rate = raw - self.gyro_bias_radps
            if self._last_imu_stamp is not None:
                dt = s.stamp_s - self._last_imu_stamp
                if 0.0 < dt < MAX_GYRO_GAP_S:
                    # The gyro covers the time since its previous sample, so also whatever of it
                    # the wheels' yaw stood in for while this sample was late: that yaw goes.
                    d_yaw += 0.5 * (rate + self._last_rate) * dt - self._wheel_yaw_since_sample
                    self.late_imu_yaw_replaced_rad += abs(self._wheel_yaw_since_sample)
                    self._wheel_yaw_since_sample = 0.0
                    self.raw_gyro_yaw_rad += 0.5 * (raw + self._last_raw) * dt
                    self.gyro_covered_s += dt
                elif dt >= MAX_GYRO_GAP_S:
                    self._wheel_yaw_since_sample = 0.0  # the gap's yaw is the wheels'
            self._last_imu_stamp = s.stamp_s
            self._last_rate = rate
            self._last_raw = raw
            have_imu = True
            self.imu_samples_used += 1
        if wheels is None:
            if fallback_distance_m is not None:
                self._last = None  # re-anchor on the next wheel reading
                if not have_imu:  # yaw from nothing: hold it
                    d_yaw = 0.0
                return self._advance(fallback_distance_m * self.wheel_scale, d_yaw)
            if have_imu:
                self._yaw = wrap_angle(self._yaw + d_yaw)
            return self.pose
        left, right = wheels
        jumped = self._last is not None and self._jumped(left, right, gap_s)
        if not have_imu and not jumped:
            yaw_before = self._yaw
            pose = self.update(left, right)
            self._wheel_yaw_since_sample += wrap_angle(self._yaw - yaw_before)
            return pose
        if self._last is None or jumped:
            self._last = (left, right)
            self._yaw = wrap_angle(self._yaw + d_yaw)
            return self.pose
        d_center = 0.5 * ((left - self._last[0]) + (right - self._last[1])) * self.wheel_scale
        self._last = (left, right)
        return self._advance(d_center, d_yaw)
