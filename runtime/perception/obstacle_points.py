"""From a lidar scan to obstacle points in the odom frame (the input of the partition).

Each point is taken from the lidar frame to base_link (the calibrated lidar mount,
calibration.sensor_calibration.SensorCalibration.T_base_lidar),
deskewed with the robot's current twist and its own time stamp (the scan is cast over
100 ms while the robot moves), cut to the robot's height band (ground removed, overhead
ignored), cropped to a range, reduced to one mean point per 2-D voxel (sparse noise cells
dropped) and put in the odom frame.
All numpy, no Python loop over points.
"""
from __future__ import annotations

import math

import numpy as np

from calibration.robot_description import RobotDescription
from runtime.common.geometry import Pose2D
from runtime.common.sensor_data import LidarScan


_KEY_STRIDE = np.int64(1 << 32)  # cell key = ix * stride + iy (cells within +-2^31 of the origin)
_NEIGHBOUR_OFFSETS = np.array(
    [dx * _KEY_STRIDE + dy for dx in (-1, 0, 1) for dy in (-1, 0, 1) if (dx, dy) != (0, 0)], dtype=np.int64
)


def voxel_filter(points: np.ndarray, voxel_m: float, min_support_ratio: float = 0.0) -> np.ndarray:
    """One point per occupied square cell: the mean of its points (PCL VoxelGrid style), keeping
    only cells with at least `min_support_ratio` x the point count of their fullest neighbour.

    Why both: the planner constrains against the nearest points, so lidar range noise (sigma 2 cm
    for a Livox Mid-360) would narrow a gap by its inward tail. The mean divides the noise of a
    cell by about sqrt(n); the support test drops the sparse cells that only the noise tail
    reaches, next to a dense surface cell (a density-based outlier filter, as PCL's
    RadiusOutlierRemoval, on the grid). An isolated thin object is its own fullest neighbour and
    stays. A mean lies inside its cell: at a convex corner it can sit up to about a quarter cell
    behind the surface, which the MPC's d_min and the supervisor's stop distance cover.
    """
    cells = np.floor(points / voxel_m).astype(np.int64)
    key = cells[:, 0] * _KEY_STRIDE + cells[:, 1]
    keys, inverse, counts = np.unique(key, return_inverse=True, return_counts=True)
    out = np.empty((keys.shape[0], 2))
    out[:, 0] = np.bincount(inverse, weights=points[:, 0]) / counts
    out[:, 1] = np.bincount(inverse, weights=points[:, 1]) / counts
    if min_support_ratio <= 0.0 or keys.shape[0] < 2:
        return out
    nb = keys[None, :] + _NEIGHBOUR_OFFSETS[:, None]  # (8, M) neighbour keys, looked up in the sorted keys
    idx = np.minimum(np.searchsorted(keys, nb), keys.shape[0] - 1)
    nb_counts = np.where(keys[idx] == nb, counts[idx], 0)
    return out[counts >= min_support_ratio * nb_counts.max(axis=0)]


def _to_now(q: np.ndarray, dt: np.ndarray, v_mps: float, omega_radps: float) -> np.ndarray:
    """(N, 3) points in base_link at their cast times (dt = cast time - now, <= 0) to base_link
    now, with a constant twist since: the yaw turned and the chord driven."""
    # Two trigonometric calls per point, not four: the yaw's from its half (double-angle identities).
    half = (0.5 * omega_radps) * dt
    ch, sh = np.cos(half), np.sin(half)
    vdt = v_mps * dt
    tx, ty = vdt * ch, vdt * sh
    c = 1.0 - 2.0 * sh * sh
    s = 2.0 * sh * ch
    out = np.empty_like(q)
    out[:, 0] = c * q[:, 0] - s * q[:, 1] + tx
    out[:, 1] = s * q[:, 0] + c * q[:, 1] + ty
    out[:, 2] = q[:, 2]
    return out


