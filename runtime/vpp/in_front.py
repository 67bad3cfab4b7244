"""What lies in front of the robot in the last partitioned scan: the stage's questions about
pushing (which movable object the bumper is on, where it lies relative to the robot, whether
anything at all is ahead), as functions of the scan's points in the odom frame and the robot's
planar pose (x, y, yaw).

The robot's footprint ahead is `box` = (half length, half width, margin) in metres: a point is in
front when 0 <= x <= half length + margin and |y| <= half width + margin in the robot's frame.
"""
from __future__ import annotations

import math

import numpy as np

from runtime.vpp.partition.labels import MOVABLE, PointPartition


def to_robot_frame(p: np.ndarray, pose) -> tuple[np.ndarray, np.ndarray]:
    """(x, y) of odom-frame points p (N, >= 2) in the frame of the robot at pose (x, y, yaw)."""
    c, s = math.cos(pose[2]), math.sin(pose[2])
    dx, dy = p[:, 0] - pose[0], p[:, 1] - pose[1]
    return c * dx + s * dy, -s * dx + c * dy


def in_front(p: np.ndarray, pose, box, forward: bool = True) -> np.ndarray:
    """(N,) bool: the points within the footprint ahead (behind the robot when not forward)."""
    half_length_m, half_width_m, margin_m = box
    x, y = to_robot_frame(p, pose)
    if not forward:
        x = -x
    return (x >= 0.0) & (x <= half_length_m + margin_m) & (np.abs(y) <= half_width_m + margin_m)


def movable_in_front(part: PointPartition, p: np.ndarray, pose, box, *, forward: bool = True,
                     min_points: int = 3) -> int | None:
    """The object id with the most P_mov points (at least min_points) of the scan in front of
    the robot; None when there is none."""
    mov = np.flatnonzero(part.label == MOVABLE)
    if not mov.size:
        return None
    near = in_front(p[mov], pose, box, forward)
    ids, counts = np.unique(part.object_id[mov[near]], return_counts=True)
    if not ids.size or counts.max() < min_points:
        return None
    return int(ids[int(np.argmax(counts))])


def object_extent_in_base(p: np.ndarray, pose, half_width_m: float, pad_m: float) -> tuple[float, float, float, float]:
    """(x min, x max, y min, y max) of an object's points p in the robot's frame, padded by pad_m;
    across, at most a footprint's width either side of the robot (what the bumper pushes)."""
    x, y = to_robot_frame(p, pose)
    ymax = 2.0 * half_width_m + pad_m
    return (float(x.min()) - pad_m, float(x.max()) + pad_m,
            max(float(y.min()) - pad_m, -ymax), min(float(y.max()) + pad_m, ymax))


__all__ = ["in_front", "movable_in_front", "object_extent_in_base", "to_robot_frame"]
