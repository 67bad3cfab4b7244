"""`dct hil serve`: the simulator in real time, as its own process, looking like the robot.

To a controller process (`dct run`) it is indistinguishable from the LIMO: the emulated base
firmware (firmware_bridge.firmware_emulator) answers on a CAN bus (udp_multicast: python-can's
bus between processes), and the sensors are ROS 2 topics over DDS with the types the real
drivers publish: livox_ros_driver2/CustomMsg (per-point offset_time, ros_io's numpy encoder), or,
when the controller's config reads a sensor_msgs/PointCloud2 lidar, the PointCloud2 the same
driver publishes with xfer_format 0 (per-point absolute `timestamp` in ns), sensor_msgs/Imu,
sensor_msgs/Image (only when a camera rate is asked for: rendering is costly) with its
sensor_msgs/CameraInfo (the rendering camera's true intrinsics, as a driver reports them).
For planner mode dct it also serves the sim-oracle as a remote VLM (the OpenAI chat-completions
API and the grounding detector API over HTTP on 127.0.0.1: hil_sim.vlm.service), answering
from the ground truth of the frames it rendered.

Physics is paced to the wall clock: every loop iteration steps the world until simulated time
catches up with the time elapsed since start, then sleeps. When the machine cannot keep up, the
simulation runs late rather than skipping physics (the lag is measured: `sim_lag_ms`), and the
sensor stamps follow simulated time mapped onto the wall clock, so a late simulator looks to the
controller like late sensor data, which is what it is.

Stamps: ROS time, i.e. the system clock, through runtime.app.run_process.EpochMonotonicClock (the
same clock the controller runs on), and as a driver's they follow a step of the system clock: the
clock-step faults step this machine's clock (`_SystemClockSteps`, root only) and undo it at the end.

The episode: starts when the controller puts the base into CAN command mode (0x421), so the
controller's start-up time is not counted; ends `settle_s` after the controller says it has
finished (at the goal with a zero command, or stopped), as lockstep's episode does: the
simulator reads what an operator would, the controller's DiagnosticArray (its `finished` value)
on the configured diagnostics topic. It also ends when the scenario's time limit has passed
since the start, when no controller has connected within `connect_timeout_s`, or on
SIGINT/SIGTERM. (A robot that merely stands still in the goal region is not finished: it may be
holding for stale data, as it does when this simulator falls behind.) The metrics
(hil_sim.episode.metrics) are then written atomically, as lockstep writes them, with `end_reason`.
What the controller knows (its state, deadline misses) is not here: `dct hil run --realtime`
adds it from the controller's own summary.

A patrol scenario (`goals:`, hil_sim.episode.patrol): the controller starts with the first goal (its
`--goal`); whenever its DiagnosticArray says it has finished with the goal sent last (`finished`
with that goal's `goal_x`, `goal_y`), the next goal is published as a geometry_msgs/PoseStamped
on the goal topic (/goal_pose, odometry frame), as an operator would send it from RViz. The
episode ends with the patrol (its loops, or `duration_s`: `--duration` overrides the file's
patrol), and the metrics add `patrol`.
"""
from __future__ import annotations

import math
import os
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from hil_sim.episode.faults import CLOCK_STEPS
from runtime.io.sensor_inbox import CLOCK_STEP_MIN_S
from runtime.loop.heap import HeapTrimmer

#: Simulated seconds between two returns of the C heap's free pages to the system (runtime.loop.heap).
TRIM_EVERY_S = 10.0


@dataclass
class ServeOptions:
    scenario: str
    seed: int = 0
    json_path: Path | None = None
    robot_path: Path | None = None
    config_path: Path | None = None
    domain_id: int | None = None
    can_channel: str | None = None
    can_port: int | None = None
    camera_rate_hz: float = 0.0
    connect_timeout_s: float = 120.0
    settle_s: float = 0.5
    #: The sim-oracle's settings (models.vlm.sim_oracle.SimOracleConfig): when given, the oracle
    #: is served over HTTP for planner mode dct (hil_sim.vlm.service) and the camera renders
    #: with segmentation (at camera_rate_hz, or lockstep's 2 Hz when that is 0).
    oracle: object = None
    #: A patrol's duration (s), instead of the scenario's `patrol` (hil_sim.episode.patrol.with_duration).
    duration_s: float | None = None
    #: ros.middleware of the simulator's side (auto | rclpy | cyclonedds; None: the config's).
    middleware: str | None = None
    #: Who may hear the simulated robot: localhost (the default for the simulator) or subnet.
    discovery: str = "localhost"
    #: The robot as built (a SPEC of hil_sim.world.robot_variant); None: the scenario's, else nominal.
    robot_variant: str | None = None
    #: Faults injected (hil_sim.episode.faults.FaultSpec), their times from the episode's start (the
    #: controller enabling the base), as `dct hil run --fault` injects them in lockstep.
    faults: tuple = ()


