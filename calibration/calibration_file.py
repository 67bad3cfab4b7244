"""Per-robot calibration file (YAML): camera intrinsics, distortion, T_camera<-lidar, provenance.

Example::

    robot: limo
    camera:
      width_px: 640
      height_px: 480
      fx: 336.0
      fy: 336.0
      cx: 319.5
      cy: 239.5
      distortion: [0.0, 0.0, 0.0, 0.0, 0.0]   # OpenCV order k1 k2 p1 p2 [k3 ...]
    lidar_to_camera:            # T_camera<-lidar: p_cam = R p_lidar + t; optional until calibrated
      xyz_m: [0.0, 0.05, -0.08]
      rpy_deg: [-90.0, 0.0, -90.0]   # or quaternion_xyzw: [...] or rotation_matrix: 3x3
    lidar_mount:                # T_base_link<-lidar: p_base = R p_lidar + t; optional (else the
      xyz_m: [0.1, 0.0, 0.15]   # robot description's lidar mount)
      rpy_deg: [0.0, 0.0, 0.0]
    provenance:
      date: 2025-01-01T12:00:00
      method: "checkerboard 9x6, 25 mm; calibrateCamera"
      intrinsics_rms_px: 0.21
      extrinsic_rms_m: 0.012
    wheel_odometry:             # optional; written by `dct calibrate wheels`
      effective_track_m: 0.524  # turns the wheel distance difference into yaw (skid-steer: > track_m)
      wheel_scale: 0.985        # true distance / wheel distance
      fit:
        reference: icp          # or ground_truth
        source: "hall loop 2025-01-02"
        windows: 412
        window_s: 0.5
        distance_m: 38.2
        rotation_deg: 1630.0
        residual_distance_rms_m: 0.004
        residual_yaw_rms_deg: 0.4
        date: 2025-01-02T10:00:00

rpy_deg uses the robot description's convention (extrinsic x-y-z: R = Rz(yaw) Ry(pitch) Rx(roll)).
Every problem raises ConfigFileError naming the file, the field and the reason, on one line.

What is refused when the file loads: any non-finite number; a focal length that is not positive;
a principal point outside the image; a lidar-camera translation longer than
MAX_LIDAR_CAMERA_TRANSLATION_M (both sensors sit on one robot); rpy angles outside [-360, 360]
degrees; a rotation_matrix that is not orthonormal (max |R R^T - I| > 1e-4) or is a reflection
(det < 0); a quaternion whose norm is not 1 (within 1e-3); a wheel_odometry effective track that
is not in (0, MAX_EFFECTIVE_TRACK_M] or a wheel scale outside WHEEL_SCALE_RANGE (the fit refuses
values outside tighter, robot-relative ranges: calibration.wheel_odometry).
"""
from __future__ import annotations

import datetime as _dt
from pathlib import Path
from typing import Annotated, Literal, Optional

import numpy as np
import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator
from scipy.spatial.transform import Rotation

from calibration.camera_model import VALID_DISTORTION_LENGTHS, CameraModel
from calibration.errors import ConfigFileError, format_validation_error, load_yaml_model
from calibration.outputs import atomic_write_text

#: T_camera<-lidar translations longer than this are refused: both sensors sit on one robot.
MAX_LIDAR_CAMERA_TRANSLATION_M = 2.0
MAX_ANGLE_DEG = 360.0
#: wheel_odometry values beyond these are a typo (mm for m), not a robot. The robot description
#: allows a track up to 3 m; the fit allows 5 x the geometric track.
MAX_EFFECTIVE_TRACK_M = 15.0
WHEEL_SCALE_RANGE = (0.8, 1.2)

FiniteFloat = Annotated[float, Field(allow_inf_nan=False)]
AngleDeg = Annotated[float, Field(allow_inf_nan=False, ge=-MAX_ANGLE_DEG, le=MAX_ANGLE_DEG)]
Row3 = tuple[FiniteFloat, FiniteFloat, FiniteFloat]


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)


