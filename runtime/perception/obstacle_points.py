"""From a lidar scan to obstacle points in the odom frame (the input of the partition).

Each point is taken from the lidar frame to base_link (the calibrated lidar mount,
calibration.sensor_calibration.SensorCalibration.T_base_lidar),
deskewed with the robot's current twist and its own time stamp (the scan is cast over
100 ms while the robot moves), cut to the robot's height band (ground removed, overhead
ignored), cropped to a range, reduced to one mean point per 2-D voxel (sparse noise cells
dropped) and put in the odom frame.
numpy, and three compiled passes (runtime/perception/point_kernels.py: the deskew to now, the
height band in the odom frame, the voxel means): no Python loop over points.
"""
from __future__ import annotations

import numpy as np

from calibration.robot_description import RobotDescription
from runtime.common.geometry import Pose2D
from runtime.common.sensor_data import LidarScan
from runtime.perception.point_kernels import band_in_odom, compile_point_kernels, deskew_to_now, voxel_means


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
    if points.shape[0] == 0:
        return np.zeros((0, 2))
    return voxel_means(np.ascontiguousarray(points, dtype=np.float64), float(voxel_m), float(min_support_ratio))


_NO_MASK = np.zeros(0, np.bool_)


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
        self.R_base_lidar = np.ascontiguousarray(t[:3, :3], dtype=np.float64)
        self.t_base_lidar = np.ascontiguousarray(t[:3, 3], dtype=np.float64)
        self.min_z_m = ground_clearance_m
        self.max_z_m = robot.body_height_m + overhead_margin_m
        self.max_range_m = max_range_m
        self.voxel_m = voxel_m
        self.min_support_ratio = min_support_ratio
        self.points_in = 0
        self.points_out = 0
        self._band = np.array([self.min_z_m, self.max_z_m, max_range_m ** 2], dtype=np.float64)
        compile_point_kernels()  # here, not in the first tick

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
        box = np.zeros(5) if carried is None else np.array([*carried, 1.0], dtype=np.float64)
        p = np.empty((scan.num_points, 3), np.float32)
        deskew_to_now(np.ascontiguousarray(scan.points_m, dtype=np.float32),
                      np.ascontiguousarray(scan.point_time_offsets_s, dtype=np.float32), float(scan.stamp_s),
                      float(now_s), float(v_mps), float(omega_radps), self.R_base_lidar, self.t_base_lidar, box, p)
        return LidarScan(stamp_s=float(now_s), points_m=p,
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
        """The scan's points in the height band and range (and `only`), deskewed to now_s (not
        when `deskew` did it already), in the odom frame: ((K, 2), their scan indices)."""
        if only is not None and only.shape != (scan.num_points,):
            raise ValueError(f"ObstaclePointExtractor: the point mask has shape {only.shape}, the scan "
                             f"{scan.num_points} points")
        offsets = scan.point_time_offsets_s
        moved = not (scan.stamp_s == now_s and not offsets.any())  # deskewed to now already: nothing to move
        return band_in_odom(
            np.ascontiguousarray(scan.points_m, dtype=np.float32), np.ascontiguousarray(offsets, dtype=np.float32),
            float(scan.stamp_s), float(now_s), float(v_mps), float(omega_radps), self.R_base_lidar,
            self.t_base_lidar, _NO_MASK if only is None else np.ascontiguousarray(only, dtype=np.bool_),
            self._band, np.array([pose_now.x_m, pose_now.y_m, pose_now.yaw_rad], dtype=np.float64), moved)