class DdsSensorSink:
    """Stands where the lockstep rig's SensorInbox stands (put_scan / put_imu / put_image) and
    publishes each piece as the robot's drivers would (module docstring)."""

    def __init__(self, transport, inputs, to_wall, frames: tuple[str, str] = ("livox_frame", "camera"),
                 rays_per_frame: int = 20_000) -> None:
        """frames: the lidar's and the camera's frame ids, as the robot's drivers stamp them (the
        controller config's ros.outputs lidar_frame and camera_frame, the children of base_link in
        its /tf_static). rays_per_frame: the simulated lidar's, for a frame with no return."""
        self.to_wall = to_wall
        self.rays_per_frame = int(rays_per_frame)
        self.lidar_frame, self.camera_frame = frames
        self.inputs = inputs
        #: CustomMsg, or PointCloud2 in livox_ros_driver2's xfer_format 0 layout (put_scan)
        self._lidar_type = inputs.lidar.type if inputs.lidar is not None else None
        self.open_writers(transport)
        self.published = {"lidar": 0, "imu": 0, "camera": 0}
        #: Frames with no return at all, published as the driver does (put_scan).
        self.no_return_frames = 0
        self.publish_s = {"lidar": 0.0, "imu": 0.0, "camera": 0.0}
        #: While the drivers' DDS participant is gone (the dds-lost fault): what was not published.
        self.lost = False
        self.unpublished = 0

    def open_writers(self, transport) -> None:
        """The drivers' publishers on `transport` (again, after the dds-lost fault: new endpoints)."""
        from runtime.io.ros.messages import ROS_TYPES, Image, Imu
        from runtime.io.ros.transport import QosSpec

        inputs = self.inputs
        self._lidar = self._imu = self._camera = None
        if inputs.lidar is not None:
            self._lidar = transport.writer(inputs.lidar.topic, ROS_TYPES[inputs.lidar.type], inputs.lidar.qos.spec())
        if inputs.imu is not None:
            self._imu = transport.writer(inputs.imu.topic, Imu, inputs.imu.qos.spec())
        if inputs.camera is not None and inputs.camera.type == "sensor_msgs/msg/Image":
            self._camera = transport.writer(inputs.camera.topic, Image, QosSpec(inputs.camera.qos.reliability, 1))
        self._camera_info = None  # the rendering camera's true intrinsics, as a driver's CameraInfo
        if self._camera is not None and getattr(inputs, "camera_info", None) is not None:
            self._camera_info = transport.writer(inputs.camera_info.topic, ROS_TYPES[inputs.camera_info.type],
                                                 inputs.camera_info.qos.spec())

    def _unheard(self) -> bool:
        """The drivers' participant is gone: nothing reaches anyone (counted)."""
        if self.lost:
            self.unpublished += 1
        return self.lost

    def put_scan(self, scan) -> bool:
        from runtime.io.ros.messages import CUSTOM_POINT_DTYPE, Header, encode_custom_msg, stamp_to_time

        if self._lidar is None or self._unheard():
            return True
        if scan.num_points == 0:
            # A Livox reports every ray it fires, a ray with no return as a point at (0, 0, 0),
            # and livox_ros_driver2 publishes them as they come: a frame that saw nothing is a
            # frame of such points, never a missing one.
            self.no_return_frames += 1
            scan = no_return_frame(scan, self.rays_per_frame)
        t0 = time.perf_counter()
        stamp = self.to_wall(scan.stamp_s)
        timebase = int(round(stamp * 1e9))
        if self._lidar_type == "sensor_msgs/msg/PointCloud2":
            cdr = lidar_pointcloud2_cdr(scan, timebase, self.lidar_frame)
        else:
            pts = np.zeros(scan.num_points, dtype=CUSTOM_POINT_DTYPE)
            pts["offset_time"] = np.round(scan.point_time_offsets_s.astype(np.float64) * 1e9).astype(np.uint32)
            pts["x"], pts["y"], pts["z"] = scan.points_m[:, 0], scan.points_m[:, 1], scan.points_m[:, 2]
            pts["reflectivity"] = 100
            header = Header(stamp_to_time(timebase * 1e-9), self.lidar_frame)
            cdr = encode_custom_msg(header, timebase, pts)
        self._lidar.write_cdr(cdr)
        self.published["lidar"] += 1
        self.publish_s["lidar"] += time.perf_counter() - t0
        return True

    def put_imu(self, sample) -> bool:
        from runtime.io.ros.fast_imu import encode_imu

        if self._imu is None or self._unheard():
            return True
        t0 = time.perf_counter()
        # No orientation (covariance[0] = -1, the ROS convention); the bytes of to_cdr(Imu(...)).
        self._imu.write_cdr(encode_imu(self.to_wall(sample.stamp_s), "imu", sample.gyro_radps, sample.accel_mps2))
        self.published["imu"] += 1
        self.publish_s["imu"] += time.perf_counter() - t0
        return True

    def put_image(self, image) -> bool:
        from runtime.io.ros.messages import Header, Image, stamp_to_time

        if self._camera is None or self._unheard():
            return True
        t0 = time.perf_counter()
        h, w = image.pixels.shape[:2]
        self._camera.write(Image(header=Header(stamp_to_time(self.to_wall(image.stamp_s)), self.camera_frame),
                                 height=h, width=w, encoding="rgb8", is_bigendian=0, step=3 * w,
                                 data=np.ascontiguousarray(image.pixels).tobytes()))
        self.published["camera"] += 1
        self.publish_s["camera"] += time.perf_counter() - t0
        return True


    def put_camera_info(self, info) -> bool:
        """The simulated camera's CameraInfo (runtime.common.sensor_data.CameraInfo) on its topic."""
        from runtime.io.ros.messages import CameraInfo, Header, stamp_to_time

        if self._camera_info is None or self._unheard():
            return True
        K = [float(v) for v in np.ravel(info.K)]
        P = [K[0], K[1], K[2], 0.0, K[3], K[4], K[5], 0.0, K[6], K[7], K[8], 0.0]
        self._camera_info.write(CameraInfo(
            header=Header(stamp_to_time(self.to_wall(info.stamp_s)), self.camera_frame), height=info.height_px,
            width=info.width_px, distortion_model=info.distortion_model, d=[float(v) for v in info.distortion], k=K,
            r=[1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0], p=P))
        return True


