"""The partition stage of the tick (Algorithm 1 lines 3-13): which lidar points are P_fix.

A strategy with one interface, chosen once when the controller is built from the config's
`partition` setting (PARTITIONS below; strategies are objects, not `if` branches in the tick):

* `all-fixed` (`AllFixedPartition`): every point is P_fix and the planner may always drive (the
  NeuPAN-like baseline, and every planner that does not read the camera).
* `vpp` (`VppPartition`): the VLM point partition (runtime.vpp.stage.VppStage): the points of
  objects the backend called movable and cheap to touch leave P_fix; before the first answer
  (or its failure, or the stage's timeout) the planner drives on every point fixed or waits
  (`vpp.before_first_answer`). The partition of the `dct` preset.

Per tick the controller calls `update(now, pose, image, scan)`, which returns the `only` mask of
the obstacle extractor (runtime.perception.obstacle_points: (N,) bool per scan point, True = P_fix) or None
for "every point"; then `ready(now)` says whether the planner may drive yet. `settle(t_s)` is the
simulator's lockstep barrier, `close()` ends work beside the tick, `describe()` adds the stage's
counters to the episode report; `relabel_fixed_in_front(...)` is correcting mode's eq. 14 (the
object a failed push was on becomes fixed).

The controller holds its strategy inside a `FallbackPartition`: `fall_back(reason, now_s)`
switches it to all-fixed for the rest of the run (the safe side: every point an obstacle, the
planner never waits), when the calibration the VPP projects with is found wrong
(runtime.perception.calibration_monitor). The reason and the time stay in `fallback` and in
`describe()` (`partition_fallback: {reason, since_s}`): the diagnostics, the console and the
run's summary say it. The modes and the controller keep the one object; what it delegates to
changes.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Protocol

import numpy as np

from runtime.common.sensor_data import CameraImage, LidarScan


class PartitionStage(Protocol):
    name: str
    #: Whether the scan is deskewed to the tick before it is partitioned (the VPP projects every
    #: point where it is now; without a partition the obstacle extractor deskews as it places).
    deskews_scan: bool
    #: The VPP stage behind it (runtime.vpp.stage.VppStage), None when there is none: its
    #: counters and last frame are read outside the tick (controller.vpp: tests, benches).
    vpp: object | None

    def update(self, now_s: float, pose: tuple[float, float, float], image: CameraImage | None,
               scan: LidarScan | None, image_pose: tuple[float, float, float] | None = None) -> np.ndarray | None:
        """This tick's partition of `scan` (every point where it is at now_s, at `pose`): (N,)
        bool, True = P_fix; None = every point P_fix. image_pose: the robot's pose when `image`
        was captured (None: `pose`)."""

    def movable(self) -> tuple[np.ndarray, np.ndarray] | None:
        """The last partitioned scan's P_mov: ((N,) bool over its points, (N,) contact costs
        0..10); None when nothing is touchable."""

    def carried_region(self) -> tuple[float, float, float, float] | None:
        """Where the object the robot is pushing lies in base_link (x min, x max, y min, y max),
        from the last scan; None when it pushes nothing."""

    def ready(self, now_s: float) -> bool:
        """Whether the planner may drive on what the stage knows by now."""

    def settle(self, t_s: float) -> None:
        """Lockstep barrier (the simulator calls it before time t_s): work due by t_s is done."""

    def close(self) -> None:
        """End the work beside the tick (a backend runner)."""

    def describe(self) -> dict:
        """JSON-ready entries for the controller's report ({} when there is nothing to say)."""

    def movable_points_lidar(self) -> np.ndarray | None:
        """The last partitioned scan's P_mov in the lidar frame (None: none): the odometry leaves
        their neighbourhood out of the next frames' ICP (a pushed box moves with the robot)."""

    def observe_contact(self, now_s: float, pose: tuple[float, float, float], v_mps: float, currents_a) -> None:
        """Push evidence for the belief (mode dct): this tick's forward speed and wheel motor
        currents (None when stale) with the robot's pose; nothing elsewhere."""

    def relabel_fixed_in_front(self, pose: tuple[float, float, float], half_length_m: float, half_width_m: float,
                               margin_m: float, forward: bool) -> int | None:
        """Correcting mode (DCT eq. 14): the movable object in front of the robot (within its
        footprint + margin_m) becomes fixed for the rest of the episode; returns its id, or None
        when no movable object is there."""


class AllFixedPartition:
    """Every point is P_fix; nothing runs beside the tick; the planner never waits."""

    name = "all-fixed"
    deskews_scan = False
    vpp = None  # no VPP stage (controller.vpp reads it)

    def update(self, now_s: float, pose: tuple[float, float, float], image: CameraImage | None,
               scan: LidarScan | None, image_pose: tuple[float, float, float] | None = None) -> np.ndarray | None:
        return None

    def movable(self) -> tuple[np.ndarray, np.ndarray] | None:
        return None

    def carried_region(self) -> tuple[float, float, float, float] | None:
        return None

    def ready(self, now_s: float) -> bool:
        return True

    def settle(self, t_s: float) -> None:
        pass

    def close(self) -> None:
        pass

    def describe(self) -> dict:
        return {}

    def observe_contact(self, now_s, pose, v_mps, currents_a) -> None:
        pass

    def movable_points_lidar(self) -> np.ndarray | None:
        return None

    def relabel_fixed_in_front(self, pose, half_length_m, half_width_m, margin_m, forward) -> int | None:
        return None  # every point is fixed already


