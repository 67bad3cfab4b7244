"""This robot's sensors as calibrated: one value, built once at start, that every stage reads.

`SensorCalibration` holds the camera model (K, distortion, image size), T_base<-lidar,
T_base<-camera and T_camera<-lidar, and for each of them where it came from: a calibration
file's field (`my_robot.yaml lidar_mount`) or the robot description's nominal value
(`robot description 'limo' sensors.lidar.mount (nominal)`). `sensor_calibration(robot, cal,
path)` builds it from the robot description and an optional calibration file:

* camera: the file's `camera` section; without a file, the description's nominal pinhole (from
  its field of view, no distortion);
* T_base<-lidar: the file's `lidar_mount`, else the description's `sensors.lidar.mount`;
* T_base<-camera: T_base<-lidar composed with the inverse of the file's `lidar_to_camera` when
  the file has one, else the description's `sensors.camera.mount`;
* T_camera<-lidar: always inv(T_base<-camera) T_base<-lidar, so the three agree.

What is refused (ConfigFileError naming the file and the field): a calibration of another robot
or another camera size (`camera_for_robot`), and a calibrated lidar or camera position that lies
off the robot's body by the description's own rule (RobotDescription.mount_problem).

The simulator's truth (its world, its sensor rig) keeps the description's mounts: this value is
what the controller believes, never what the world is.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from calibration.camera_model import CameraModel
from calibration.errors import ConfigFileError


@dataclass(frozen=True)
class SensorCalibration:
    """The camera and the mounts the controller uses (module docstring). Arrays are read-only."""

    camera: CameraModel
    T_base_lidar: np.ndarray
    T_base_camera: np.ndarray
    #: Where each value came from, by key: "camera", "lidar_mount", "camera_mount".
    sources: dict
    #: The calibration file's path as given (None: nominal values only).
    path: str | None = None
    #: How a camera field is named in a message, "{}" the field (fx, cy, distortion).
    camera_fields: str = "the camera's {}"

    def __post_init__(self) -> None:
        for name in ("T_base_lidar", "T_base_camera"):
            T = np.array(getattr(self, name), dtype=np.float64)
            if T.shape != (4, 4) or not np.isfinite(T).all():
                raise ValueError(f"SensorCalibration.{name}: must be a finite 4x4 transform, got shape {T.shape}")
            T.flags.writeable = False
            object.__setattr__(self, name, T)
        missing = {"camera", "lidar_mount", "camera_mount"} - set(self.sources)
        if missing:
            raise ValueError(f"SensorCalibration.sources: no source for {sorted(missing)}")

    @property
    def T_cam_lidar(self) -> np.ndarray:
        """4x4 T_camera<-lidar (p_cam = T p_lidar), consistent with the two mounts."""
        return np.linalg.inv(self.T_base_camera) @ self.T_base_lidar

    def camera_field(self, name: str) -> str:
        """The camera field `name` as a message names it: `my_robot.yaml camera.fx`."""
        return self.camera_fields.format(name)

    @property
    def nominal(self) -> bool:
        """No value came from a calibration file."""
        return self.path is None

    def describe(self) -> dict:
        """JSON-ready: where each value came from, and the values (for the run's summary)."""
        K = self.camera.K
        return {
            "path": self.path,
            "sources": dict(self.sources),
            "camera": {"fx": float(K[0, 0]), "fy": float(K[1, 1]), "cx": float(K[0, 2]), "cy": float(K[1, 2]),
                       "distortion": [float(d) for d in self.camera.dist],
                       "size_px": [self.camera.width_px, self.camera.height_px]},
            "lidar_mount_xyz_m": [round(float(v), 6) for v in self.T_base_lidar[:3, 3]],
            "camera_mount_xyz_m": [round(float(v), 6) for v in self.T_base_camera[:3, 3]],
        }


def _nominal_camera(robot) -> CameraModel:
    cam = robot.sensors.camera
    return CameraModel(cam.nominal_intrinsics(), np.zeros(5), cam.width_px, cam.height_px)


def nominal_sensors(robot, robot_source: str | None = None) -> SensorCalibration:
    """The robot description's nominal camera and mounts (no calibration file)."""
    where = robot_source or f"robot description '{robot.name}'"
    return SensorCalibration(
        camera=_nominal_camera(robot),
        T_base_lidar=robot.sensors.lidar.mount.transform(),
        T_base_camera=robot.sensors.camera.mount.transform(),
        sources={"camera": f"{where} sensors.camera (nominal: horizontal_fov_deg, no distortion)",
                 "lidar_mount": f"{where} sensors.lidar.mount (nominal)",
                 "camera_mount": f"{where} sensors.camera.mount (nominal)"},
        camera_fields=f"{where} sensors.camera: nominal {{}} (from horizontal_fov_deg)",
    )


def sensor_calibration(robot, cal=None, path: str | Path | None = None,
                       robot_source: str | None = None) -> SensorCalibration:
    """The sensors of `robot` (a RobotDescription) as `cal` (a CalibrationFile loaded from `path`,
    or None) calibrates them; nominal where the file says nothing (module docstring).
    ConfigFileError naming the file and the field when the file does not fit the robot."""
    nominal = nominal_sensors(robot, robot_source)
    if cal is None:
        return nominal
    from calibration.calibration_file import camera_for_robot

    where = str(path) if path is not None else f"calibration of '{cal.robot}'"
    camera, T_cam_lidar = camera_for_robot(cal, robot, where)
    sources = {"camera": f"{where} camera", "lidar_mount": nominal.sources["lidar_mount"],
               "camera_mount": nominal.sources["camera_mount"]}
    T_base_lidar = nominal.T_base_lidar
    if cal.lidar_mount is not None:
        T_base_lidar = cal.lidar_mount.matrix()
        sources["lidar_mount"] = f"{where} lidar_mount"
        _on_the_body(robot, where, "lidar_mount.xyz_m", T_base_lidar)
    T_base_camera = nominal.T_base_camera
    if T_cam_lidar is not None:
        T_base_camera = T_base_lidar @ np.linalg.inv(T_cam_lidar)
        via = " and lidar_mount" if cal.lidar_mount is not None else f" and {nominal.sources['lidar_mount']}"
        sources["camera_mount"] = f"{where} lidar_to_camera{via}"
        _on_the_body(robot, where, "lidar_to_camera (the camera's position on base_link)", T_base_camera)
    return SensorCalibration(camera, T_base_lidar, T_base_camera, sources, path=where,
                             camera_fields=f"{where} camera.{{}}")


def _on_the_body(robot, where: str, field: str, T: np.ndarray) -> None:
    problem = robot.mount_problem(field, tuple(float(v) for v in T[:3, 3]))
    if problem is not None:
        raise ConfigFileError(f"{where}: {problem}")


__all__ = ["SensorCalibration", "nominal_sensors", "sensor_calibration"]