def no_return_frame(scan, rays: int):
    """`scan` (no points: nothing seen) as a Livox frame of `rays` rays with no return: every
    point at (0, 0, 0), spread evenly over the frame's duration."""
    from runtime.common.sensor_data import LidarScan

    pts = np.zeros((rays, 3), dtype=np.float32)
    offsets = (np.arange(rays, dtype=np.float64) * (scan.frame_duration_s / rays)).astype(np.float32)
    return LidarScan(scan.stamp_s, pts, offsets, scan.frame_duration_s, scan.frame_id)


def lidar_pointcloud2_cdr(scan, timebase_ns: int, frame_id: str = "livox_frame") -> bytes:
    """A LidarScan as the CDR of the PointCloud2 livox_ros_driver2 publishes (xfer_format 0): the
    header stamp is timebase_ns, each point's `timestamp` its absolute time in ns."""
    from runtime.io.ros.convert import livox_pointcloud2_msg
    from runtime.io.ros.messages import to_cdr

    return to_cdr(livox_pointcloud2_msg(timebase_ns, frame_id, scan.points_m,
                                        scan.point_time_offsets_s))


def _controller_finished(reader) -> bool:
    """Whether the newest DiagnosticArray from the controller says `finished` = True."""
    from runtime.io.ros.messages import DiagnosticArray, from_cdr

    samples = reader.take_raw()
    for data in reversed(samples):
        try:
            msg = from_cdr(DiagnosticArray, data)
        except Exception:  # noqa: BLE001 - not ours to judge; the next one will do
            continue
        for status in msg.status:
            for kv in status.values:
                if kv.key == "finished":
                    return kv.value == "True"
    return False


def _controller_status(reader, last: dict) -> dict:
    """The newest DiagnosticArray's values from the controller (key -> string), or `last` when no
    new one has arrived."""
    from runtime.io.ros.messages import DiagnosticArray, from_cdr

    for data in reversed(reader.take_raw()):
        try:
            msg = from_cdr(DiagnosticArray, data)
        except Exception:  # noqa: BLE001 - not ours to judge; the next one will do
            continue
        for status in msg.status:
            return {kv.key: kv.value for kv in status.values}
    return last


class _PatrolOperator:
    """A patrol's operator in real time: hil_sim.episode.patrol.PatrolSequencer fed from the controller's
    diagnostics, its goals published on the goal topic (module docstring)."""

    def __init__(self, scenario, transport, inputs, odom_frame: str, reader, t0_s: float, to_wall, echo,
                 seed: int = 0) -> None:
        from hil_sim.episode.patrol import PatrolSequencer
        from runtime.io.ros.messages import PoseStamped

        self.echo = echo
        self.sequencer = PatrolSequencer(scenario, t0_s, seed)
        self.reader = reader
        self.writer = transport.writer(inputs.goal.topic, PoseStamped, inputs.goal.qos.spec())
        self.frame = odom_frame
        self.to_wall = to_wall
        self.status: dict = {}
        self.goals_published = 0

    def step(self, t_s: float, robot_world_pose) -> None:
        from runtime.common.geometry import Pose2D
        from runtime.io.ros.convert import goal_pose_msg

        self.status = _controller_status(self.reader, self.status)
        st = self.status
        try:
            goal_xy = (float(st["goal_x"]), float(st["goal_y"]))
        except (KeyError, ValueError):
            goal_xy = None
        try:
            pose = Pose2D(float(st["pose_x"]), float(st["pose_y"]), float(st["pose_yaw"]))
        except (KeyError, ValueError):
            pose = None
        seq = self.sequencer
        goal = seq.update(t_s, robot_world_pose, goal_xy, st.get("finished") == "True", st.get("state") == "STOPPED",
                          pose)
        if goal is None and seq.resend_due(t_s, goal_xy):
            goal = seq.current_goal_odom()
        if goal is not None:
            self.writer.write(goal_pose_msg(self.to_wall(t_s), goal, frame_id=self.frame))
            self.goals_published += 1
            v = seq.current
            if len(seq.visits) > 1 and v.sent_at_s == t_s - seq.t0_s:  # a new goal, not a repeat
                last = seq.visits[-2]
                self.echo(f"dct hil serve: t={t_s - seq.t0_s:.1f} s: goal {last.visit} {last.outcome} "
                          f"({last.world_error_m:.2f} m off); goal {v.visit} (goals[{v.goal_index}], loop {v.loop}) "
                          "published on the goal topic")


