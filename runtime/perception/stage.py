"""The partition stage of the tick (Algorithm 1 lines 3-13): from the good lidar frame to the points
the planner must keep clear of.

    scan (deskewed to the tick when the partition projects it) -> partition (P_fix mask, P_mov)
         -> obstacle points (odom frame, height band, voxel means) = P_fix
         -> moving obstacles: people followed, their predicted way added = the points to plan on

It holds, in the odom frame: `points_fix` (P_fix as the lidar saw it), `points_plan` (P_fix and
where people walking go next: what the planner and the supervisor keep clear of), `points_mov`
with `costs_mov` (the touchable objects' points and their contact costs 0..10: they cost in the
reference path, never constrain the MPC). An ICP correction moves them with the pose
(`follow_correction`), so the robot-to-obstacle geometry does not jump.
"""
from __future__ import annotations

import math

import numpy as np

from runtime.common.geometry import Pose2D
from runtime.common.sensor_data import CameraImage, LidarScan
from runtime.perception.moving_obstacles import MovingObstacles, PredictorSettings
from runtime.perception.obstacle_points import ObstaclePointExtractor
from runtime.perception.partition import PartitionStage

_NO_POINTS = np.zeros((0, 2))


class PerceptionStage:
    def __init__(self, robot, config, partition: PartitionStage, sensors) -> None:
        """robot: calibration.robot_description.RobotDescription; config: runtime.config.ControllerConfig;
        partition: which points are P_fix (runtime.perception.partition); sensors: the calibrated
        mounts (calibration.sensor_calibration.SensorCalibration): the lidar's places the points."""
        op = config.planner.obstacle_points
        self.partition = partition
        self.obstacles = ObstaclePointExtractor(
            robot, op.ground_clearance_m, op.overhead_margin_m, op.max_range_m, op.voxel_m, op.min_support_ratio,
            T_base_lidar=sensors.T_base_lidar,
        )
        # People walking: P_fix clusters followed scan to scan; where they go next joins P_fix for
        # the planner and the supervisor (points_plan), not for the odometry checks.
        self.moving = MovingObstacles(PredictorSettings.for_robot(config.moving_obstacles, robot))
        self.points_fix = _NO_POINTS
        self.points_mov = _NO_POINTS
        self.costs_mov = np.zeros(0)
        self.points_plan = _NO_POINTS

    def exclude_from_odometry(self, odometry, now_s: float) -> None:
        """What moves with the robot or by itself is kept out of the lidar odometry: a box the
        robot pushes (the last scan's P_mov) and the people walking (where their tracks put them now)."""
        odometry.exclude_near(self.partition.movable_points_lidar())
        odometry.exclude_movers(self.moving.moving_points(now_s))

    def follow_correction(self, correction: np.ndarray | None) -> None:
        """An ICP correction moves the pose; the points, placed with the pose before it, move with it."""
        if correction is None:
            return
        self.moving.shift(correction)
        c, s = math.cos(correction[2]), math.sin(correction[2])
        for name in ("points_fix", "points_mov", "points_plan"):
            p = getattr(self, name)
            if len(p):
                setattr(self, name, np.column_stack([c * p[:, 0] - s * p[:, 1] + correction[0],
                                                     s * p[:, 0] + c * p[:, 1] + correction[1]]))

    def update(self, now_s: float, pose: Pose2D, scan: LidarScan | None, image: CameraImage | None,
               image_pose: tuple[float, float, float] | None, inputs, yaw_rate_radps: float) -> None:
        """This tick's partition of the good frame `scan` (None: none this tick; the points stay as
        they are) seen from `pose`; `image` (None: none) taken at `image_pose`; inputs: the base's
        (runtime.io.hardware.BaseInputs: the speed for the deskew, the motor currents for the
        push evidence)."""
        partition = self.partition
        if scan is not None and partition.deskews_scan:
            # every point where it is now, as the pose places it, for the partition and the
            # obstacle points alike (obstacle_points.deskew; without a partition the extractor
            # deskews as it places)
            scan = self.obstacles.deskew(scan, now_s, inputs.linear_mps, yaw_rate_radps,
                                         carried=partition.carried_region())
        xyyaw = (pose.x_m, pose.y_m, pose.yaw_rad)
        only = partition.update(now_s, xyyaw, image, scan, image_pose)
        # what pushing tells about the object pushed (the belief; wheel currents of 0x251-0x254)
        partition.observe_contact(now_s, xyyaw, inputs.linear_mps, inputs.motor_currents_a)
        if scan is None:
            return
        self.points_fix = self.obstacles.extract(scan, pose, now_s, inputs.linear_mps, yaw_rate_radps, only=only)
        self.moving.update(now_s, self.points_fix, (pose.x_m, pose.y_m, pose.yaw_rad), inputs.linear_mps)
        self.points_plan = self.moving.with_predictions(self.points_fix)
        movable = partition.movable()
        if movable is None:
            self.points_mov, self.costs_mov = _NO_POINTS, np.zeros(0)
        else:
            self.points_mov, index = self.obstacles.extract_indexed(
                scan, pose, now_s, inputs.linear_mps, yaw_rate_radps, only=movable[0])
            self.costs_mov = movable[1][index].astype(np.float64)