class VppPartition:
    """The VLM point partition (runtime.vpp.stage.VppStage, its public API only)."""

    name = "vpp"
    deskews_scan = True

    def __init__(self, stage, footprint: tuple[float, float] = (0.161, 0.11), contact_margin_m: float = 0.08) -> None:
        self.vpp = stage  # runtime.vpp.stage.VppStage: tests and telemetry read its counters
        #: (half length, half width) of the robot (m) and the distance in front of it that is contact
        self._half_length_m, self._half_width_m = footprint
        self._contact_margin_m = contact_margin_m

    def update(self, now_s: float, pose: tuple[float, float, float], image: CameraImage | None,
               scan: LidarScan | None, image_pose: tuple[float, float, float] | None = None) -> np.ndarray | None:
        frame = self.vpp.update(now_s, pose, image, scan, image_pose)
        return frame.fixed if frame is not None else None

    def movable(self) -> tuple[np.ndarray, np.ndarray] | None:
        frame = self.vpp.last_frame
        if frame is None:
            return None
        mov = ~frame.fixed  # P_mov: the points of touchable objects
        if not mov.any():
            return None
        part = frame.partition
        cost = part.cost.astype(np.float64)  # NaN off P_mov; on it the belief's expected cost
        cost[mov] = self.vpp.expected_costs(part.object_id[mov], part.cost[mov])
        return mov, cost

    def ready(self, now_s: float) -> bool:
        """The VLM's first answer (or failure) came back, or the stage stopped waiting for it:
        before that the partition knows nothing the all-fixed one does not, and the controller
        waits rather than commit to a detour."""
        return self.vpp.ready(now_s)

    def settle(self, t_s: float) -> None:
        self.vpp.settle(t_s)

    def close(self) -> None:
        self.vpp.close()

    def describe(self) -> dict:
        return {"vpp": self.vpp.describe()}

    def movable_points_lidar(self) -> np.ndarray | None:
        return self.vpp.movable_points_lidar()

    def carried_region(self) -> tuple[float, float, float, float] | None:
        # touching: within 3 cm of the bumper (the contact margin's 8-12 cm would carry a box
        # still standing a tenth of a second ahead, and put its points that far off)
        return self.vpp.carried_region(self._half_length_m, self._half_width_m, 0.03)

    def observe_contact(self, now_s, pose, v_mps, currents_a) -> None:
        self.vpp.observe_contact(now_s, pose, v_mps, currents_a, self._half_length_m, self._half_width_m,
                                 self._contact_margin_m)

    def relabel_fixed_in_front(self, pose, half_length_m, half_width_m, margin_m, forward) -> int | None:
        oid = self.vpp.movable_in_front(pose, half_length_m, half_width_m, margin_m, forward)
        if oid is not None:
            self.vpp.demote(oid)
        return oid


class FallbackPartition:
    """A partition strategy that can fall back to all-fixed for good (module docstring)."""

    def __init__(self, inner: PartitionStage) -> None:
        self.inner = inner
        self._active: PartitionStage = inner
        #: (reason, since_s) once fallen back; None while the configured strategy runs.
        self.fallback: tuple[str, float] | None = None

    @property
    def name(self) -> str:
        return self._active.name

    @property
    def configured(self) -> str:
        return self.inner.name

    @property
    def deskews_scan(self) -> bool:
        return self._active.deskews_scan

    @property
    def vpp(self):
        """The VPP stage while it partitions; None after the fall-back (nothing reads a stale frame)."""
        return self._active.vpp

    def fall_back(self, reason: str, now_s: float) -> bool:
        """Every point P_fix from now on; False (nothing changes) when the strategy is all-fixed
        already or has fallen back before."""
        if self.fallback is not None or self.inner.name == AllFixedPartition.name:
            return False
        self.fallback = (str(reason), float(now_s))
        self._active = AllFixedPartition()
        return True

    def update(self, now_s, pose, image, scan, image_pose=None):
        return self._active.update(now_s, pose, image, scan, image_pose)

    def movable(self):
        return self._active.movable()

    def carried_region(self):
        return self._active.carried_region()

    def ready(self, now_s: float) -> bool:
        return self._active.ready(now_s)

    def settle(self, t_s: float) -> None:
        self.inner.settle(t_s)  # a request in flight still ends on the simulator's barrier

    def close(self) -> None:
        self.inner.close()

    def describe(self) -> dict:
        out = dict(self.inner.describe())
        if self.fallback is not None:
            reason, since = self.fallback
            out["partition_fallback"] = {"reason": reason, "since_s": since, "configured": self.inner.name}
        return out

    def movable_points_lidar(self):
        return self._active.movable_points_lidar()

    def observe_contact(self, now_s, pose, v_mps, currents_a) -> None:
        self._active.observe_contact(now_s, pose, v_mps, currents_a)

    def relabel_fixed_in_front(self, pose, half_length_m, half_width_m, margin_m, forward):
        return self._active.relabel_fixed_in_front(pose, half_length_m, half_width_m, margin_m, forward)