def serve(opts: ServeOptions, stop: threading.Event | None = None, echo=print) -> dict:
    """Run one real-time episode of opts.scenario until it ends (module docstring); returns the
    metrics (also written to opts.json_path)."""
    stop = stop or threading.Event()
    server = _Server(opts, echo)
    wall, sensor_stats = server.run(stop)
    out = server.report(wall, sensor_stats)
    if opts.json_path is not None:
        from calibration.outputs import atomic_write_json

        atomic_write_json(opts.json_path, out)
    return out


def _load(opts: ServeOptions):
    """(scenario, robot, controller config, its ros.inputs with --domain-id, the robot variant or
    None) of `dct hil serve`."""
    from calibration.robot_description import load_robot_description
    from hil_sim.episode.patrol import with_duration
    from hil_sim.world.robot_variant import resolve_variant
    from hil_sim.world.scenario import load_scenario
    from runtime.config import load_controller_config

    scenario = load_scenario(opts.scenario, seed=opts.seed)  # a generated scene is drawn from the seed
    scenario = with_duration(scenario, opts.duration_s)
    robot = load_robot_description(opts.robot_path)
    config = load_controller_config(opts.config_path)
    inputs = config.ros.inputs
    if opts.domain_id is not None:
        inputs = inputs.model_copy(update={"domain_id": opts.domain_id})
    spec = opts.robot_variant if opts.robot_variant is not None else scenario.robot_variant
    variant = resolve_variant(spec, robot) if spec is not None else None
    return scenario, robot, config, inputs, variant


def _open_transport(ros, domain_id: int, opts: ServeOptions):
    """The simulator's ROS 2 node: the config's middleware unless --middleware says otherwise."""
    from runtime.io.ros.transport import TransportOptions, open_transport

    return open_transport(TransportOptions(middleware=opts.middleware or ros.middleware, domain_id=domain_id,
                                           discovery=opts.discovery, node_name="dct_hil_sim"))


@dataclass
class _EpisodeState:
    """What the paced loop learns about the episode (module docstring)."""

    t_start: float | None = None  # when the controller took the base (0x421)
    finished_at: float | None = None  # when the controller said it had finished
    t_goal: float | None = None
    end_reason: str = "signal"
    patrol: _PatrolOperator | None = None


