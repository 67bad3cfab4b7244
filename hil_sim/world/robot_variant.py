"""A robot variant: one robot as built, departing from its description within build tolerances.

No two robots are alike: the camera's focal length and principal point differ from the lens's
datasheet, the lens distorts, and the lidar and camera sit a little off their drawn mounts. A
variant gives those departures; the simulator builds the robot as the variant says (the lidar and
the camera at the perturbed mounts, MuJoCo's camera with the variant's focal lengths and principal
point, the distortion applied to every render: hil_sim.sensors.camera_lens), while the
controller keeps reading the nominal robot description, unless it is given a calibration file.

A variant is named by a SPEC (`dct hil run --robot-variant SPEC`, `dct hil serve --robot-variant
SPEC`, `dct calibrate hil --robot-variant SPEC`, or a scenario's `robot_variant:` key):

* `nominal`: the robot as described (the simulator renders exactly as without a variant);
* an integer seed: every departure drawn uniformly within its bounds (`BOUNDS`), the same
  variant for the same seed on any machine; a lens that folds over inside the image is
  redrawn from the same stream;
* a YAML file (or, in a scenario, the mapping itself) with explicit values, validated with the
  same bounds (a value outside them is a one-line error naming the field)::

      camera:
        focal_scale: [1.012, 1.009]        # fx, fy over the nominal focal length (1 +- 0.03)
        principal_offset_px: [4.5, -7.0]   # cx, cy minus the image centre (+- 10 px)
        distortion: [-0.12, 0.05, 0.001, -0.0005, -0.01]   # k1 k2 p1 p2 k3 (OpenCV order)
      lidar_mount:                          # departures of T_base_link<-lidar
        dxyz_m: [0.01, -0.005, 0.0]         # added to the mount's position (+- 0.02 m)
        drpy_deg: [0.5, -1.0, 0.2]          # rotation about base_link's x, y, z (+- 2 deg)
      camera_mount: {dxyz_m: [0, 0, 0.01], drpy_deg: [0, 1.5, 0]}

  Missing sections or keys are no departure.

The seam for what a real robot's drivers report: `RobotVariant.true_camera()` is the camera's
true K and distortion (a camera driver's factory calibration, what the simulated images carry),
`true_lidar_mount()` and `true_camera_mount()` the mounts as built, `true_calibration()` a
calibration file holding the truth.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any

import numpy as np
from pydantic import Field
from scipy.spatial.transform import Rotation

from calibration.errors import ConfigFileError, load_yaml_model
from calibration.robot_description import Mount, RobotDescription
from hil_sim.world.scenario_objects import StrictModel

if TYPE_CHECKING:  # the lens and the camera model import numba: only when a variant is built
    from calibration.camera_model import CameraModel
    from hil_sim.sensors.camera_lens import CameraLens

#: Bounds of each departure: (low, high). Focal scale: fx and fy over the nominal focal length;
#: principal point offset in pixels; distortion of a small wide-angle lens (k1, k2, p1, p2, k3);
#: mount position (m, each axis) and rotation (deg, about each base_link axis).
BOUNDS: dict[str, tuple[float, float]] = {
    "focal_scale": (0.97, 1.03),
    "principal_offset_px": (-10.0, 10.0),
    "k1": (-0.30, 0.10),
    "k2": (-0.10, 0.15),
    "p1": (-0.003, 0.003),
    "p2": (-0.003, 0.003),
    "k3": (-0.05, 0.05),
    "dxyz_m": (-0.02, 0.02),
    "drpy_deg": (-2.0, 2.0),
}
#: A drawn variant's fy is fx times 1 +- this (square pixels, within manufacturing), kept in BOUNDS.
DRAWN_ASPECT_SPREAD = 0.005
#: Draws of the distortion before a seed is given up (a lens that folds over is redrawn).
MAX_LENS_DRAWS = 100


def _bounded(name: str):
    low, high = BOUNDS[name]
    return Annotated[float, Field(ge=low, le=high, allow_inf_nan=False)]


FocalScale = _bounded("focal_scale")
PrincipalOffset = _bounded("principal_offset_px")
K1, K2, P1, P2, K3 = (_bounded(k) for k in ("k1", "k2", "p1", "p2", "k3"))
Dxyz = _bounded("dxyz_m")
Drpy = _bounded("drpy_deg")


class CameraDeparture(StrictModel):
    """The camera's intrinsics as built, relative to the description's pinhole."""

    focal_scale: tuple[FocalScale, FocalScale] = (1.0, 1.0)
    principal_offset_px: tuple[PrincipalOffset, PrincipalOffset] = (0.0, 0.0)
    distortion: tuple[K1, K2, P1, P2, K3] = (0.0, 0.0, 0.0, 0.0, 0.0)


class MountDeparture(StrictModel):
    """A mount as built: position offset in base_link, then a small turn about base_link's axes."""

    dxyz_m: tuple[Dxyz, Dxyz, Dxyz] = (0.0, 0.0, 0.0)
    drpy_deg: tuple[Drpy, Drpy, Drpy] = (0.0, 0.0, 0.0)

    def apply(self, mount: Mount) -> np.ndarray:
        """T_base<-sensor as built: R = R_xyz(drpy) R_nominal, t = t_nominal + dxyz."""
        T = mount.transform()
        T[:3, :3] = Rotation.from_euler("xyz", self.drpy_deg, degrees=True).as_matrix() @ T[:3, :3]
        T[:3, 3] += np.asarray(self.dxyz_m)
        return T