class CameraIntrinsics(_Strict):
    width_px: int = Field(gt=0, le=16384)
    height_px: int = Field(gt=0, le=16384)
    fx: float = Field(gt=0.0, allow_inf_nan=False)
    fy: float = Field(gt=0.0, allow_inf_nan=False)
    cx: float = Field(allow_inf_nan=False)
    cy: float = Field(allow_inf_nan=False)
    skew: float = Field(default=0.0, allow_inf_nan=False)
    distortion: list[float] = Field(default_factory=lambda: [0.0] * 5)

    @field_validator("distortion")
    @classmethod
    def _distortion_length(cls, v: list[float]) -> list[float]:
        if len(v) not in VALID_DISTORTION_LENGTHS:
            raise ValueError(f"must have one of {VALID_DISTORTION_LENGTHS} coefficients (OpenCV order), got {len(v)}")
        if not all(np.isfinite(v)):
            raise ValueError(f"coefficients must be finite, got {v}")
        return v

    @model_validator(mode="after")
    def _principal_point_in_image(self) -> "CameraIntrinsics":
        if not (0.0 <= self.cx <= self.width_px and 0.0 <= self.cy <= self.height_px):
            raise ValueError(
                f"principal point ({self.cx}, {self.cy}) lies outside the {self.width_px}x{self.height_px} image"
            )
        return self

    def K(self) -> np.ndarray:
        return np.array([[self.fx, self.skew, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    def camera_model(self) -> CameraModel:
        return CameraModel(self.K(), np.array(self.distortion), self.width_px, self.height_px)


class RigidTransform(_Strict):
    """A rigid transform: translation plus exactly one rotation form."""

    xyz_m: Row3
    rpy_deg: Optional[tuple[AngleDeg, AngleDeg, AngleDeg]] = None
    quaternion_xyzw: Optional[tuple[FiniteFloat, FiniteFloat, FiniteFloat, FiniteFloat]] = None
    rotation_matrix: Optional[tuple[Row3, Row3, Row3]] = None

    @field_validator("xyz_m")
    @classmethod
    def _plausible_translation(cls, v):
        length_m = float(np.linalg.norm(v))
        if length_m > MAX_LIDAR_CAMERA_TRANSLATION_M:
            raise ValueError(f"translation is {length_m:.3g} m long, implausible between two sensors on one robot "
                             f"(at most {MAX_LIDAR_CAMERA_TRANSLATION_M} m)")
        return v

    @model_validator(mode="after")
    def _one_valid_rotation(self) -> "RigidTransform":
        given = [k for k in ("rpy_deg", "quaternion_xyzw", "rotation_matrix") if getattr(self, k) is not None]
        if len(given) != 1:
            raise ValueError(f"give exactly one of rpy_deg, quaternion_xyzw, rotation_matrix (got {given or 'none'})")
        if self.quaternion_xyzw is not None:
            q = np.array(self.quaternion_xyzw)
            if abs(np.linalg.norm(q) - 1.0) > 1e-3:
                raise ValueError(f"quaternion_xyzw must have unit norm (got norm {np.linalg.norm(q):.6g})")
        if self.rotation_matrix is not None:
            R = np.array(self.rotation_matrix)
            err = np.abs(R @ R.T - np.eye(3)).max()
            if err > 1e-4:
                raise ValueError(f"rotation_matrix is not orthonormal (max |R R^T - I| = {err:.3g})")
            det = np.linalg.det(R)
            if det < 0:
                raise ValueError(f"rotation_matrix has determinant {det:.3g} (a reflection, not a rotation)")
        return self

    def rotation(self) -> np.ndarray:
        if self.rpy_deg is not None:
            return Rotation.from_euler("xyz", self.rpy_deg, degrees=True).as_matrix()
        if self.quaternion_xyzw is not None:
            return Rotation.from_quat(self.quaternion_xyzw).as_matrix()
        return np.array(self.rotation_matrix, dtype=float)

    def matrix(self) -> np.ndarray:
        T = np.eye(4)
        T[:3, :3] = self.rotation()
        T[:3, 3] = self.xyz_m
        return T

    @classmethod
    def from_matrix(cls, T: np.ndarray) -> "RigidTransform":
        return cls(**cls.fields_from_matrix(T))

    @staticmethod
    def fields_from_matrix(T: np.ndarray) -> dict:
        """The file fields of a 4x4 transform: xyz_m plus rpy_deg, or quaternion_xyzw near gimbal lock."""
        T = np.asarray(T, dtype=float)
        xyz = [float(x) for x in T[:3, 3]]
        if not np.all(np.isfinite(T[:3, :3])):  # let validation name the non-finite values
            return {"xyz_m": xyz, "rotation_matrix": T[:3, :3].tolist()}
        rot = Rotation.from_matrix(T[:3, :3])
        if abs(np.degrees(np.arcsin(np.clip(-T[2, 0], -1.0, 1.0)))) > 85.0:  # near gimbal lock
            return {"xyz_m": xyz, "quaternion_xyzw": [float(q) for q in rot.as_quat()]}
        return {"xyz_m": xyz, "rpy_deg": [float(a) for a in rot.as_euler("xyz", degrees=True)]}


class Provenance(_Strict):
    date: _dt.datetime
    method: str = Field(min_length=1)
    intrinsics_rms_px: Optional[float] = Field(default=None, ge=0.0, allow_inf_nan=False)
    per_image_rms_px: Optional[dict[str, float]] = None
    extrinsic_rms_m: Optional[float] = Field(default=None, ge=0.0, allow_inf_nan=False)
    n_images: Optional[int] = Field(default=None, ge=0)
    n_board_poses: Optional[int] = Field(default=None, ge=0)
    notes: Optional[str] = None


class WheelOdometryFitRecord(_Strict):
    """How the wheel odometry values were found (calibration.wheel_odometry.fit_wheel_odometry)."""

    reference: Literal["ground_truth", "icp"]
    source: str = Field(min_length=1)
    windows: int = Field(ge=1)
    window_s: float = Field(gt=0.0, allow_inf_nan=False)
    distance_m: float = Field(gt=0.0, allow_inf_nan=False)
    rotation_deg: float = Field(gt=0.0, allow_inf_nan=False)
    residual_distance_rms_m: float = Field(ge=0.0, allow_inf_nan=False)
    residual_yaw_rms_deg: float = Field(ge=0.0, allow_inf_nan=False)
    date: _dt.datetime


class WheelOdometryCalibration(_Strict):
    """Wheel odometry of this robot: yaw = wheel_scale * (dR - dL) / effective_track_m, distance =
    wheel_scale * (dL + dR) / 2. Read at run time through calibration.wheel_odometry.wheel_params."""

    effective_track_m: float = Field(gt=0.0, le=MAX_EFFECTIVE_TRACK_M, allow_inf_nan=False)
    wheel_scale: float = Field(ge=WHEEL_SCALE_RANGE[0], le=WHEEL_SCALE_RANGE[1], allow_inf_nan=False)
    fit: WheelOdometryFitRecord


class CalibrationFile(_Strict):
    robot: str = Field(min_length=1)
    camera: CameraIntrinsics
    lidar_to_camera: Optional[RigidTransform] = None
    #: T_base_link<-lidar, the lidar's mount as calibrated; None: the robot description's mount.
    #: The camera's pose on the base is then this composed with lidar_to_camera's inverse.
    lidar_mount: Optional[RigidTransform] = None
    provenance: Provenance
    wheel_odometry: Optional[WheelOdometryCalibration] = None

    def camera_model(self) -> CameraModel:
        return self.camera.camera_model()

    def T_cam_lidar(self) -> np.ndarray:
        """4x4 T_camera<-lidar; ConfigFileError if the file has no extrinsic yet."""
        if self.lidar_to_camera is None:
            raise ConfigFileError(f"calibration for robot '{self.robot}' has no lidar_to_camera extrinsic yet")
        return self.lidar_to_camera.matrix()

    def T_base_lidar(self, robot) -> np.ndarray:
        """4x4 T_base_link<-lidar: the calibrated mount, else `robot`'s (a RobotDescription) nominal one."""
        return self.lidar_mount.matrix() if self.lidar_mount is not None else robot.sensors.lidar.mount.transform()


def camera_for_robot(cal: CalibrationFile, robot, path: str | Path) -> tuple[CameraModel, np.ndarray | None]:
    """(camera model, T_cam_lidar or None without the extrinsic) of a calibration for `robot`
    (a RobotDescription), for the controller's VPP partition; ConfigFileError naming the file
    and field when the calibration is another robot's or another camera's."""
    if cal.robot != robot.name:
        raise ConfigFileError(f"{path}: robot: the calibration is for robot '{cal.robot}', the robot description "
                              f"is '{robot.name}'")
    cam = robot.sensors.camera
    if (cal.camera.width_px, cal.camera.height_px) != (cam.width_px, cam.height_px):
        raise ConfigFileError(f"{path}: camera: {cal.camera.width_px}x{cal.camera.height_px} px, the robot's camera "
                              f"is {cam.width_px}x{cam.height_px} px")
    return cal.camera_model(), (cal.T_cam_lidar() if cal.lidar_to_camera is not None else None)


def load_calibration(path: str | Path) -> CalibrationFile:
    """Load and validate a calibration file; any problem raises ConfigFileError."""
    return load_yaml_model(Path(path), CalibrationFile, what="calibration file")


def calibration_yaml(cal: CalibrationFile) -> str:
    """The YAML text of a calibration (validated again, as load_calibration would read it)."""
    data = cal.model_dump(mode="json", exclude_none=True)
    try:
        CalibrationFile.model_validate(data)
    except ValidationError as exc:  # a field assigned after construction (no validate_assignment)
        raise ConfigFileError(f"calibration is invalid: {format_validation_error(exc)}") from None
    return yaml.safe_dump(data, sort_keys=False)


def save_calibration(cal: CalibrationFile, path: str | Path) -> None:
    """Write a calibration file atomically (validated again before writing)."""
    atomic_write_text(path, calibration_yaml(cal))


def make_calibration(
    robot: str,
    K: np.ndarray,
    dist: np.ndarray,
    width_px: int,
    height_px: int,
    T_cam_lidar: np.ndarray | None,
    method: str,
    **provenance,
) -> CalibrationFile:
    """Build a validated CalibrationFile from arrays (ConfigFileError on bad values)."""
    K = np.asarray(K, dtype=float)
    data = {
        "robot": robot,
        "camera": {"width_px": width_px, "height_px": height_px, "fx": K[0, 0], "fy": K[1, 1], "cx": K[0, 2],
                   "cy": K[1, 2], "skew": K[0, 1], "distortion": [float(x) for x in np.ravel(dist)]},
        "provenance": {"date": _dt.datetime.now().replace(microsecond=0), "method": method, **provenance},
    }
    if T_cam_lidar is not None:
        data["lidar_to_camera"] = RigidTransform.fields_from_matrix(T_cam_lidar)
    try:
        return CalibrationFile.model_validate(data)
    except ValidationError as exc:
        raise ConfigFileError(f"calibration is invalid: {format_validation_error(exc)}") from None


def calibration_from_opencalib(
    intrinsic_json: str | Path, extrinsic_json: str | Path, width_px: int, height_px: int, robot: str = "opencalib"
) -> CalibrationFile:
    """Import OpenCalib (SensorsCalibration) camera-intrinsic and lidar-to-camera extrinsic JSON files.

    The image size is passed explicitly: OpenCalib's img_dist_w/h may not match the image.
    """
    import json

    def _param(path: Path) -> dict:
        try:
            doc = json.loads(Path(path).read_text(encoding="utf-8"))
            (entry,) = doc.values()
            return entry["param"]
        except (OSError, ValueError, KeyError, TypeError, AttributeError) as exc:
            raise ConfigFileError(f"OpenCalib file {path}: cannot read ({exc})") from exc

    try:
        p_in = _param(Path(intrinsic_json))
        K = np.array(p_in["cam_K"]["data"], dtype=float)
        dist = np.array(p_in["cam_dist"]["data"], dtype=float).ravel()
        T = np.array(_param(Path(extrinsic_json))["sensor_calib"]["data"], dtype=float)
    except (KeyError, TypeError, ValueError) as exc:
        raise ConfigFileError(f"OpenCalib files {intrinsic_json}, {extrinsic_json}: missing or bad field ({exc})") from exc
    if K.shape != (3, 3) or T.shape != (4, 4):
        raise ConfigFileError(f"OpenCalib: cam_K must be 3x3 and sensor_calib 4x4, got {K.shape}, {T.shape}")
    for name, arr, src in (("cam_K", K, intrinsic_json), ("cam_dist", dist, intrinsic_json),
                           ("sensor_calib", T, extrinsic_json)):
        if not np.all(np.isfinite(arr)):
            raise ConfigFileError(f"OpenCalib file {src}: {name} has a non-finite value (got {arr.ravel().tolist()})")
    if not np.allclose(T[3], [0.0, 0.0, 0.0, 1.0]):
        raise ConfigFileError(f"OpenCalib file {extrinsic_json}: sensor_calib last row must be [0, 0, 0, 1], "
                              f"got {T[3].tolist()}")
    # Re-orthonormalize the 6-digit rotation before storing it as rpy.
    U, _, Vt = np.linalg.svd(T[:3, :3])
    if np.abs(T[:3, :3] - U @ Vt).max() > 1e-3 or np.linalg.det(U @ Vt) < 0:
        raise ConfigFileError(f"OpenCalib file {extrinsic_json}: sensor_calib rotation is not a rotation "
                              f"(not orthonormal, or a reflection)")
    T = T.copy()
    T[:3, :3] = U @ Vt
    return make_calibration(robot, K, dist, width_px, height_px, T, method="imported from OpenCalib JSON")


__all__ = ["CalibrationFile", "CameraIntrinsics", "RigidTransform", "Provenance", "WheelOdometryCalibration",
           "WheelOdometryFitRecord", "MAX_EFFECTIVE_TRACK_M", "camera_for_robot", "WHEEL_SCALE_RANGE", "load_calibration",
           "save_calibration", "calibration_yaml", "MAX_LIDAR_CAMERA_TRANSLATION_M", "make_calibration", "calibration_from_opencalib", "ConfigFileError"]