class _Server:
    """One `dct hil serve` episode: the world, the CAN bus and DDS, the sensors, the oracle, and the
    loop that paces physics to the wall clock (module docstring)."""

    def __init__(self, opts: ServeOptions, echo) -> None:
        from firmware_bridge import protocol
        from firmware_bridge.buses import DEFAULT_UDP_GROUP, DEFAULT_UDP_PORT, BusConfig, open_bus
        from firmware_bridge.firmware_emulator import EmulatedBaseFirmware
        from hil_sim.episode.faults import FaultInjector, FaultyBus
        from hil_sim.episode.lockstep import LockstepSimulation
        from hil_sim.episode.metrics import EpisodeMetrics
        from hil_sim.world.mujoco_world import World
        from hil_sim.world.sensor_rig import SensorRig, SensorRigConfig
        from runtime.app.run_process import EpochMonotonicClock

        self.opts, self.echo = opts, echo
        scenario, robot, config, inputs, variant = _load(opts)
        self.scenario, self.config, self.inputs = scenario, config, inputs
        self.bus_config = BusConfig(interface="udp_multicast", channel=opts.can_channel or DEFAULT_UDP_GROUP,
                                    udp_port=opts.can_port or DEFAULT_UDP_PORT)
        self.world = world = World(scenario, robot, variant=variant,
                                   ground_clearance_m=config.planner.obstacle_points.ground_clearance_m)
        world.reset(opts.seed)
        self.metrics = EpisodeMetrics(world, scenario, opts.seed)
        self.clock = EpochMonotonicClock()
        if scenario.is_patrol and (inputs.goal is None or not config.ros.outputs.diagnostics):
            raise ValueError(f"scenario {scenario.name} is a patrol: it needs ros.inputs.goal (where its goals are "
                             "published) and ros.outputs.diagnostics (where it watches the controller) in the config")
        self.bus = open_bus(self.bus_config)
        self.transport = _open_transport(config.ros, inputs.domain_id, opts)
        self.sim_t0 = world.time_s
        self.wall_t0 = self.clock.now()
        out = config.ros.outputs
        losses = tuple(f for f in opts.faults if f.name == "dds-lost")
        # the dds-lost fault takes the sensor drivers' own participant away (on the robot they are
        # nodes of their own): they get one; otherwise they share the simulator's
        drivers = _open_transport(config.ros, inputs.domain_id, opts) if losses else self.transport
        self.sink = DdsSensorSink(drivers, inputs, self.to_wall, (out.lidar_frame, out.camera_frame),
                                  rays_per_frame=SensorRigConfig().lidar.points_per_frame)
        self.dds_loss = (_DdsLoss(losses, self.sink, drivers, lambda: _open_transport(config.ros, inputs.domain_id, opts),
                                  self.echo) if losses else None)
        self.oracle_service = None
        camera_rate_hz, segmentation = opts.camera_rate_hz, False
        if opts.oracle is not None:
            camera_rate_hz, segmentation = self._start_oracle(camera_rate_hz)
        self.diagnostics = self._diagnostics_reader()
        # The faults act where lockstep's do: between the firmware and its CAN bus, and between the
        # sensors and what they publish. None is active before the episode starts (start_s, set
        # when the controller enables the base).
        fw_bus = FaultyBus(self.bus)
        self.firmware = EmulatedBaseFirmware(fw_bus, robot)
        # emulate_clock False: the clock-step faults step this machine's clock (_SystemClockSteps), and
        # the sensors stamp with it (to_wall)
        self.injector = FaultInjector(tuple(opts.faults), self.firmware, self.sink, start_s=float("inf"),
                                      far_m=config.planner.obstacle_points.max_range_m + 4.0, seed=opts.seed,
                                      emulate_clock=False)
        fw_bus.injector = self.injector
        kills = tuple(f for f in opts.faults if f.name == "controller-kill")
        self.kills = _ControllerKills(kills, self.firmware, world, self.injector, self.echo) if kills else None
        if self.dds_loss is not None:
            self.dds_loss.injector = self.injector
        steps = tuple(f for f in opts.faults if f.name in CLOCK_STEPS)
        self.clock_steps = _SystemClockSteps(steps, self.injector, self.echo) if steps else None
        self.hogs = tuple(f for f in opts.faults if f.name == "cpu-hog")
        self._hogs_on = [False] * len(self.hogs)
        if self.oracle_service is not None:  # the vlm-* faults act in the service, over HTTP
            from hil_sim.episode.faults import VLM_STALE_S

            self.oracle_service.faults, self.oracle_service.stale_s = self.injector, VLM_STALE_S
        self.rig = SensorRig(world, robot, self.injector, SensorRigConfig(
            seed=opts.seed, camera_rate_hz=camera_rate_hz, camera_segmentation=segmentation, camera_async=True))
        self.sim = LockstepSimulation(world, self.firmware, self.metrics, [self.rig], controls=[self.injector])
        self._can_mode = protocol.CONTROL_MODE_CAN
        # every catch-up of a 10-minute run (at most one per physics step: 600k in 10 min at 1 ms)
        self.lag_samples = np.zeros(1 << 20)
        self.n_lag = 0
        self.heap = HeapTrimmer(every_ticks=0)
        self.state = _EpisodeState()

    def to_wall(self, t_sim: float) -> float:
        """A simulated time on the wall clock (ROS time), as a driver stamps with the system clock:
        a step of that clock since the start (the clock-step faults, NTP) moves the stamps with it."""
        step = self.clock.system_step_s()
        return self.wall_t0 + (t_sim - self.sim_t0) + (step if abs(step) >= CLOCK_STEP_MIN_S else 0.0)

    def _start_oracle(self, camera_rate_hz: float) -> tuple[float, bool]:
        """Serve the sim-oracle over HTTP; the sink records what the oracle answers about. Returns the
        camera's rate (lockstep's 2 Hz when none is asked for) and segmentation on."""
        from hil_sim.episode.lockstep import DCT_CAMERA_RATE_HZ
        from hil_sim.vlm.service import OracleService, RecordingSink

        self.oracle_service = OracleService.for_world(self.world, self.opts.oracle).start()
        self.sink = RecordingSink(self.sink, self.oracle_service)
        self.echo(f"dct hil serve: VLM oracle at {self.oracle_service.base_url}/v1 (chat completions) and "
                  f"{self.oracle_service.base_url} (grounding /detect)")
        return camera_rate_hz or DCT_CAMERA_RATE_HZ, True

    def _diagnostics_reader(self):
        """A reader of the controller's DiagnosticArray topic, or None when the config names none."""
        topic = self.config.ros.outputs.diagnostics
        if not topic:
            return None
        from runtime.io.ros.messages import DiagnosticArray
        from runtime.io.ros.transport import QosSpec

        return self.transport.reader(topic, DiagnosticArray, QosSpec("reliable", 4))

    def run(self, stop: threading.Event) -> tuple[float, dict]:
        """Step physics up to the wall clock, sleep, repeat until the episode ends or `stop` is set;
        returns (wall seconds, the sensors' stats)."""
        world, sim = self.world, self.sim
        dt = world.timestep_s
        half = 0.5 * dt
        self.echo(f"dct hil serve: {self.scenario.name} seed {self.opts.seed} serving: CAN udp_multicast "
                  f"{self.bus_config.channel}:{self.bus_config.udp_port}, DDS domain {self.inputs.domain_id} "
                  f"({self.transport.name}, discovery {self.opts.discovery}), pid {os.getpid()}")
        self.wall_t0 = self.clock.now()
        wall_start = time.monotonic()
        next_trim = world.time_s + TRIM_EVERY_S
        try:
            while not stop.is_set():
                now = self.clock.now()
                target = self.sim_t0 + (now - self.wall_t0)
                behind = target - world.time_s  # how late physics is before this catch-up
                stepped = 0
                while world.time_s < target - half and stepped < 200:
                    sim.step()
                    stepped += 1
                if stepped:
                    self.lag_samples[self.n_lag % len(self.lag_samples)] = max(0.0, behind)
                    self.n_lag += 1
                    self._watch_kills(world.time_s)
                if self._episode_ended(world.time_s):
                    break
                if not stepped:
                    if world.time_s >= next_trim:  # the C heap's free pages back, in the slack (runtime.loop.heap)
                        self.heap.trim()
                        next_trim = world.time_s + TRIM_EVERY_S
                    time.sleep(0.5 * dt)  # the next step is due within dt
        finally:
            if self.clock_steps is not None:  # the machine's clock as it was, whatever ended the run
                self.clock_steps.undo()
            wall = time.monotonic() - wall_start
            sensor_stats = self.rig.stats()  # before close: it lets the renderer go
            self.rig.close()
            self.bus.shutdown()
            if self.dds_loss is not None:
                self.dds_loss.close()
            self.transport.close()
            if self.oracle_service is not None:
                self.oracle_service.close()
        return wall, sensor_stats

    def _episode_ended(self, t: float) -> bool:
        """Start the episode when the controller takes the base; True (end_reason set) when it ends."""
        st = self.state
        if st.t_start is None:
            if self.firmware.control_mode == self._can_mode:
                st.t_start = t
                self.injector.start_s = t
                self.echo(f"dct hil serve: controller connected at t={t - self.sim_t0:.2f} s; episode starts")
                if self.scenario.is_patrol:
                    st.patrol = _PatrolOperator(self.scenario, self.transport, self.inputs,
                                                self.config.ros.outputs.odom_frame, self.diagnostics, t, self.to_wall,
                                                self.echo, self.opts.seed)
            elif t - self.sim_t0 > self.opts.connect_timeout_s:
                st.end_reason = "no_controller"
                return True
        elif st.patrol is not None:
            st.patrol.step(t, self.world.robot_pose())
            if st.patrol.sequencer.done:
                st.end_reason = f"patrol_{st.patrol.sequencer.end_reason}"
                return True
            if t - st.t_start >= self.scenario.time_limit_s:
                st.end_reason = "time_limit"
                return True
        else:
            if st.finished_at is None and self.diagnostics is not None and _controller_finished(self.diagnostics):
                st.finished_at = t
                self.echo(f"dct hil serve: the controller says it has finished at t={t - st.t_start:.2f} s")
            if st.finished_at is not None and t - st.finished_at >= self.opts.settle_s:
                st.end_reason, st.t_goal = "controller_finished", st.finished_at
                return True
            if t - st.t_start >= self.scenario.time_limit_s:
                st.end_reason = "time_limit"
                return True
        return False

    def _watch_kills(self, t: float) -> None:
        if self.state.t_start is None:
            return
        if self.kills is not None:
            self.kills.step(t - self.state.t_start)
        if self.clock_steps is not None:
            self.clock_steps.step(t - self.state.t_start)
        if self.dds_loss is not None:
            self.dds_loss.step(t - self.state.t_start)
        for k, fault in enumerate(self.hogs):  # say when each cpu-hog begins and ends (the runner runs it)
            on = fault.active(t - self.state.t_start)
            if on != self._hogs_on[k]:
                self._hogs_on[k] = on
                if on:
                    self.injector._count("cpu-hog")
                self.echo(f"dct hil serve: t={t - self.state.t_start:.3f} s: {HOG_LINE} {'start' if on else 'end'}")

    def report(self, wall: float, sensor_stats: dict) -> dict:
        """The episode's metrics (hil_sim.episode.metrics) with end_reason, the patrol's and the simulator's figures."""
        from hil_sim.episode.lockstep import world_distance_to_goal, world_goal_reached

        world, scenario, st, patrol = self.world, self.scenario, self.state, self.state.patrol
        t_end = world.time_s
        started = st.t_start if st.t_start is not None else t_end
        nav_time = (st.t_goal if st.t_goal is not None else t_end) - started
        x_end, y_end, _ = world.robot_pose()
        return self.metrics.to_dict(
            # As in lockstep: where the robot is when the episode ends (a goal reached just before the
            # time limit counts; `dct hil run --realtime` also needs the controller's GOAL_REACHED).
            # A patrol: its verdict (hil_sim.episode.patrol).
            goal_reached=patrol.sequencer.succeeded if patrol is not None else world_goal_reached(world, scenario),
            navigation_time_s=nav_time,
            deadline_misses=0,
            extra={
                "end_reason": st.end_reason,
                **({"patrol": {**patrol.sequencer.report(t_end), "goals_published": patrol.goals_published}}
                   if patrol is not None else {}),
                "final_distance_to_goal_m": (patrol.sequencer.distance_to_current_m((x_end, y_end))
                                             if patrol is not None else world_distance_to_goal(world, scenario)),
                "final_pose_world": [float(v) for v in world.robot_pose()],
                "sim_time_s": t_end - started,
                "scenario_warnings": list(world.scenario_warnings),
                "firmware_frames_rejected": self.firmware.frames_rejected,
                # as lockstep reports them: each fault's window and what the base obeyed around it
                "faults": [{**r, "acted_on": self.injector.applied[r["name"]]} for r in self.injector.reactions()],
                "faults_applied": dict(self.injector.applied),
                **({"controller_kills": self.kills.records} if self.kills is not None else {}),
                **({"dds_losses": self.dds_loss.records,
                    "unpublished_while_lost": self.sink.unpublished} if self.dds_loss is not None else {}),
                "simulator": self._simulator_report(wall, sensor_stats, t_end),
                **({"robot_variant": world.robot_variant.to_dict()} if world.robot_variant is not None else {}),
            },
        )

    def _simulator_report(self, wall: float, sensor_stats: dict, t_end: float) -> dict:
        """What the simulator process spent and published: pid, times, lag, publications, sensors, oracle."""
        lags = self.lag_samples[: min(self.n_lag, len(self.lag_samples))] * 1e3
        t_start = self.state.t_start
        return {
            "pid": os.getpid(),
            "wall_time_s": wall,
            "cpu_time_s": time.process_time(),
            "sim_time_total_s": t_end - self.sim_t0,
            "realtime_factor": (t_end - self.sim_t0) / wall if wall > 0 else None,
            "physics_steps": self.sim.steps,
            "heap_trim": self.heap.summary(),
            "controller_connected_after_s": None if t_start is None else t_start - self.sim_t0,
            "sim_lag_ms": {"p50": float(np.percentile(lags, 50)) if len(lags) else None,
                           "p99": float(np.percentile(lags, 99)) if len(lags) else None,
                           "max": float(lags.max()) if len(lags) else None},
            "published": dict(self.sink.published),
            "publish_ms_total": {k: v * 1e3 for k, v in self.sink.publish_s.items()},
            "sensors": sensor_stats,
            "oracle": self.oracle_service.stats() if self.oracle_service is not None else None,
        }