class VariantDepartures(StrictModel):
    """A variant file (module docstring): every departure from the robot description."""

    camera: CameraDeparture = Field(default_factory=CameraDeparture)
    lidar_mount: MountDeparture = Field(default_factory=MountDeparture)
    camera_mount: MountDeparture = Field(default_factory=MountDeparture)

    @property
    def is_nominal(self) -> bool:
        return self == VariantDepartures()


class VariantError(ConfigFileError):
    """A robot variant SPEC that cannot be used (unknown, out of bounds, a lens that folds over)."""


@dataclass(frozen=True)
class RobotVariant:
    """A resolved variant: its SPEC, the departures, and the truth they make of the robot."""

    spec: str
    #: "nominal", "seed", "file" or "scenario".
    source: str
    departures: VariantDepartures
    #: The robot description as built: the lidar and camera mounts moved (the rest unchanged).
    robot: RobotDescription
    nominal_robot: RobotDescription
    #: The camera as built (K, distortion, image size, and the canvas MuJoCo renders it from);
    #: None: the description's pinhole, rendered as without a variant.
    lens: "CameraLens | None"

    @property
    def is_nominal(self) -> bool:
        return self.departures.is_nominal

    def true_camera(self) -> "CameraModel":
        """The camera's true K and distortion: what a camera driver publishes as its camera_info."""
        from calibration.camera_model import CameraModel

        if self.lens is None:
            cam = self.nominal_robot.sensors.camera
            return CameraModel(cam.nominal_intrinsics(), np.zeros(5), cam.width_px, cam.height_px)
        return CameraModel(self.lens.K.copy(), _five(self.lens.dist), self.lens.width_px, self.lens.height_px)

    def true_lidar_mount(self) -> np.ndarray:
        """T_base_link<-lidar as built (4x4)."""
        return self.robot.sensors.lidar.mount.transform()

    def true_camera_mount(self) -> np.ndarray:
        """T_base_link<-camera (optical frame) as built (4x4)."""
        return self.robot.sensors.camera.mount.transform()

    def true_T_cam_lidar(self) -> np.ndarray:
        """T_camera<-lidar as built (4x4)."""
        return np.linalg.inv(self.true_camera_mount()) @ self.true_lidar_mount()

    def true_calibration(self, method: str = "robot variant ground truth"):
        """A calibration file (calibration.calibration_file.CalibrationFile) holding the truth."""
        from calibration.calibration_file import RigidTransform, make_calibration

        cam = self.true_camera()
        cal = make_calibration(self.robot.name, cam.K, cam.dist, cam.width_px, cam.height_px, self.true_T_cam_lidar(),
                               method=f"{method} ({self.label})")
        return cal.model_copy(update={"lidar_mount": RigidTransform.from_matrix(self.true_lidar_mount())})

    @property
    def label(self) -> str:
        return {"seed": f"seed {self.spec}", "file": f"file {self.spec}"}.get(self.source, self.source)

    def to_dict(self) -> dict:
        """The episode JSON's `robot_variant` section: the spec, the departures and the truth."""
        cam = self.true_camera()
        return {
            "spec": self.spec,
            "source": self.source,
            "departures": self.departures.model_dump(mode="json"),
            "camera": {"width_px": cam.width_px, "height_px": cam.height_px, "fx": cam.fx, "fy": cam.fy, "cx": cam.cx,
                       "cy": cam.cy, "distortion": [float(x) for x in cam.dist]},
            "lidar_mount": _mount_dict(self.robot.sensors.lidar.mount),
            "camera_mount": _mount_dict(self.robot.sensors.camera.mount),
        }


def _five(dist: np.ndarray) -> np.ndarray:
    out = np.zeros(5)
    out[: len(dist)] = dist
    return out


def _mount_dict(mount: Mount) -> dict:
    return {"xyz_m": [float(x) for x in mount.xyz_m], "rpy_deg": [float(a) for a in mount.rpy_deg]}


def _as_mount(T: np.ndarray) -> Mount:
    rpy = Rotation.from_matrix(T[:3, :3]).as_euler("xyz", degrees=True)
    return Mount(xyz_m=tuple(float(x) for x in T[:3, 3]), rpy_deg=tuple(float(a) for a in rpy))


