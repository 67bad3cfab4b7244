"""Robot description, camera and lidar-camera calibration, per-robot calibration files."""