def build_vpp_partition(config, robot, backend, lockstep: bool, sensors) -> VppPartition:
    """The VPP stage: the robot's camera, the backend in a runner on the controller's clock
    (simulated time in lockstep, the wall clock otherwise).

    config: runtime.config.ControllerConfig; robot: calibration.robot_description.RobotDescription;
    backend: a models.vlm backend (VlmBackend). sensors: the calibrated camera and mounts
    (calibration.sensor_calibration.SensorCalibration): Phase III projects with its camera model
    (intrinsics and distortion; the stage takes only images that carry them) and places the
    camera and the lidar on the base with its two mounts."""
    from models.vlm.runner import BackendRunner
    from runtime.vpp.belief import PushResistanceEstimator
    from runtime.vpp.deformable import RobotBox
    from runtime.vpp.stage import VppStage

    cam, camera = robot.sensors.camera, sensors.camera
    if (camera.width_px, camera.height_px) != (cam.width_px, cam.height_px):
        raise ValueError(f"calibration camera: {camera.width_px}x{camera.height_px} px, the robot's camera "
                         f"({robot.name}) is {cam.width_px}x{cam.height_px} px: a calibration of another camera")
    T_base_lidar, T_base_cam = sensors.T_base_lidar, sensors.T_base_camera
    runner_config = config.vpp.runner.model_copy(update={"clock": "lockstep" if lockstep else "realtime"})
    footprint = (robot.footprint.length_m / 2.0, robot.footprint.width_m / 2.0)
    stage = VppStage(config.vpp, camera, T_base_cam, T_base_lidar, BackendRunner(backend, runner_config),
                     resistance=PushResistanceEstimator(
                         robot, traction_coefficient=config.vpp.belief.traction_coefficient),
                     robot_box=RobotBox(footprint[0], footprint[1]))
    return VppPartition(stage, footprint, config.correcting.contact_margin_m)


@dataclass(frozen=True)
class PartitionContext:
    """What a partition's builder may use."""

    config: object  # runtime.config.ControllerConfig
    robot: object  # calibration.robot_description.RobotDescription
    lockstep: bool
    #: The contact-tolerance backend (models.vlm): the simulator passes its sim-oracle; None: the
    #: one the config names (`vpp.backend`, models.vlm.factory).
    vlm_backend: object = None
    #: The calibrated camera and mounts (calibration.sensor_calibration.SensorCalibration); None:
    #: the robot description's nominal ones.
    sensors: object = None


def _build_vpp(ctx: PartitionContext) -> VppPartition:
    backend = ctx.vlm_backend
    if backend is None:  # (the sim-oracle cannot be built outside the simulator: a clear error)
        from models.vlm.factory import build_backend

        backend = build_backend(ctx.config.vpp.backend)
    sensors = ctx.sensors
    if sensors is None:
        from calibration.sensor_calibration import nominal_sensors

        sensors = nominal_sensors(ctx.robot)
    return build_vpp_partition(ctx.config, ctx.robot, backend, lockstep=ctx.lockstep, sensors=sensors)


@dataclass(frozen=True)
class PartitionSpec:
    build: Callable[[PartitionContext], PartitionStage]
    #: Reads camera images (the simulator renders them; `dct run` subscribes to the image topic).
    uses_camera: bool
    #: Asks a contact-tolerance backend (models.vlm) beside the tick.
    uses_vlm_backend: bool
    summary: str


#: The partitions by name (`partition` in the controller config).
PARTITIONS = {
    "all-fixed": PartitionSpec(lambda ctx: AllFixedPartition(), uses_camera=False, uses_vlm_backend=False,
                               summary="every lidar point is P_fix"),
    "vpp": PartitionSpec(_build_vpp, uses_camera=True, uses_vlm_backend=True,
                         summary="the VLM point partition: touchable objects' points leave P_fix"),
}


def partition_spec(name: str) -> PartitionSpec:
    try:
        return PARTITIONS[name]
    except KeyError:
        raise ValueError(f"unknown partition {name!r}; known: {', '.join(PARTITIONS)}") from None


def build_partition(name: str, context: PartitionContext) -> PartitionStage:
    return partition_spec(name).build(context)


__all__ = ["AllFixedPartition", "FallbackPartition", "PARTITIONS", "PartitionContext", "PartitionSpec", "PartitionStage",
           "VppPartition", "build_partition", "build_vpp_partition", "partition_spec"]
