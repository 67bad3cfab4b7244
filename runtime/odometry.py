"""Odometry stage. Step 1: dead reckoning from the base's cumulative wheel distances (0x311).

Later steps fuse KISS-ICP lidar odometry and the IMU here; the tick only asks for a pose.
"""
from __future__ import annotations

import math

from runtime.geometry import Pose2D, wrap_angle


class WheelOdometry:
    """Integrates left/right wheel distance increments (midpoint rule) into a pose in the odom frame."""

    def __init__(self, track_m: float, effective_track_factor: float = 1.0) -> None:
        if track_m <= 0.0:
            raise ValueError(f"track must be positive, got {track_m} m")
        self.effective_track_m = track_m * effective_track_factor
        self._last: tuple[float, float] | None = None
        self._x = self._y = self._yaw = 0.0
        self.distance_travelled_m = 0.0

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
        d_left = left_wheel_m - self._last[0]
        d_right = right_wheel_m - self._last[1]
        self._last = (left_wheel_m, right_wheel_m)
        d_center = 0.5 * (d_left + d_right)
        d_yaw = (d_right - d_left) / self.effective_track_m
        mid_yaw = self._yaw + 0.5 * d_yaw
        self._x += d_center * math.cos(mid_yaw)
        self._y += d_center * math.sin(mid_yaw)
        self._yaw = wrap_angle(self._yaw + d_yaw)
        self.distance_travelled_m += abs(d_center)
        return self.pose