__all__ = ["serve", "ServeOptions", "DdsSensorSink"]


#: What the simulator says when a cpu-hog fault begins and ends (then "start" or "end"): the runner
#: (`dct hil run --realtime`) runs the busy processes.
HOG_LINE = "fault cpu-hog:"


class _DdsLoss:
    """The dds-lost faults (real time only): at the fault's start the sensor drivers' DDS participant
    is closed (the controller's subscriptions lose their publishers: discovery lost), at its end a
    new one is opened with new publishers, which the controller's readers must discover. Closing and
    opening a participant takes a while (an rclpy context: 0.1-1 s), so both run on a thread of
    their own, one after the other, beside the paced physics; nothing is published meanwhile."""

    def __init__(self, faults, sink: DdsSensorSink, transport, open_transport, echo) -> None:
        self.faults, self.sink, self.transport, self.open_transport, self.echo = \
            faults, sink, transport, open_transport, echo
        self.injector = None
        self.records: list[dict] = []
        self._lost = False
        self._work: threading.Thread | None = None

    def step(self, t: float) -> None:
        lost = any(f.active(t) for f in self.faults)
        if lost:
            self.injector._count("dds-lost")
        if lost == self._lost:
            return
        self._lost = lost
        if lost:
            self.sink.lost = True
            self.records.append({"lost_s": t, "closed_s": None, "regained_s": None})
            self.echo(f"dct hil serve: t={t:.3f} s: the sensor drivers' DDS participant closed (dds-lost)")
        self._after_work(lambda: self._close(t) if lost else self._reopen(t))

    def _after_work(self, job) -> None:
        previous = self._work

        def run():
            if previous is not None:
                previous.join()
            job()
        self._work = threading.Thread(target=run, name="dds-lost", daemon=True)
        self._work.start()

    def _close(self, t: float) -> None:
        transport, self.transport = self.transport, None
        t0 = time.monotonic()
        transport.close()
        self.records[-1]["closed_s"] = t + time.monotonic() - t0

    def _reopen(self, t: float) -> None:
        t0 = time.monotonic()
        transport = self.open_transport()
        self.sink.open_writers(transport)
        self.transport = transport
        self.sink.lost = False
        self.records[-1]["regained_s"] = t + time.monotonic() - t0
        self.echo(f"dct hil serve: t={t:.3f} s: a new sensor drivers' DDS participant opened "
                  f"({time.monotonic() - t0:.2f} s to open; the controller must discover it)")

    def close(self) -> None:
        if self._work is not None:
            self._work.join(timeout=10.0)
        if self.transport is not None:
            self.transport.close()
            self.transport = None


