"""Preflight's calibration checks on live data: the calibration `dct run` would use (the file's,
else the robot description's nominal values) against what the sensors show now, as the
controller checks it while driving (runtime.perception.calibration_monitor), with the config's
tolerances (`calibration_check`):

* `calibration:intrinsics`: the last CameraInfo heard on the camera's info topic against the
  calibrated camera: every field beyond its tolerance named with the file and how far off;
* `calibration:floor`: the floor of the last lidar frame heard, placed on base_link with the
  calibrated lidar mount: tilted or off z = 0 beyond the tolerances names the mount's source.

What would make the controller fall back to the all-fixed partition FAILs when the config's
partition reads the camera (it would drive all-fixed from the first check), else WARNs; what
cannot be checked (no CameraInfo heard, too little floor in view) WARNs with how to check it.
"""
from __future__ import annotations

from typing import Any

from runtime.app.preflight.check import Check, one_line


def check_calibration_live(last: dict[str, bytes], ros_inputs: Any, sensors: Any, config: Any) -> list[Check]:
    """The two checks from the last sample of each stream (`last`: stream -> CDR bytes, as
    preflight's listener keeps them); ros_inputs: the config's ros.inputs; sensors: the calibration
    (calibration.sensor_calibration.SensorCalibration); config: the controller config (None: the
    shipped defaults)."""
    from runtime.perception.calibration_monitor import CalibrationCheckConfig

    tol = config.calibration_check if config is not None else CalibrationCheckConfig()
    bad = "FAIL" if config is not None and config.uses_camera else "WARN"
    return [_intrinsics(last.get("camera_info"), ros_inputs.camera_info, sensors, tol, bad),
            _floor(last.get("lidar"), ros_inputs.lidar, sensors, tol, bad)]


def _intrinsics(cdr: bytes | None, topic: Any, sensors: Any, tol: Any, bad: str) -> Check:
    from calibration.consistency import ReportedCamera, intrinsics_problems
    from runtime.common.sensor_data import SensorDataError
    from runtime.io.ros import convert
    from runtime.io.ros.receiver import decode_cdr

    name = "calibration:intrinsics"
    if topic is None:
        return Check(name, "WARN", "not checked: the config names no camera_info topic (ros.inputs.camera_info)",
                     "add the camera driver's CameraInfo topic to ros.inputs")
    if cdr is None:
        return Check(name, "WARN", f"not checked: nothing heard on {topic.topic}",
                     "start the camera driver (it publishes its CameraInfo beside the image)")
    try:
        info = convert.camera_info_to_intrinsics(decode_cdr(topic.type, cdr))
    except SensorDataError as exc:
        return Check(name, "WARN", f"not checked: {topic.topic}: {one_line(exc)[:200]}",
                     "calibrate the camera in its driver, or compare by hand with `dct calibrate report`")
    problems, notes = intrinsics_problems(
        sensors.camera, ReportedCamera(info.K, info.distortion, info.width_px, info.height_px, info.distortion_model),
        sensors.camera_field, focal_rel=tol.focal_tolerance, principal_px=tol.principal_point_tolerance_px,
        distortion_px=tol.distortion_tolerance_px)
    extra = f" ({'; '.join(notes)})" if notes else ""
    if problems:
        return Check(name, bad, "; ".join(problems) + extra,
                     "recalibrate the camera (dct calibrate intrinsics) or use this robot's calibration file; "
                     "driving, the partition would fall back to all-fixed")
    return Check(name, "PASS", f"{sensors.sources['camera']} matches the CameraInfo on {topic.topic} within "
                 f"{tol.focal_tolerance * 100:g}% / {tol.principal_point_tolerance_px:g} px{extra}")


def _floor(cdr: bytes | None, topic: Any, sensors: Any, tol: Any, bad: str) -> Check:
    import numpy as np

    from calibration.consistency import fit_floor, floor_problem
    from runtime.app.preflight.ros_graph import lidar_scan
    from runtime.common.sensor_data import SensorDataError

    name = "calibration:floor"
    if topic is None or cdr is None:
        return Check(name, "WARN", "not checked: no lidar frame heard", "see topic:lidar")
    try:
        scan = lidar_scan(topic, cdr)
    except SensorDataError as exc:
        return Check(name, "WARN", f"not checked: {topic.topic}: {one_line(exc)[:200]}", "see topic:lidar")
    T = sensors.T_base_lidar
    fit = fit_floor(np.asarray(scan.points_m, dtype=np.float64) @ T[:3, :3].T + T[:3, 3], T[:3, 3])
    if fit is None:
        return Check(name, "WARN", f"not checked: the last frame on {topic.topic} shows too little floor through "
                     f"{sensors.sources['lidar_mount']}", "run preflight with the robot in open space (2 m clear around)")
    problem = floor_problem(fit, sensors.sources["lidar_mount"], tilt_deg=tol.floor_tilt_tolerance_deg,
                            height_m=tol.floor_height_tolerance_m)
    if problem is not None:
        return Check(name, bad, problem, "measure the lidar's mount again (or `dct calibrate`) and set the "
                     "calibration file's lidar_mount; driving, the partition would fall back to all-fixed")
    return Check(name, "PASS", f"the floor through {sensors.sources['lidar_mount']}: tilted {fit.tilt_deg:.2f} deg, "
                 f"at z {fit.height_m * 100:+.1f} cm ({fit.cells} cells of floor)")