class ObstaclePointExtractor:
    def __init__(
        self,
        robot: RobotDescription,
        ground_clearance_m: float = 0.04,
        overhead_margin_m: float = 0.10,
        max_range_m: float = 6.0,
        voxel_m: float = 0.04,
        min_support_ratio: float = 0.25,
        *,
        T_base_lidar: np.ndarray,
    ) -> None:
        """T_base_lidar: the lidar's mount as calibrated (4x4, p_base = T p_lidar)."""
        t = np.asarray(T_base_lidar, dtype=np.float64)
        if t.shape != (4, 4) or not np.isfinite(t).all():
            raise ValueError(f"ObstaclePointExtractor.T_base_lidar: must be a finite 4x4 transform, got shape {t.shape}")
        self.R_base_lidar = t[:3, :3].astype(np.float64)
        self.t_base_lidar = t[:3, 3].astype(np.float64)
        self.min_z_m = ground_clearance_m
        self.max_z_m = robot.body_height_m + overhead_margin_m
        self.max_range_m = max_range_m
        self.voxel_m = voxel_m
        self.min_support_ratio = min_support_ratio
        self.points_in = 0
        self.points_out = 0

    def deskew(self, scan: LidarScan, now_s: float, v_mps: float, omega_radps: float,
               carried: tuple[float, float, float, float] | None = None) -> LidarScan:
        """The scan with every point moved to base_link's pose at `now_s` (constant twist (v,
        omega) since each point's cast time), given back in the lidar frame, offsets zero, stamped
        `now_s`: one instant, as the pose the tick places it with.

        Why the VPP partition needs it: it places the scan in the odom frame and projects it into
        the camera with the pose of the tick. Undeskewed, a frame cast over 100 ms at 1 m/s is
        smeared by up to 14 cm along the motion (10 cm of frame, the tick's lag behind it), and a
        box's face points land off its tracked template and stay P_fix
        (docs/decisions/planning-obstacle-points-deskew.md).

        carried: (x min, x max, y min, y max) in base_link: the object the robot pushes, which
        moves with it. Its points stay where the robot saw them (relative to the robot); deskewed
        with the world they would trail up to 14 cm behind the bumper, into the robot.
        """
        q = scan.points_m.astype(np.float64) @ self.R_base_lidar.T + self.t_base_lidar  # base_link at cast time
        dt = scan.stamp_s + scan.point_time_offsets_s.astype(np.float64) - now_s
        if carried is not None:
            x0, x1, y0, y1 = carried
            dt[(q[:, 0] >= x0) & (q[:, 0] <= x1) & (q[:, 1] >= y0) & (q[:, 1] <= y1)] = 0.0
        q = _to_now(q, dt, v_mps, omega_radps)
        p = (q - self.t_base_lidar) @ self.R_base_lidar  # R^T (q - t), per row
        return LidarScan(stamp_s=float(now_s), points_m=p.astype(np.float32),
                         point_time_offsets_s=np.zeros(scan.num_points, np.float32),
                         frame_duration_s=scan.frame_duration_s, frame_id=scan.frame_id,
                         nothing_seen=scan.nothing_seen)

    def extract(self, scan: LidarScan, pose_now: Pose2D, now_s: float, v_mps: float, omega_radps: float,
                only: np.ndarray | None = None) -> np.ndarray:
        """P (N, 2) in the odom frame, deskewed to `now_s` with the twist (v, omega). only: (N,)
        bool, the scan points to use (the VPP's P_fix); None: all of them."""
        pts, _ = self._deskewed(scan, pose_now, now_s, v_mps, omega_radps, only)
        self.points_in = int(scan.num_points)
        if self.voxel_m > 0.0 and pts.shape[0]:
            pts = voxel_filter(pts, self.voxel_m, self.min_support_ratio)
        self.points_out = int(pts.shape[0])
        return pts

    def extract_indexed(self, scan: LidarScan, pose_now: Pose2D, now_s: float, v_mps: float, omega_radps: float,
                        only: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """As extract, without the voxel filter: (P (M, 2) odom frame, the scan indices of its
        points), for points that carry a value of their own (P_mov and its contact costs)."""
        return self._deskewed(scan, pose_now, now_s, v_mps, omega_radps, only)

    def _deskewed(self, scan: LidarScan, pose_now: Pose2D, now_s: float, v_mps: float, omega_radps: float,
                  only: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
        q = scan.points_m.astype(np.float64) @ self.R_base_lidar.T + self.t_base_lidar  # base_link at cast time
        keep = (q[:, 2] > self.min_z_m) & (q[:, 2] < self.max_z_m)
        if only is not None:
            keep &= only
        keep &= (q[:, 0] ** 2 + q[:, 1] ** 2) < self.max_range_m**2
        index = np.flatnonzero(keep)
        if scan.stamp_s == now_s and not scan.point_time_offsets_s.any():
            b = q[keep]  # deskewed to now already (deskew): nothing to move
        else:
            dt = (scan.stamp_s + scan.point_time_offsets_s[keep].astype(np.float64)) - now_s
            b = _to_now(q[keep], dt, v_mps, omega_radps)
        bx, by = b[:, 0], b[:, 1]
        # base_link now -> odom
        cy, sy = math.cos(pose_now.yaw_rad), math.sin(pose_now.yaw_rad)
        pts = np.empty((bx.shape[0], 2))
        pts[:, 0] = pose_now.x_m + cy * bx - sy * by
        pts[:, 1] = pose_now.y_m + sy * bx + cy * by
        return pts, index