class _SystemClockSteps:
    """The clock-step faults in real time: this machine's system clock (CLOCK_REALTIME) stepped by
    CLOCK_STEPS at each fault's start and back at its end, as NTP steps a clock, for every process:
    the simulator's sensors stamp with it (SimulatorProcess.to_wall) and the controller reads it.
    The monotonic clock, which both loops run on, does not move. Needs CAP_SYS_TIME (root); the
    step in force is undone when the run ends, however it ends (SIGKILL aside)."""

    def __init__(self, faults, injector, echo) -> None:
        if not may_set_the_clock():
            names = ", ".join(sorted({f.name for f in faults}))
            raise ValueError(f"--fault {names}: stepping the system clock needs CAP_SYS_TIME (run as root)")
        self.faults, self.injector, self.echo = faults, injector, echo
        self.applied_s = 0.0

    def step(self, t: float) -> None:
        want = sum(CLOCK_STEPS[f.name] for f in self.faults if f.active(t))
        if want != self.applied_s:
            self._set(want, f"t={t:.3f} s")
        for f in self.faults:
            if f.active(t):
                self.injector._count(f.name)

    def undo(self) -> None:
        if self.applied_s != 0.0:
            self._set(0.0, "the run's end")

    def _set(self, want: float, when: str) -> None:
        delta = want - self.applied_s
        time.clock_settime(time.CLOCK_REALTIME, time.time() + delta)
        self.applied_s = want
        self.echo(f"dct hil serve: {when}: the system clock stepped {delta:+.3f} s")


