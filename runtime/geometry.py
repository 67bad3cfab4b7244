"""Planar poses (x, y, yaw) and the few operations the controller needs on them."""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


def wrap_angle(a_rad: float) -> float:
    """Wrap an angle to [-pi, pi)."""
    return (a_rad + math.pi) % (2.0 * math.pi) - math.pi


def in_box(points: np.ndarray, lo, hi) -> np.ndarray:
    """Mask (N,) of points (N, 2) with lo <= p <= hi per axis. Column compares: several times
    faster than reducing an (N, 2) boolean array over axis 1, and this runs in the tick."""
    x, y = points[:, 0], points[:, 1]
    return (x >= lo[0]) & (x <= hi[0]) & (y >= lo[1]) & (y <= hi[1])


@dataclass(frozen=True)
class Pose2D:
    x_m: float
    y_m: float
    yaw_rad: float

    def compose(self, other: "Pose2D") -> "Pose2D":
        """self * other: `other` expressed in self's frame, returned in self's parent frame."""
        c, s = math.cos(self.yaw_rad), math.sin(self.yaw_rad)
        return Pose2D(
            self.x_m + c * other.x_m - s * other.y_m,
            self.y_m + s * other.x_m + c * other.y_m,
            wrap_angle(self.yaw_rad + other.yaw_rad),
        )

    def inverse(self) -> "Pose2D":
        c, s = math.cos(self.yaw_rad), math.sin(self.yaw_rad)
        return Pose2D(-c * self.x_m - s * self.y_m, s * self.x_m - c * self.y_m, wrap_angle(-self.yaw_rad))

    def distance_to(self, other: "Pose2D") -> float:
        return math.hypot(other.x_m - self.x_m, other.y_m - self.y_m)
