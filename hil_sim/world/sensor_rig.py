"""The robot's simulated sensors in one lockstep device: lidar, IMU and (on demand) camera.

`SensorRig.step(t_s)` is the `SimulatedDevice` protocol of hil_sim.episode.lockstep.LockstepSimulation.
Time convention: `t_s` is the simulation time *before* the physics step just taken. MuJoCo's
`mj_step` computes positions, sensors and everything derived from them for the state at the
start of the step and then integrates, so after `world.step()` the body poses (`xpos`,
`xmat`, `geom_xpos`) and `sensordata` in `data` belong to time `world.time_s - timestep`.
LockstepSimulation.step() passes that time; a caller that drives the rig itself after
`mj_forward` passes `data.time`.

Per call:
- the lidar casts every slice due up to t_s (hil_sim.sensors.lidar.SimLidar) and every completed frame
  goes to `inbox.put_scan`;
- the IMU samples when a sample is due at `imu.rate_hz` and each goes to `inbox.put_imu`;
- the camera renders only when a frame is due at `camera_rate_hz` (0 = off, no renderer is
  even created): rendering costs tens of ms, never do it every physics step. Each image goes
  to `inbox.put_image`, and beside it the intrinsics it was rendered with go to
  `inbox.put_camera_info`, as a camera driver publishes its CameraInfo (what the controller's
  calibration check holds its calibration against). If steps are so coarse that several frame
  instants passed, one frame is rendered and the others are counted in `camera_frames_missed`.

Robustness: no physics state makes `step` raise (a crash into a wall saturates the IMU, whose
samples are then clipped and flagged; NaN readings give no IMU sample, lidar no-returns and no
camera image; see hil_sim.sensors.imu and hil_sim.sensors.lidar); only a bad call does (time not finite or going backwards).

The robot's own geoms (groups World.ROBOT_OWN_GEOM_GROUPS) are invisible to the lidar rays
and hidden from the camera: both mounts lie inside the coarse chassis boxes.

A world built as a robot variant (hil_sim.world.robot_variant) has its lidar and camera at the
variant's mounts, and the camera renders through the variant's lens (`World.camera_lens`): its
images carry the true K and distortion, as a camera driver reports its factory calibration.
"""
from __future__ import annotations

import dataclasses

import math
import threading
import time
from collections.abc import Callable

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, model_validator

from calibration.robot_description import RobotDescription
from hil_sim.sensors.imu import ImuConfig, SimImu
from hil_sim.sensors.lidar import LidarConfig, SimLidar
from hil_sim.world.model_spec import ROBOT_OWN_GEOM_GROUPS
from hil_sim.world.mujoco_world import World
from runtime.common.sensor_data import CameraImage, CameraInfo, LidarScan
from runtime.io.sensor_inbox import SensorInbox

_EPS_S = 1e-9


class SensorRigError(ValueError):
    """A bad sensor-rig configuration or call (robot groups visible to the lidar, time going back)."""


