"""The robot description: one YAML file per robot, validated with pydantic on load.

Everything that depends on the robot's body (footprint, wheel geometry, limits, motor
data, sensor mounts, CAN timing) is read from here; no other module hard-codes it.
"""
from __future__ import annotations

from importlib import resources
from pathlib import Path
from typing import Annotated, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, model_validator
from scipy.spatial.transform import Rotation

from calibration.errors import ConfigFileError, load_yaml_model


#: Where a sensor mount may be (base_link: footprint centre on the ground, z up). A mount
#: farther than this outside the footprint's bounding box horizontally, below the floor
#: (z < 0), or higher than body_height_m + MOUNT_MAX_ABOVE_BODY_M is a typo (a value in mm, a
#: sign), not a robot, and the file is refused. rpy angles must lie in [-360, 360] degrees.
MOUNT_MAX_OUTSIDE_FOOTPRINT_M = 0.5
MOUNT_MAX_ABOVE_BODY_M = 1.0
MOUNT_MAX_ANGLE_DEG = 360.0

FiniteFloat = Annotated[float, Field(allow_inf_nan=False)]
AngleDeg = Annotated[float, Field(allow_inf_nan=False, ge=-MOUNT_MAX_ANGLE_DEG, le=MOUNT_MAX_ANGLE_DEG)]


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)


class Mount(_Strict):
    """A rigid mount: the sensor frame's pose in base_link (finite; angles in [-360, 360] deg)."""

    xyz_m: tuple[FiniteFloat, FiniteFloat, FiniteFloat]
    rpy_deg: tuple[AngleDeg, AngleDeg, AngleDeg] = (0.0, 0.0, 0.0)

    def rotation(self) -> np.ndarray:
        """3x3 rotation of the sensor frame in base_link (extrinsic x-y-z, i.e. R = Rz Ry Rx)."""
        return Rotation.from_euler("xyz", self.rpy_deg, degrees=True).as_matrix()

    def transform(self) -> np.ndarray:
        """4x4 homogeneous transform T_base<-sensor."""
        t = np.eye(4)
        t[:3, :3] = self.rotation()
        t[:3, 3] = self.xyz_m
        return t


class Footprint(_Strict):
    length_m: float = Field(gt=0.05, lt=5.0)
    width_m: float = Field(gt=0.05, lt=5.0)

    def vertices(self) -> np.ndarray:
        """Counter-clockwise corners (4x2) in base_link, starting front-left."""
        hl, hw = self.length_m / 2, self.width_m / 2
        return np.array([[hl, hw], [-hl, hw], [-hl, -hw], [hl, -hw]])

    def halfspaces(self) -> tuple[np.ndarray, np.ndarray]:
        """(G, g) with the footprint = {x : G x <= g}, one row per edge (front, left, rear, right)."""
        hl, hw = self.length_m / 2, self.width_m / 2
        G = np.array([[1.0, 0.0], [0.0, 1.0], [-1.0, 0.0], [0.0, -1.0]])
        g = np.array([hl, hw, hl, hw])
        return G, g


class Drive(_Strict):
    type: Literal["differential"]
    wheelbase_m: float = Field(gt=0.0, lt=3.0)
    track_m: float = Field(gt=0.0, lt=3.0)
    wheel_radius_m: float = Field(gt=0.005, lt=1.0)
    wheel_width_m: float = Field(gt=0.001, lt=1.0)
    #: Skid-steer slip: the yaw rate the wheel speed difference implies (and what 0x111/0x221
    #: carry as angular velocity) divided by the body's true yaw rate. 1.0 = an ideal
    #: differential drive. Calibrate on the robot: command a spin, compare with the gyro.
    skid_steer_yaw_factor: float = Field(default=1.0, ge=1.0, le=10.0)


class Limits(_Strict):
    max_linear_speed_mps: float = Field(gt=0.0, le=5.0)
    max_angular_speed_radps: float = Field(gt=0.0, le=20.0)
    max_linear_accel_mps2: float = Field(gt=0.0, le=50.0)
    max_angular_accel_radps2: float = Field(gt=0.0, le=200.0)


class Motors(_Strict):
    count: Literal[2, 4]
    torque_constant_nm_per_a: float = Field(gt=0.0, lt=10.0)
    current_limit_a: float = Field(gt=0.0, lt=500.0)
    resistance_ohm: float = Field(gt=0.0, lt=100.0)
    supply_voltage_v: float = Field(gt=0.0, lt=100.0)
    encoder_pulses_per_rev: int = Field(gt=0, lt=1_000_000)
    speed_loop_kp_a_per_radps: float = Field(ge=0.0, lt=1000.0)
    speed_loop_ki_a_per_rad: float = Field(ge=0.0, lt=100000.0)
    command_timeout_s: float = Field(gt=0.0, le=5.0)


class LidarDescription(_Strict):
    mount: Mount