def may_set_the_clock() -> bool:
    """CAP_SYS_TIME in this process's effective capabilities (Linux)."""
    try:
        with open("/proc/self/status", encoding="ascii") as f:
            caps = next(line.split()[1] for line in f if line.startswith("CapEff:"))
    except (OSError, StopIteration, IndexError):
        return False
    return bool(int(caps, 16) >> 25 & 1)


class _ControllerKills:
    """The controller-kill faults (real time only): at each one's start the simulator says KILL_LINE
    on stderr (`dct hil run --realtime` kills the controller with SIGKILL when it reads it and starts
    it again as the systemd unit would) and then watches the base: the last 0x111 it took from the
    dead controller and its command, the moment its own command timeout stopped it, the wheels at
    rest, and the first command to move again (the restarted controller). Episode seconds."""

    KILL_LINE = "fault controller-kill: kill the controller now"

    def __init__(self, kills, firmware, world, injector, echo) -> None:
        self.kills, self.firmware, self.world, self.injector, self.echo = kills, firmware, world, injector, echo
        self.records: list[dict | None] = [None] * len(kills)

    def step(self, t: float) -> None:
        from firmware_bridge import protocol as p

        fw = self.firmware
        for k, fault in enumerate(self.kills):
            r = self.records[k]
            if r is None:
                if fault.active(t):
                    self.records[k] = {"start_s": fault.start_s, "said_s": t, "last_command_s": None,
                                       "last_command": None, "base_timeout_s": None, "at_rest_s": None,
                                       "commanded_again_s": None}
                    self.injector._count("controller-kill")
                    self.echo(f"dct hil serve: t={t:.3f} s: {self.KILL_LINE}")
                continue
            if r["base_timeout_s"] is None:
                if fw.last_command_time_s is not None:
                    r["last_command_s"] = fw.last_command_time_s - (self.world.time_s - t)
                    r["last_command"] = [float(fw.commanded[0]), float(fw.commanded[1])]
                elif fw.error_code & p.ERROR_HOST_COMM_LOST:
                    r["base_timeout_s"] = t
            elif r["at_rest_s"] is None:
                vx, vy, wz = self.world.robot_body_velocity()
                if math.hypot(vx, vy) < 0.01 and abs(wz) < 0.02:
                    r["at_rest_s"] = t
            elif r["commanded_again_s"] is None and fw.commanded != (0.0, 0.0):
                r["commanded_again_s"] = t