class SensorRigConfig(BaseModel):
    """Which sensors run in the simulator, and how."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    lidar_enabled: bool = True
    #: geomgroup None: the world's lidar_geomgroup (everything but the robot) is used.
    lidar: LidarConfig = Field(default_factory=LidarConfig)
    imu_enabled: bool = True
    imu: ImuConfig = Field(default_factory=ImuConfig)
    #: Camera frames per second of simulated time; 0 = camera off (the VLM asks for ~1-2 Hz).
    camera_rate_hz: float = Field(0.0, ge=0.0, le=100.0)
    #: Also render ground-truth segmentation (geom ids) into each image (doubles the cost).
    camera_segmentation: bool = False
    #: Multisampled RGB (SimCamera's antialias). Off halves the render; the segmentation is the
    #: same either way (lockstep's camera for the sim-oracle, which answers from the segmentation).
    camera_antialias: bool = True
    #: Render beside the physics, in a thread of its own: a frame costs tens of ms (55 with
    #: segmentation), which inline stalls physics, the lidar and the IMU every frame. The state
    #: of the frame instant is copied (mj_copyData, a few microseconds) and rendered from the
    #: copy, stamped with that instant. Without camera_latency_s (the real-time simulator, `dct
    #: hil serve`) the image is delivered when it is done, as a camera driver's image arrives
    #: after its exposure, and a frame due while the last one still renders is skipped
    #: (camera_frames_missed). Lockstep sets camera_latency_s: there an image must reach the
    #: controller at a deterministic point of the run.
    camera_async: bool = False
    #: The image reaches the inbox this long after its instant, in simulated time (exposure,
    #: read-out and transfer: 30-100 ms for a USB camera), stamped with its instant. With
    #: camera_async the frame renders beside the physics meanwhile and is handed over exactly at
    #: that instant, waiting for the render when it is not done, so a lockstep run stays
    #: deterministic and the render costs no simulator time (SensorRig.defer_hand_over lets
    #: the physics go on meanwhile). 0: delivered when rendered.
    camera_latency_s: float = Field(0.0, ge=0.0, le=0.5)
    #: Cast the lidar's rays in a child process (SimLidar's cast_in_process): the same frames
    #: bit for bit, handed over at the same step; the physics steps on while the child casts
    #: (a 20k-ray frame costs the simulator's thread 6 ms inline, 0.5 ms this way).
    lidar_process: bool = False
    seed: int = Field(0, ge=0)

    @model_validator(mode="after")
    def _latency_within_a_frame(self) -> "SensorRigConfig":
        # one frame in transfer at a time: a latency of a period or more would skip every other frame
        if self.camera_rate_hz > 0 and self.camera_latency_s >= 1.0 / self.camera_rate_hz:
            raise ValueError(f"camera_latency_s ({self.camera_latency_s} s) must be shorter than the camera "
                             f"period (1 / camera_rate_hz = {1.0 / self.camera_rate_hz:g} s)")
        return self


def _camera_pose_is_finite(data, camera_name: str) -> bool:
    """False when the camera pose in data is NaN or infinite (a diverged simulation): a render
    would be a blank image that looks like a real one."""
    cam = data.camera(camera_name)
    return bool(np.isfinite(cam.xpos).all() and np.isfinite(cam.xmat).all())


class CameraThread:
    """SensorRigConfig.camera_async: a SimCamera in a thread of its own, rendering copies of the
    state. The renderer (and its EGL context) is made and used in that thread only.

    deliver: called in the render thread with each image when it is done; None: the image is
    kept for `result()`, which the simulator's thread calls when it hands the image over (at
    the instant it is due, or with defer_hand_over before the next tick)."""

    def __init__(self, model, camera_args: tuple, segmentation: bool,
                 deliver: Callable[[CameraImage], None] | None) -> None:
        import mujoco

        self._mujoco = mujoco
        self._model = model
        self._snap = mujoco.MjData(model)
        self._args = camera_args
        self._segmentation = bool(segmentation)
        self._deliver = deliver
        self._job = threading.Event()
        self._idle = threading.Event()
        self._warm = threading.Event()  # the renderer's warm-up render is done (or failed)
        self._stop = False
        self._stamp = 0.0
        self._started = threading.Event()
        self._camera = None
        self._image: CameraImage | None = None
        #: The exception that ended the thread (re-raised by the next submit), if any.
        self.error: BaseException | None = None
        self._thread = threading.Thread(target=self._run, name="sim-camera", daemon=True)
        self._thread.start()
        self._started.wait()
        if self.error is not None:
            raise self.error

    @property
    def renders(self) -> int:
        return 0 if self._camera is None else self._camera.renders

    def submit(self, data, t_s: float) -> bool:
        """Render the state now in data, stamped t_s, beside the caller; False (nothing done)
        while the last frame still renders."""
        self._warm.wait()  # the first frame only: the warm-up started with the thread
        if self.error is not None:
            raise self.error
        if not self._idle.is_set():
            return False
        self._mujoco.mj_copyData(self._snap, self._model, data)
        self._stamp = float(t_s)
        self._idle.clear()
        self._job.set()
        return True

    def _run(self) -> None:
        from hil_sim.sensors.camera import SimCamera

        try:
            self._camera = SimCamera(self._model, self._snap, *self._args)
        except BaseException as exc:  # reported by __init__
            self.error = exc
            self._started.set()
            return
        self._started.set()
        try:
            self._mujoco.mj_forward(self._model, self._snap)  # the model's initial state, to warm up on
            self._camera.warm_up(self._segmentation)
            self._idle.set()  # before _warm: a submit that waited for the warm-up finds the thread idle
            self._warm.set()
            while True:
                self._job.wait()
                self._job.clear()
                if self._stop:
                    return
                cam = self._camera
                image = cam.render_rgb_with_segmentation(self._stamp) if self._segmentation else cam.render_rgb(
                    self._stamp)
                if self._deliver is None:
                    self._image = image
                else:
                    self._deliver(image)
                self._idle.set()
        except BaseException as exc:  # the simulator's loop raises it at the next frame
            self.error = exc
        finally:
            self._warm.set()
            self._idle.set()  # a result() waiting for the frame that failed returns (and raises)
            self._camera.close()

    def result(self) -> CameraImage:
        """The image of the last submit (deliver None), waiting for its render."""
        self._idle.wait()
        if self.error is not None:
            raise self.error
        image, self._image = self._image, None
        if image is None:
            raise RuntimeError("CameraThread.result: no frame was submitted")
        return image

    def close(self) -> None:
        self._stop = True
        self._job.set()
        self._thread.join(timeout=5.0)


def _make_lidar(world: World, c: SensorRigConfig, seed: int, start_s: float) -> SimLidar:
    """The lidar on the world's mount, blind to the robot's own geom groups (SensorRigError when
    the config's geomgroup lets it see them)."""
    lidar_cfg = c.lidar
    if lidar_cfg.geomgroup is None:
        lidar_cfg = lidar_cfg.model_copy(update={"geomgroup": world.lidar_geomgroup})
    else:
        seen = [g for g in ROBOT_OWN_GEOM_GROUPS if lidar_cfg.geomgroup[g]]
        if seen:
            raise SensorRigError(f"SensorRigConfig.lidar.geomgroup {lidar_cfg.geomgroup} lets the lidar see "
                                 f"the robot's own geom groups {seen}; set them to 0 (or leave geomgroup None)")
    return SimLidar(world.model, world.data, world.robot_body_id, world.lidar_mount, lidar_cfg, seed=seed,
                    start_s=start_s, cast_in_process=c.lidar_process)


class SensorRig:
    """Lidar + IMU + camera of the robot in a World, feeding a SensorInbox (see module docstring)."""

    def __init__(self, world: World, robot: RobotDescription, inbox: SensorInbox,
                 config: SensorRigConfig | None = None, intrinsics: tuple[np.ndarray, np.ndarray] | None = None) -> None:
        """intrinsics: (K, distortion) the images reach the inbox with: the controller's
        calibration, as on the robot, where the camera driver's image carries none and the
        controller attaches its calibration's (runtime.io.ros.convert). None: the simulated
        camera's true ones. Listeners get the true ones (ground truth for evaluations)."""
        self._intrinsics = intrinsics
        self.world = world
        self.robot = robot
        self.inbox = inbox
        self.config = c = config or SensorRigConfig()
        m, d = world.model, world.data
        start_s = world.time_s
        seeds = np.random.SeedSequence(c.seed).generate_state(2)

        self.lidar: SimLidar | None = _make_lidar(world, c, int(seeds[0]), start_s) if c.lidar_enabled else None
        self.imu: SimImu | None = None
        self.camera = None
        self._camera_period_s = 1.0 / c.camera_rate_hz if c.camera_rate_hz > 0 else math.inf
        self._camera_start_s = start_s
        self._camera_next = 0
        #: (due time, image or None when the render thread holds it) of the frame not yet handed over.
        self._camera_held: tuple[float, CameraImage | None] | None = None
        #: Set by a simulator whose inbox is read only at known points (lockstep: the controller's
        #: tick): a held frame whose time has come is handed over by `hand_over_due()`, which the
        #: simulator calls before that reader reads, instead of in the physics step, which would
        #: wait for the render there. The reader finds the same image either way; the physics
        #: meanwhile goes on beside the render. A capture due first hands it over too.
        self.defer_hand_over = False
        self._camera_overdue = False
        try:  # a device that cannot be built must not leave the lidar's cast process running
            if c.imu_enabled:
                gyro, accel = world.imu_sensor_names
                self.imu = SimImu(m, d, gyro, accel, c.imu, seed=int(seeds[1]), start_s=start_s)
            if c.camera_rate_hz > 0:
                self.camera = self._make_camera()
        except BaseException:
            if self.lidar is not None:
                self.lidar.close()
            raise

        self._last_t: float | None = None
        #: Called with every scan and image the rig produces, before the inbox gets it, in the
        #: simulator's time (evaluations read the ground truth beside them: `dct vpp eval`, whose
        #: camera renders inline; with defer_hand_over an image comes at its hand-over, up to a
        #: tick after its time, so the world may have moved on since its instant).
        self.listeners: list[Callable[[LidarScan | CameraImage], None]] = []
        self.scans_produced = 0
        self.images_produced = 0
        self.imu_samples_produced = 0
        self.camera_frames_missed = 0
        #: Camera frames not rendered because the camera pose in data was not finite.
        self.camera_invalid_poses = 0
        #: put_* calls the inbox refused (validation or stamp order), per stream.
        self.rejected = {"lidar": 0, "camera": 0, "imu": 0}
        #: Wall-clock seconds spent in each sensor (including the inbox's validation).
        self.time_spent_s = {"lidar": 0.0, "camera": 0.0, "imu": 0.0}

    def _make_camera(self):
        """The camera: rendered in a thread of its own (camera_async) or inline (SimCamera)."""
        from hil_sim.sensors.camera import SimCamera  # creates an EGL context: only when the camera is on

        world, c = self.world, self.config
        cam = self.robot.sensors.camera
        args = (world.camera_name, cam.width_px, cam.height_px, "camera", world.camera_hidden_geom_groups,
                world.camera_lens, c.camera_antialias)
        if c.camera_async:
            deliver = None if c.camera_latency_s > 0 else self._deliver_image
            return CameraThread(world.model, args, c.camera_segmentation, deliver)
        return SimCamera(world.model, world.data, *args)

    # ------------------------------------------------------------------ stepping
    def step(self, t_s: float) -> None:
        """Advance every sensor to t_s (the time of the state now in data; see module docstring)."""
        t_s = float(t_s)
        if not math.isfinite(t_s):
            raise SensorRigError(f"SensorRig.step: time {t_s} is not finite")
        if self._last_t is not None and t_s < self._last_t:
            raise SensorRigError(f"SensorRig.step: time went backwards ({t_s} < {self._last_t}); "
                                 f"make a new rig after World.reset()")
        self._last_t = t_s
        inbox = self.inbox
        spent = self.time_spent_s
        clock = time.perf_counter

        # A sensor with nothing due is not called (most physics steps: a lidar slice is due
        # every 2 ms, an IMU sample every 5 ms); its own step would return at once.
        lidar, imu, due_t = self.lidar, self.imu, t_s + _EPS_S
        if lidar is not None and due_t >= lidar.next_due_s:
            t0 = clock()
            lidar.step(t_s)
            scan = lidar.pop_frame()
            while scan is not None:
                self.scans_produced += 1
                for listener in self.listeners:
                    listener(scan)
                if not inbox.put_scan(scan):
                    self.rejected["lidar"] += 1
                scan = lidar.pop_frame()
            spent["lidar"] += clock() - t0

        if imu is not None and due_t >= imu.next_due_s:
            t0 = clock()
            imu.step(t_s)
            for sample in imu.pop_samples():
                self.imu_samples_produced += 1
                if not inbox.put_imu(sample):
                    self.rejected["imu"] += 1
            spent["imu"] += clock() - t0

        if self.camera is not None:
            self._step_camera(t_s)

    def _step_camera(self, t_s: float) -> None:
        """Hand over the held frame when its time came, then render the frame due, if any."""
        spent, clock = self.time_spent_s, time.perf_counter
        held = self._camera_held
        if held is not None and t_s + _EPS_S >= held[0]:
            if self.defer_hand_over:
                self._camera_overdue = True
            else:
                self._hand_over()
        due = self._camera_start_s + self._camera_next * self._camera_period_s
        if t_s + _EPS_S < due:
            return
        if self._camera_overdue:  # one frame in transfer at a time: the late one first
            self._hand_over()
        t0 = clock()
        n_due = int(math.floor((t_s + _EPS_S - self._camera_start_s) / self._camera_period_s)) + 1
        self.camera_frames_missed += max(0, n_due - self._camera_next - 1)
        self._camera_next = max(self._camera_next + 1, n_due)
        latency = self.config.camera_latency_s
        if not _camera_pose_is_finite(self.world.data, self.world.camera_name):
            self.camera_invalid_poses += 1  # no image rather than a blank one
        elif self._camera_held is not None:
            self.camera_frames_missed += 1  # the last frame is still in transfer
        elif isinstance(self.camera, CameraThread):
            if not self.camera.submit(self.world.data, t_s):
                self.camera_frames_missed += 1  # the last frame still renders
            elif latency > 0:
                self._camera_held = (t_s + latency, None)
        else:
            image = (self.camera.render_rgb_with_segmentation(t_s) if self.config.camera_segmentation
                     else self.camera.render_rgb(t_s))
            if latency > 0:
                self._camera_held = (t_s + latency, image)
            else:
                self._deliver_image(image)
        spent["camera"] += clock() - t0

    def _hand_over(self) -> None:
        """The held frame to the inbox (waiting for its render when the thread still has it)."""
        t0 = time.perf_counter()
        held, self._camera_held, self._camera_overdue = self._camera_held, None, False
        self._deliver_image(held[1] if held[1] is not None else self.camera.result())
        self.time_spent_s["camera"] += time.perf_counter() - t0

    def hand_over_due(self) -> None:
        """With defer_hand_over: hand over the frame whose time the physics has passed, if any,
        waiting for its render (lockstep calls it before each tick, the inbox's only reader)."""
        if self._camera_overdue:
            self._hand_over()

    def _deliver_image(self, image: CameraImage) -> None:
        self.images_produced += 1
        for listener in self.listeners:
            listener(image)
        put_info = getattr(self.inbox, "put_camera_info", None)
        if put_info is not None:  # the true intrinsics, as the camera's driver reports them
            dist = image.distortion
            put_info(CameraInfo(image.stamp_s, image.width, image.height, image.K, dist if len(dist) else np.zeros(5),
                                "plumb_bob" if len(dist) <= 5 else "rational_polynomial", image.frame_id))
        if self._intrinsics is not None:
            image = dataclasses.replace(image, K=self._intrinsics[0], distortion=self._intrinsics[1])
        if not self.inbox.put_image(image):
            self.rejected["camera"] += 1

    # ------------------------------------------------------------------ reporting
    @property
    def renders(self) -> int:
        """Renderer passes so far (RGB and segmentation each count one)."""
        return 0 if self.camera is None else self.camera.renders

    def stats(self) -> dict:
        """Counters: frames produced per sensor, late/missed/dropped, saturated IMU samples, physics
        readings that were not finite (no IMU sample; lidar slices with no returns), inbox
        rejections, renders."""
        return {
            "scans_produced": self.scans_produced,
            "images_produced": self.images_produced,
            "imu_samples_produced": self.imu_samples_produced,
            "renders": self.renders,
            "camera_frames_missed": self.camera_frames_missed,
            "lidar_late_slices": 0 if self.lidar is None else self.lidar.late_slices,
            "lidar_dropped_frames": 0 if self.lidar is None else self.lidar.dropped_frames,
            "imu_missed_samples": 0 if self.imu is None else self.imu.missed_samples,
            "imu_saturated_samples": 0 if self.imu is None else self.imu.saturated_samples,
            "imu_invalid_readings": 0 if self.imu is None else self.imu.invalid_readings,
            "lidar_invalid_pose_slices": 0 if self.lidar is None else self.lidar.invalid_pose_slices,
            "camera_invalid_poses": self.camera_invalid_poses,
            "rejected": dict(self.rejected),
            "time_spent_s": dict(self.time_spent_s),
        }

    def wait_ready(self) -> None:
        """Until every sensor can produce (the lidar's cast process has started)."""
        if self.lidar is not None:
            self.lidar.wait_ready()

    def close(self) -> None:
        """Release the renderer and the lidar's caster."""
        if self.lidar is not None:
            self.lidar.close()
        if self.camera is not None:
            self.camera.close()
            self.camera = None
            self._camera_period_s = math.inf


__all__ = ["SensorRig", "SensorRigConfig", "SensorRigError"]
