"""Odometry: where the robot is in the odom frame, from wheels, IMU and lidar.

- `wheels`: dead reckoning from the base's wheel distances (0x311) and the IMU gyro.
- `icp`: KISS-ICP lidar odometry on deskewed scans (runs beside the tick).
- `icp_config`, `icp_settings`, `kiss_pipeline`: KISS-ICP's settings, the auto ones derived from
  the first frame, the iteration cap from the time budget, the range gate's count; its steps.
- `degeneracy`: does a scan constrain the planar motion, and along which direction not.
- `fusion`: one pose stream with a covariance from ICP, wheels and gyro.
- `metrics`: drift and relative pose error against a reference trajectory.
- `sequence`: KISS-ICP over a recorded sequence (scans, reference poses, times) against its poses;
  its inputs: `scan_files` (PCD/PLY/KITTI .bin folders), `bag_scans` (ROS 2 bags), `pose_files`
  (KITTI/TUM poses, times, --frames); its figures beside ours: `evo_eval` (evo's APE/RPE, plot)
  and `reference_check` (does the reference move like the scans).
- `pair`: one scan registered onto another (the real HDL-32 pair check).
- `cli`, `cli_scans`: `dct odom eval` and `dct odom register`.
"""
from runtime.odometry.wheels import WheelGyroOdometry, WheelOdometry

__all__ = ["WheelOdometry", "WheelGyroOdometry"]
