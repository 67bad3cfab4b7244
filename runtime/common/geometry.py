"""Planar poses (x, y, yaw) and the few operations the controller needs on them; a scan's nearest
return per bearing round a point, and the least of it near a point's bearing (the moving-obstacle
tests of space seen free)."""
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


#: The widest bearing window of least_return_near (bins either side).
MAX_WINDOW_BINS = 30


def bearing_bins(offsets: np.ndarray, nb: int) -> np.ndarray:
    """Bearing bin (0..nb-1) of each offset (N, 2) from an origin."""
    return (np.floor((np.arctan2(offsets[:, 1], offsets[:, 0]) + math.pi) * (nb / (2.0 * math.pi)))
            .astype(np.intp)) % nb


def nearest_returns(offsets: np.ndarray, nb: int, range_m: float) -> np.ndarray:
    """A scan's nearest return (m) per bearing bin (nb bins) from the offsets (N, 2) of its
    points from the origin; inf where none lies within range_m."""
    out = np.full(nb, np.inf)
    if len(offsets):
        r = np.hypot(offsets[:, 0], offsets[:, 1])
        keep = r < range_m
        np.minimum.at(out, bearing_bins(offsets[keep], nb), r[keep])
    return out


def window_minima(profile: np.ndarray, kmax: int) -> np.ndarray:
    """(kmax, nb): row k-1 is the profile's minimum over bins b-k..b+k (wrapping)."""
    out = np.empty((kmax, profile.shape[0]))
    cur = np.minimum(profile, np.minimum(np.roll(profile, 1), np.roll(profile, -1)))
    out[0] = cur
    for k in range(2, kmax + 1):
        cur = np.minimum(cur, np.minimum(np.roll(profile, k), np.roll(profile, -k)))
        out[k - 1] = cur
    return out


def least_return_near(profile: np.ndarray, offsets: np.ndarray, lateral_m: float) -> tuple[np.ndarray, np.ndarray]:
    """For points at offsets (N, 2) from the profile's origin: (their range (N,), the least
    return of the profile (nearest_returns) over the bearings within lateral_m across the ray
    of each, at least one bin either side, at most MAX_WINDOW_BINS (N,)). A single bearing bin
    is not enough: a voxel-thinned cloud leaves bins empty on a surface near the robot (0.7 cm
    per degree at 0.4 m), and rays graze past an edge."""
    nb = profile.shape[0]
    r = np.hypot(offsets[:, 0], offsets[:, 1])
    if not len(offsets):
        return r, r.copy()
    k = np.clip(np.ceil(np.arctan2(lateral_m, np.maximum(r, 1e-3)) * (nb / (2.0 * math.pi))),
                1, MAX_WINDOW_BINS).astype(np.intp)
    return r, window_minima(profile, int(k.max()))[k - 1, bearing_bins(offsets, nb)]


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