def build_variant(departures: VariantDepartures, robot: RobotDescription, spec: str, source: str) -> RobotVariant:
    """The variant of `robot` the departures make (VariantError naming the field when its lens folds over)."""
    if departures.is_nominal:
        return RobotVariant(spec, source, departures, robot, robot, None)
    sensors = robot.sensors
    lidar = sensors.lidar.model_copy(update={"mount": _as_mount(departures.lidar_mount.apply(sensors.lidar.mount))})
    camera = sensors.camera.model_copy(
        update={"mount": _as_mount(departures.camera_mount.apply(sensors.camera.mount))})
    built = robot.model_copy(update={"sensors": sensors.model_copy(update={"lidar": lidar, "camera": camera})})
    from hil_sim.sensors.camera_lens import LensError

    try:
        lens = camera_lens(departures.camera, robot)
    except LensError as exc:
        raise VariantError(f"robot variant {spec}: camera.distortion: {exc}") from None
    return RobotVariant(spec, source, departures, built, robot, lens)


def camera_lens(camera: CameraDeparture, robot: RobotDescription) -> "CameraLens | None":
    """The camera lens of a departure (None: the nominal pinhole); LensError when it folds over."""
    from hil_sim.sensors.camera_lens import CameraLens

    if camera == CameraDeparture():
        return None
    cam = robot.sensors.camera
    return CameraLens.build(_camera_K(camera, robot), np.array(camera.distortion), cam.width_px, cam.height_px)


def _camera_K(camera: CameraDeparture, robot: RobotDescription) -> np.ndarray:
    K = robot.sensors.camera.nominal_intrinsics()
    f = K[0, 0]
    K[0, 0], K[1, 1] = f * camera.focal_scale[0], f * camera.focal_scale[1]
    K[0, 2] += camera.principal_offset_px[0]
    K[1, 2] += camera.principal_offset_px[1]
    return K


def draw_departures(seed: int, robot: RobotDescription) -> VariantDepartures:
    """Departures drawn uniformly within BOUNDS from `seed` (the same on any machine); a lens that
    folds over inside `robot`'s image is redrawn from the same stream."""
    rng = np.random.default_rng([int(seed), 0x7A41])

    def u(name: str, n: int) -> tuple[float, ...]:
        low, high = BOUNDS[name]
        return tuple(float(x) for x in rng.uniform(low, high, n))

    fx_scale = u("focal_scale", 1)[0]
    aspect = float(rng.uniform(1 - DRAWN_ASPECT_SPREAD, 1 + DRAWN_ASPECT_SPREAD))
    fy_scale = float(np.clip(fx_scale * aspect, *BOUNDS["focal_scale"]))
    principal = u("principal_offset_px", 2)
    mounts = {name: MountDeparture(dxyz_m=u("dxyz_m", 3), drpy_deg=u("drpy_deg", 3))
              for name in ("lidar_mount", "camera_mount")}
    from hil_sim.sensors.camera_lens import LensError, check_lens

    cam = robot.sensors.camera
    for _ in range(MAX_LENS_DRAWS):
        dist = tuple(u(k, 1)[0] for k in ("k1", "k2", "p1", "p2", "k3"))
        camera = CameraDeparture(focal_scale=(fx_scale, fy_scale), principal_offset_px=principal, distortion=dist)
        try:
            check_lens(_camera_K(camera, robot), np.array(dist), cam.width_px, cam.height_px)
        except LensError:
            continue
        return VariantDepartures(camera=camera, **mounts)
    raise VariantError(f"robot variant seed {seed}: no lens within the bounds fits the image in {MAX_LENS_DRAWS} draws")


def load_departures(path: str | Path) -> VariantDepartures:
    """A variant file (ConfigFileError naming the file, field and reason)."""
    return load_yaml_model(Path(path), VariantDepartures, what="robot variant")


def resolve_variant(spec: Any, robot: RobotDescription, source: str | None = None) -> RobotVariant:
    """The variant a SPEC names (module docstring): 'nominal', an integer seed (int or digits), a
    path to a variant file, or (from a scenario) VariantDepartures. VariantError on a bad SPEC."""
    if isinstance(spec, VariantDepartures):
        return build_variant(spec, robot, "scenario", source or "scenario")
    if isinstance(spec, bool):
        raise VariantError(f"robot variant: SPEC must be nominal, a seed or a file, got {spec!r}")
    if isinstance(spec, int) or (isinstance(spec, str) and spec.strip().isdigit()):
        seed = int(spec)
        if not 0 <= seed < 2 ** 32:
            raise VariantError(f"robot variant: the seed must be in [0, 2**32), got {seed}")
        return build_variant(draw_departures(seed, robot), robot, str(seed), source or "seed")
    text = str(spec).strip()
    if text == "nominal":
        return build_variant(VariantDepartures(), robot, "nominal", source or "nominal")
    path = Path(text)
    if not path.is_file():
        raise VariantError(f"robot variant '{text}': not 'nominal', not a seed (an integer >= 0) and no such file")
    try:
        departures = load_departures(path)
    except VariantError:
        raise
    except ConfigFileError as exc:
        raise VariantError(str(exc)) from None
    return build_variant(departures, robot, str(path), source or "file")


__all__ = ["BOUNDS", "CameraDeparture", "MountDeparture", "VariantDepartures", "RobotVariant", "VariantError",
           "build_variant", "camera_lens", "draw_departures", "load_departures", "resolve_variant"]