class CameraDescription(_Strict):
    mount: Mount
    width_px: int = Field(gt=0, le=8192)
    height_px: int = Field(gt=0, le=8192)
    horizontal_fov_deg: float = Field(gt=1.0, lt=179.0)

    def nominal_intrinsics(self) -> np.ndarray:
        """Pinhole K from the field of view: square pixels, principal point at the image centre in
        OpenCV's convention (pixel centres at integers, so cx = (W - 1) / 2)."""
        fx = (self.width_px / 2) / np.tan(np.radians(self.horizontal_fov_deg) / 2)
        return np.array([[fx, 0.0, (self.width_px - 1) / 2], [0.0, fx, (self.height_px - 1) / 2], [0.0, 0.0, 1.0]])


class ImuDescription(_Strict):
    mount: Mount


class Sensors(_Strict):
    lidar: LidarDescription
    camera: CameraDescription
    imu: ImuDescription


class CanSettings(_Strict):
    bitrate_bps: int = Field(gt=0, le=1_000_000)
    command_period_s: float = Field(gt=0.0, le=0.1)
    feedback_timeout_s: float = Field(gt=0.0, le=1.0)


class RobotDescription(_Strict):
    name: str = Field(min_length=1)
    mass_kg: float = Field(gt=0.0, lt=1000.0)
    body_height_m: float = Field(gt=0.0, lt=3.0)
    footprint: Footprint
    drive: Drive
    limits: Limits
    motors: Motors
    sensors: Sensors
    can: CanSettings

    @property
    def body_max_angular_speed_radps(self) -> float:
        """The body yaw rate the base can reach (its 0x111 limit divided by the skid-steer factor)."""
        return self.limits.max_angular_speed_radps / self.drive.skid_steer_yaw_factor

    @property
    def body_max_angular_accel_radps2(self) -> float:
        return self.limits.max_angular_accel_radps2 / self.drive.skid_steer_yaw_factor

    @model_validator(mode="after")
    def _wheels_fit_the_footprint(self) -> "RobotDescription":
        if self.drive.track_m > self.footprint.width_m:
            raise ValueError(
                f"drive.track_m ({self.drive.track_m}) is wider than footprint.width_m ({self.footprint.width_m})"
            )
        if self.drive.wheelbase_m > self.footprint.length_m:
            raise ValueError(
                f"drive.wheelbase_m ({self.drive.wheelbase_m}) is longer than footprint.length_m "
                f"({self.footprint.length_m})"
            )
        return self

    @model_validator(mode="after")
    def _sensors_on_the_body(self) -> "RobotDescription":
        """Every sensor mount lies on or near the body (see MOUNT_MAX_* above)."""
        mounts = {name: getattr(self.sensors, name).mount.xyz_m for name in ("lidar", "camera", "imu")}
        problems = [p for name, xyz in mounts.items() if (p := self.mount_problem(f"sensors.{name}.mount.xyz_m", xyz))]
        if problems:
            raise ValueError("; ".join(problems))
        return self

    def mount_problem(self, field: str, xyz_m: tuple[float, float, float]) -> str | None:
        """Why a sensor at xyz_m (base_link) cannot be on this robot (MOUNT_MAX_* above), None when
        it can: the description's own mounts and a calibration file's are judged alike."""
        x, y, z = xyz_m
        half_x = self.footprint.length_m / 2 + MOUNT_MAX_OUTSIDE_FOOTPRINT_M
        half_y = self.footprint.width_m / 2 + MOUNT_MAX_OUTSIDE_FOOTPRINT_M
        top = self.body_height_m + MOUNT_MAX_ABOVE_BODY_M
        where = f"{field} {[round(float(v), 4) for v in xyz_m]}"
        if abs(x) > half_x or abs(y) > half_y:
            return (f"{where} is more than {MOUNT_MAX_OUTSIDE_FOOTPRINT_M} m outside the footprint "
                    f"(|x| <= {half_x:g} m, |y| <= {half_y:g} m)")
        if z < 0.0:
            return f"{where} is below the floor (z must be >= 0 m in base_link)"
        if z > top:
            return f"{where} is more than {MOUNT_MAX_ABOVE_BODY_M} m above the body (z <= {top:g} m)"
        return None


def load_robot_description(path: str | Path | None = None) -> RobotDescription:
    """Load and validate a robot description; None loads the shipped LIMO description.

    A bad file raises ConfigFileError naming the file, the field and the reason.
    """
    if path is None:
        path = resources.files("calibration") / "robots" / "limo.yaml"
    return load_yaml_model(Path(str(path)), RobotDescription, what="robot description")


__all__ = ["RobotDescription", "Mount", "Footprint", "load_robot_description", "ConfigFileError",
           "MOUNT_MAX_OUTSIDE_FOOTPRINT_M", "MOUNT_MAX_ABOVE_BODY_M", "MOUNT_MAX_ANGLE_DEG"]
