"""Preflight's file checks: `robot`, `config`, `calibration` (for this robot's camera: robot name,
image size, lidar->camera extrinsic close to the robot description's mounts), `calibration:mounts`
(the calibrated lidar and camera on the robot's body) and `distance_net` (loads, and its footprint
is the robot's). The sensors as calibrated (`LoadedFiles.sensors`) go on to the live checks
(runtime.app.preflight.calibration_live)."""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from runtime.app.preflight.check import Check, one_line

#: The calibration's lidar->camera extrinsic may differ from the robot description's mounts by
#: this much before preflight warns (a mount moved, or the calibration is for another robot).
EXTRINSIC_WARN_M = 0.05
EXTRINSIC_WARN_DEG = 5.0


@dataclass
class LoadedFiles:
    robot: Any = None
    config: Any = None
    calibration: Any = None
    #: The sensors as calibrated (calibration.sensor_calibration.SensorCalibration: the file's,
    #: else the description's nominal ones), for the live checks; None when they cannot be built.
    sensors: Any = None
    checks: list[Check] = field(default_factory=list)


def check_files(robot_path: str | Path | None, calibration_path: str | Path | None,
                config_path: str | Path | None, *, load_net: bool = True) -> LoadedFiles:
    """Load and cross-check the robot description, controller config, calibration and distance net."""
    from calibration.calibration_file import load_calibration
    from calibration.errors import ConfigFileError
    from calibration.robot_description import load_robot_description
    from runtime.config import load_controller_config

    out = LoadedFiles()
    try:
        out.robot = load_robot_description(robot_path)
        out.checks.append(Check("robot", "PASS", f"robot description '{out.robot.name}' "
                                f"{robot_path or '(shipped LIMO description)'}: valid"))
    except ConfigFileError as exc:
        out.checks.append(Check("robot", "FAIL", one_line(exc), "correct the robot description file"))
    try:
        out.config = load_controller_config(config_path)
        out.checks.append(Check("config", "PASS", f"controller config {config_path or '(shipped default)'}: valid, "
                                f"planner {out.config.preset}"))
    except ConfigFileError as exc:
        out.checks.append(Check("config", "FAIL", one_line(exc), "correct the controller config file"))
    needs_camera = out.config is not None and out.config.uses_camera
    if calibration_path is None:
        out.checks.append(Check("calibration", "FAIL" if needs_camera else "WARN", "no calibration file given",
                                "pass --calibration (made by `dct calibrate`)" + (
                                    "; the vpp partition projects lidar points into the camera" if needs_camera else "")))
    else:
        try:
            cal = load_calibration(calibration_path)
            out.calibration = cal
            out.checks.append(_calibration_matches_robot(cal, out.robot, calibration_path, needs_camera))
        except ConfigFileError as exc:
            out.checks.append(Check("calibration", "FAIL", one_line(exc), "recalibrate with `dct calibrate`"))
    _sensors(out, calibration_path)
    out.checks.append(_check_distance_net(out.robot, out.config) if load_net else
                      Check("distance_net", "WARN", "not checked", "run without skipping the model check"))
    return out


def _sensors(out: LoadedFiles, calibration_path: Any) -> None:
    """out.sensors from the robot and the calibration (when each loaded); a calibrated mount off
    the robot's body is a FAIL naming the file's field."""
    from calibration.errors import ConfigFileError
    from calibration.sensor_calibration import sensor_calibration

    if out.robot is None or (calibration_path is not None and out.calibration is None):
        return
    if any(c.name == "calibration" and c.status == "FAIL" for c in out.checks):
        return  # another robot's or another camera's file: said already
    try:
        out.sensors = sensor_calibration(out.robot, out.calibration, calibration_path)
    except ConfigFileError as exc:
        out.checks.append(Check("calibration:mounts", "FAIL", one_line(exc), "correct the calibration file's "
                                "lidar_mount or lidar_to_camera (dct calibrate), or use this robot's file"))


