"""From a lidar scan to obstacle points in the odom frame (the input of the partition).

Each point is taken from the lidar frame to base_link (mount from the robot description),
deskewed with the robot's current twist and its own time stamp (the scan is cast over
100 ms while the robot moves), cut to the robot's height band (ground removed, overhead
ignored), cropped to a range, thinned on a 2-D voxel grid and put in the odom frame.
All numpy, no Python loop over points.
"""
from __future__ import annotations

import math

import numpy as np

from calibration.robot_description import RobotDescription
from runtime.geometry import Pose2D
from runtime.sensor_data import LidarScan


class ObstaclePointExtractor:
    def __init__(
        self,
        robot: RobotDescription,
        ground_clearance_m: float = 0.04,
        overhead_margin_m: float = 0.10,
        max_range_m: float = 6.0,
        voxel_m: float = 0.04,
    ) -> None:
        t = robot.sensors.lidar.mount.transform()
        self.R_base_lidar = t[:3, :3].astype(np.float64)
        self.t_base_lidar = t[:3, 3].astype(np.float64)
        self.min_z_m = ground_clearance_m
        self.max_z_m = robot.body_height_m + overhead_margin_m
        self.max_range_m = max_range_m
        self.voxel_m = voxel_m
        self.points_in = 0
        self.points_out = 0

    def extract(self, scan: LidarScan, pose_now: Pose2D, now_s: float, v_mps: float, omega_radps: float) -> np.ndarray:
        """P (N, 2) in the odom frame, deskewed to `now_s` with the twist (v, omega)."""
        q = scan.points_m.astype(np.float64) @ self.R_base_lidar.T + self.t_base_lidar  # base_link at cast time
        keep = (q[:, 2] > self.min_z_m) & (q[:, 2] < self.max_z_m)
        keep &= (q[:, 0] ** 2 + q[:, 1] ** 2) < self.max_range_m**2
        q = q[keep]
        dt = (scan.stamp_s + scan.point_time_offsets_s[keep].astype(np.float64)) - now_s  # <= 0: cast in the past
        # Pose at cast time relative to the pose now, constant twist: yaw_i, and the chord.
        yaw = omega_radps * dt
        half = 0.5 * yaw
        tx = v_mps * dt * np.cos(half)
        ty = v_mps * dt * np.sin(half)
        c, s = np.cos(yaw), np.sin(yaw)
        bx = c * q[:, 0] - s * q[:, 1] + tx
        by = s * q[:, 0] + c * q[:, 1] + ty
        # base_link now -> odom
        cy, sy = math.cos(pose_now.yaw_rad), math.sin(pose_now.yaw_rad)
        pts = np.empty((bx.shape[0], 2))
        pts[:, 0] = pose_now.x_m + cy * bx - sy * by
        pts[:, 1] = pose_now.y_m + sy * bx + cy * by
        self.points_in = int(scan.num_points)
        if self.voxel_m > 0.0 and pts.shape[0]:
            keys = np.floor(pts / self.voxel_m).astype(np.int64)
            key = keys[:, 0] * 1_000_003 + keys[:, 1]
            _, first = np.unique(key, return_index=True)
            pts = pts[np.sort(first)]
        self.points_out = int(pts.shape[0])
        return pts