def _calibration_matches_robot(cal: Any, robot: Any, path: Any, needs_camera: bool) -> Check:
    if robot is None:
        return Check("calibration", "FAIL", f"calibration {path}: valid, but cannot be compared (no robot description)",
                     "fix the robot description first")
    cam = robot.sensors.camera
    problems = []
    if cal.robot != robot.name:
        problems.append(f"it is for robot '{cal.robot}', not '{robot.name}'")
    if (cal.camera.width_px, cal.camera.height_px) != (cam.width_px, cam.height_px):
        problems.append(f"its image is {cal.camera.width_px}x{cal.camera.height_px} px, the robot's camera "
                        f"{cam.width_px}x{cam.height_px} px")
    if problems:
        return Check("calibration", "FAIL", f"calibration {path}: " + "; ".join(problems),
                     f"use the calibration made on robot '{robot.name}' (dct calibrate)")
    if cal.lidar_to_camera is None:
        return Check("calibration", "FAIL" if needs_camera else "WARN",
                     f"calibration {path}: camera intrinsics for '{robot.name}', but no lidar_to_camera extrinsic",
                     "run `dct calibrate extrinsics`")
    import numpy as np

    from calibration.sensor_calibration import nominal_sensors

    expected = nominal_sensors(robot).T_cam_lidar  # the description's mounts
    T = cal.T_cam_lidar()
    dt = float(np.linalg.norm(T[:3, 3] - expected[:3, 3]))
    cos = (np.trace(expected[:3, :3].T @ T[:3, :3]) - 1.0) / 2.0
    dr = math.degrees(math.acos(max(-1.0, min(1.0, cos))))
    msg = (f"calibration {path}: for '{robot.name}' camera {cam.width_px}x{cam.height_px}; lidar->camera "
           f"{dt * 100:.1f} cm / {dr:.1f} deg from the robot description's mounts")
    if dt > EXTRINSIC_WARN_M or dr > EXTRINSIC_WARN_DEG:
        return Check("calibration", "WARN", msg + f" (more than {EXTRINSIC_WARN_M * 100:g} cm / {EXTRINSIC_WARN_DEG:g} deg)",
                     "check the sensor mounts, or the robot description's sensors section, and recalibrate")
    method = str(cal.provenance.method)
    if "nominal" in method.lower():
        return Check("calibration", "WARN", msg + f"; nominal values, not measured ({method})",
                     "calibrate the camera on this robot (`dct calibrate`)")
    return Check("calibration", "PASS", msg)


def distance_net_path(config: Any) -> str | None:
    return None if config is None else config.planner.distance_net_path


def _check_distance_net(robot: Any, config: Any) -> Check:
    if config is not None and not config.uses_distance_net:
        return Check("distance_net", "PASS", f"not used (planner {config.preset})")
    if robot is None:
        return Check("distance_net", "FAIL", "not checked: no valid robot description", "fix the robot description")
    from models.distance_net import DistanceNet, shipped_artifact_path
    from models.errors import DistanceNetError, FootprintMismatchError

    path = distance_net_path(config)
    shown = path or f"{shipped_artifact_path()} (shipped)"
    try:
        net = DistanceNet.load(path, robot=robot)
    except FootprintMismatchError as exc:
        return Check("distance_net", "FAIL", f"wrong model footprint: {one_line(exc)}",
                     f"point planner.distance_net_path at the net trained for '{robot.name}'")
    except (DistanceNetError, OSError, ValueError) as exc:
        return Check("distance_net", "FAIL", one_line(exc), "reinstall the bundle or retrain: dct models train-distance")
    fp = net.metadata.get("footprint", {})
    return Check("distance_net", "PASS", f"{shown}: footprint {fp.get('length_m')} x {fp.get('width_m')} m "
                 f"matches '{robot.name}', integrity verified")
