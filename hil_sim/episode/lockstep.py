"""Lockstep HIL episodes: simulation time drives everything.

The controller runs its ordinary fixed-rate loop; its clock is the simulator's. Each
`sleep_until(t)` of the loop advances physics to t, stepping the emulated base firmware
(which reads the controller's CAN frames and answers with feedback frames) every physics
step. The controller and the firmware talk over an in-process python-can bus
(hil_sim.episode.lockstep_bus.LockstepBus), exactly the frames they would exchange on the
robot; the controller is wired as on the robot (runtime.controller.builder).

Deterministic: an episode's metrics depend only on the scenario, robot, config, seed and faults.
What the computer spent (wall-clock stage and tick times, wall-clock deadline misses) is returned
in `telemetry` and `wall_time_s`, never in the metrics.

A patrol scenario (`goals:`): hil_sim.episode.patrol.PatrolSequencer sends the next goal to the
controller (`request_goal`, between two ticks) when it has finished with the current one; the
episode ends with the patrol (its loops or duration), and the metrics add `patrol` (goals sent,
reached, missed, every visit); `goal_reached` is the patrol's verdict.
"""
from __future__ import annotations

import time
import uuid
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Callable, Iterable, Protocol

import can
import numpy as np

from calibration.robot_description import RobotDescription, load_robot_description
from firmware_bridge.firmware_emulator import EmulatedBaseFirmware
from hil_sim.episode.faults import FaultInjector, FaultSpec, FaultyBus
from hil_sim.episode.metrics import EpisodeMetrics
from hil_sim.episode.failure import failure_reason
from hil_sim.episode.lockstep_bus import LockstepBus
from hil_sim.episode.patrol import PatrolSequencer
from hil_sim.world.robot_variant import RobotVariant, resolve_variant
from hil_sim.world.scenario import Scenario, load_scenario
from hil_sim.world.mujoco_world import World
from runtime.config import ControllerConfig, load_controller_config
from runtime.controller.builder import RobotSetup, Wiring, assemble
from runtime.controller.navigation import ControllerState, NavigationController
from runtime.common.geometry import Pose2D
from runtime.io.sensor_inbox import SensorInbox

if TYPE_CHECKING:  # the rig imports MuJoCo rendering only when sensors are on
    from calibration.sensor_calibration import SensorCalibration
    from hil_sim.world.sensor_rig import SensorRigConfig
    from models.vlm.sim_oracle import SimOracleConfig
    from runtime.io.recording import RunRecorder
    from runtime.loop.telemetry import TickTelemetry

#: Camera frames per second in planner mode dct (the VLM answers about once a second).
DCT_CAMERA_RATE_HZ = 2.0
#: Simulated time from a camera frame's instant to its arrival at the controller (exposure,
#: read-out, USB transfer). The frame renders beside the physics meanwhile, in a thread of its
#: own, so a lockstep step does not stall on the renderer (tens of ms per frame).
CAMERA_LATENCY_S = 0.05


class SimulatedDevice(Protocol):
    """Anything stepped with physics (sensors, later fault injectors)."""

    def step(self, t_s: float) -> None: ...


class LockstepSimulation:
    """Physics + emulated firmware (+ sensors), advanced only when asked."""

    def __init__(
        self,
        world: World,
        firmware: EmulatedBaseFirmware,
        metrics: EpisodeMetrics | None = None,
        devices: Iterable[SimulatedDevice] = (),
        controls: Iterable[SimulatedDevice] = (),
    ) -> None:
        """devices: stepped after physics (sensors). controls: stepped before the firmware, with
        the time of the step about to be taken (fault injection: a fault that starts at t acts on
        everything the firmware and the sensors produce from t on)."""
        self.world = world
        self.firmware = firmware
        self.metrics = metrics
        self.devices = list(devices)
        self.controls = list(controls)
        self.steps = 0
        self._half_step = 0.5 * world.timestep_s

    @property
    def time_s(self) -> float:
        return self.world.time_s

    def step(self) -> None:
        """One physics step, then every device with the time *before* the step.

        mj_step computes kinematics and sensors of the state at the start of the step and then
        integrates, so after it the poses and sensordata in `data` belong to that earlier time.
        """
        world = self.world
        t_before = world.time_s
        for control in self.controls:
            control.step(t_before)
        torques = self.firmware.step(t_before, world.wheel_speeds_radps(), world.wheel_angles_rad())
        world.set_wheel_torques(torques)
        world.step()
        self.steps += 1
        if self.metrics is not None:
            self.metrics.update(world)
        for device in self.devices:
            device.step(t_before)

    def advance_to(self, t_s: float) -> None:
        while self.world.time_s < t_s - self._half_step:
            self.step()


class LockstepBarrier(Protocol):
    """Work beside the tick that delivers at a fixed simulated latency (ICP): once physics has
    reached t_s, and before the tick at t_s runs, the simulator waits for whatever is due by
    t_s instead of racing it."""

    def settle(self, t_s: float) -> None: ...


class LockstepClock:
    """The loop's clock in lockstep mode: now() is simulation time; sleeping advances physics
    (and waits for every barrier's work due by then)."""

    def __init__(self, sim: LockstepSimulation, barriers: Iterable[LockstepBarrier] = (),
                 system_step: Callable[[], float] | None = None) -> None:
        """system_step: how far the emulated system clock is stepped now (the clock-step faults,
        hil_sim.episode.faults.FaultInjector.system_step_s); None: it never steps."""
        self.sim = sim
        self.barriers = list(barriers)
        self._system_step = system_step

    def now(self) -> float:
        return self.sim.time_s

    def system_step_s(self) -> float:
        """What runtime.loop.clocks.EpochMonotonicClock.system_step_s says on the robot."""
        return 0.0 if self._system_step is None else self._system_step()

    def sleep_until(self, t_s: float) -> None:
        self.sim.advance_to(t_s)
        for barrier in self.barriers:
            barrier.settle(self.sim.time_s)


def virtual_bus_pair(channel: str | None = None) -> tuple[can.BusABC, can.BusABC]:
    """Two ends of one in-process CAN bus: (controller side, simulator side). python-can buses
    (hil_sim.episode.lockstep_bus.LockstepBus: python-can's virtual bus without its per-frame
    deep copy and wall-clock stamps)."""
    channel = channel or f"dct-hil-{uuid.uuid4().hex}"
    return LockstepBus(channel), LockstepBus(channel)


@dataclass
class EpisodeResult:
    metrics: dict
    telemetry: dict
    controller: dict
    wall_time_s: float
    sim_time_s: float
    extra: dict = field(default_factory=dict)
    #: The telemetry's per-tick records (runtime.loop.telemetry.tick_record_dtype), oldest first:
    #: what `dct bench tick` takes its percentiles from (the summary above has only a few).
    tick_records: np.ndarray | None = None

    @property
    def realtime_factor(self) -> float:
        return self.sim_time_s / self.wall_time_s if self.wall_time_s > 0 else float("inf")


def goal_in_odom_frame(scenario: Scenario) -> Pose2D:
    """The goal relative to the start pose: the odometry frame starts at the robot's start."""
    start = Pose2D(scenario.robot_start.x_m, scenario.robot_start.y_m, scenario.robot_start.yaw_rad)
    goal = Pose2D(scenario.goal.x_m, scenario.goal.y_m, scenario.goal.yaw_rad)
    return start.inverse().compose(goal)


# (Long for the documentation of its sixteen keyword options; the body is about 40 lines.)
def _refuse_realtime_only(faults) -> None:
    from hil_sim.episode.faults import FAULTS, FaultSpecError

    for f in faults:
        kind = FAULTS.get(f.name)
        if kind is not None and kind.realtime_only:
            raise FaultSpecError(f"--fault {f.name}: real time only (`dct hil run --realtime`): a lockstep episode "
                                 "has the controller in the simulator's process")


def run_episode(
    scenario: Scenario | str,
    *,
    robot: RobotDescription | None = None,
    config: ControllerConfig | None = None,
    seed: int = 0,
    settle_s: float = 0.5,
    progress: Callable[[float], None] | None = None,
    sensors: "SensorRigConfig | None | bool" = None,
    faults: Iterable[FaultSpec] = (),
    wheel_calibration: tuple[float, float] | None = None,
    observe: Callable[[NavigationController], None] | None = None,
    oracle: "SimOracleConfig | None" = None,
    on_start: "Callable[[LockstepSimulation, NavigationController], None] | None" = None,
    recorder: "RunRecorder | None" = None,
    sensor_calibration: "SensorCalibration | None" = None,
    goal_when_ready: bool = False,
    robot_variant: "RobotVariant | None" = None,
    on_telemetry: "Callable[[TickTelemetry], None] | None" = None,
    end_requested: Callable[[], bool] | None = None,
) -> EpisodeResult:
    """Run one lockstep episode of the navigation controller in a scenario.

    sensors: a SensorRigConfig, True for the default rig, False for none; None picks what the
    controller needs (lidar + IMU for the MPC and grid-astar, nothing for pure pursuit).
    faults: injected faults (hil_sim.episode.faults), times from the start of the episode.
    wheel_calibration: (effective track m, wheel scale) for the odometry (calibration file).
    sensor_calibration: the camera and mounts the controller believes
    (calibration.sensor_calibration: a calibration file's, else the description's nominal ones):
    every stage places and projects with them, and the images reach it carrying its intrinsics.
    The world builds the robot as `robot_variant` says (else as described) and the simulated camera
    renders with its true intrinsics (reported to the controller as the camera driver's
    CameraInfo): a calibration's error is real here, and the calibration check sees it.
    observe: called with the controller once after every tick, outside the tick and its timing:
    evaluation harnesses that inspect the stages they measure (`dct bench tick` reads the frame's
    point counts and the planner's counters with it); other observers read `controller.snapshot`.
    on_telemetry: called once with the loop's TickTelemetry before the first tick (a soak reads the
    tick records as they come, outside the tick: hil_sim.bench.soak).
    end_requested: asked between two ticks; True ends the episode there, its metrics as they are
    (an interrupted soak keeps what it measured).
    on_start: called once with the simulation and the controller before the first tick
    (evaluations attach to the sensor rig's listeners: `dct vpp eval`).
    recorder: records the ticks, poses, CAN frames, P_fix and plan to MCAP (runtime.io.recording);
    the caller closes it. Recording changes no metric.
    goal_when_ready: the navigation clock of a robot switched on before it is sent: the controller
    starts in standby (start-up sequence, odometry, the VLM partition's first answer; the robot
    stands still) and the goal is given at the first tick at which it is ACTIVE and its partition
    ready (the vpp partition: the VLM answered once; otherwise the start-up sequence done).
    Navigation time, the time limit and the events count from then (`standby_s` says how long it
    stood). False (default): the goal is given at switch-on and the clock starts there.
    robot_variant: the simulated robot as built (hil_sim.world.robot_variant: its camera's
    intrinsics and lens, its lidar and camera mounts); None: the scenario's `robot_variant:`, else
    the robot as described. The controller is not told: it reads `robot` (and its calibration).
    The metrics add `robot_variant` (the departures and the truth) when there is one.
    oracle: the VPP's sim-oracle settings, used as given (its seed too) instead of the config's
    `vpp.backend` (whose seed is added to the episode seed). With no `oracle` and a backend other
    than the sim-oracle in the config, the controller builds that backend. (Module docstring: patrols,
    determinism.)
    """
    faults = tuple(faults)
    _refuse_realtime_only(faults)
    if isinstance(scenario, str):
        scenario = load_scenario(scenario, seed=seed)  # a generated scene is drawn from the seed
    robot = robot or load_robot_description()
    config = config or load_controller_config()
    if robot_variant is None and scenario.robot_variant is not None:
        robot_variant = resolve_variant(scenario.robot_variant, robot)
    bench = _SimulatedBench.build(scenario, robot, config, seed, faults, sensors, sensor_calibration, robot_variant)
    sim = LockstepSimulation(bench.world, bench.firmware, bench.metrics, bench.devices, controls=[bench.injector])
    clock = LockstepClock(sim, system_step=bench.injector.system_step_s)
    bench.inbox.stamp_clock = clock  # stamps back onto the loop's clock across a step, as on the robot
    bus = recorder.wrap_bus(bench.controller_bus, clock.now) if recorder is not None else bench.controller_bus
    if sensor_calibration is None:
        from calibration.sensor_calibration import nominal_sensors

        sensor_calibration = nominal_sensors(robot)
    try:  # loads the distance net: a bad model file must not leave the buses open
        parts = assemble(RobotSetup(robot, config, wheel_calibration, sensor_calibration),
                         Wiring(bus, clock, goal_in_odom_frame(scenario), bench.inbox if bench.has_sensors else None,
                                lockstep=True, vlm_backend=_faulty(_vlm_backend(bench.world, config, oracle, seed),
                                                                   bench.injector, faults),
                                goal_given=not goal_when_ready, start_odometry=True))
    except BaseException:
        bench.close()
        raise
    controller = parts.controller
    parts.loop.before_tick = bench.hand_over_due
    clock.barriers.append(controller.odometry)
    clock.barriers.append(controller)  # the VLM answers due (the vpp partition; nothing otherwise)
    operator = _Operator(sim, controller, scenario, settle_s, progress, observe, seed)
    operator.end_requested = end_requested

    def before() -> None:  # inside the run's clean-up: a harness that fails here closes everything
        bench.wait_ready()
        if recorder is not None:
            from runtime.io.ros.outbound import robot_sensor_mounts

            out = config.ros.outputs
            mounts = robot_sensor_mounts(sensor_calibration, base_frame=out.base_frame,
                                         lidar_frame=out.lidar_frame, camera_frame=out.camera_frame)
            parts.loop.after_tick = recorder.attach(controller, config, {"scenario": scenario.name, "seed": seed,
                                                                          "clock": "lockstep"}, static_transforms=mounts)
        if on_telemetry is not None:
            on_telemetry(parts.telemetry)
        if on_start is not None:
            on_start(sim, controller)

    wall0 = time.perf_counter()
    try:
        parts.run(operator.should_stop, before=before)
    finally:
        try:
            sim.advance_to(sim.time_s + 0.02)  # let the firmware consume the final zero command
        finally:
            bench.close()
    wall = time.perf_counter() - wall0
    return _result(_Episode(bench, sim, parts, operator, config, faults, goal_when_ready), wall)


def _faulty(backend, injector: FaultInjector, faults):
    """The backend behind the VLM service's faults when any is injected (FaultyVlm), else as it is."""
    if backend is None or not any(f.name.startswith("vlm-") for f in faults):
        return backend
    from hil_sim.episode.faults import FaultyVlm

    return FaultyVlm(backend, injector)


def _vlm_backend(world, config, oracle, seed):
    """The sim-oracle, which needs this world's object table: built here, passed to the controller.
    None for any other backend (the controller builds it from the config) or without the VPP."""
    if not config.uses_vlm_backend or (oracle is None and config.vpp.backend.kind != "sim-oracle"):
        return None
    from hil_sim.vlm.oracle import oracle_backend

    return oracle_backend(world, oracle or config.vpp.backend.oracle_config(episode_seed=seed))


@dataclass
class _SimulatedBench:
    """The simulated robot on its bench: the world, the emulated firmware on one end of a virtual
    CAN bus, the sensor rig feeding the inbox, the fault injector, the episode's metrics."""

    world: World
    metrics: EpisodeMetrics
    controller_bus: can.BusABC
    sim_bus: can.BusABC
    firmware: EmulatedBaseFirmware
    inbox: SensorInbox
    injector: FaultInjector
    devices: list
    has_sensors: bool

    @classmethod
    def build(cls, scenario, robot, config, seed, faults, sensors, sensor_calibration,
              robot_variant=None) -> "_SimulatedBench":
        world = World(scenario, robot, ground_clearance_m=config.planner.obstacle_points.ground_clearance_m,
                      variant=robot_variant)
        world.reset(seed)
        metrics = EpisodeMetrics(world, scenario, seed)
        controller_bus, channel = virtual_bus_pair()
        sim_bus = FaultyBus(channel)  # the CAN faults act between the firmware and its channel
        try:  # a device that cannot be built must not leave the buses open
            firmware = EmulatedBaseFirmware(sim_bus, robot)
            inbox = SensorInbox()
            injector = FaultInjector(
                faults, firmware, inbox, start_s=world.time_s,
                far_m=config.planner.obstacle_points.max_range_m + 4.0, seed=seed,
            )
            sim_bus.injector = injector
            if sensors is None:
                sensors = config.uses_lidar
            has_sensors = sensors is not False
            devices = ([_sensor_rig(world, robot, config, injector, sensors, seed, sensor_calibration)]
                       if has_sensors else [])
            for rig in devices:  # a late render's image reaches the inbox before the tick (run_episode)
                rig.defer_hand_over = rig.config.camera_async
        except BaseException:
            controller_bus.shutdown()
            sim_bus.shutdown()
            raise
        return cls(world, metrics, controller_bus, sim_bus, firmware, inbox, injector, devices, has_sensors)

    def hand_over_due(self, t_s: float) -> None:
        """Before the tick at t_s (FixedRateLoop.before_tick): every image whose time the physics
        passed while it still rendered reaches the inbox (SensorRig.defer_hand_over), waiting
        for its render: the tick finds what it would have found had the physics waited at the
        image's instant, and the physics ran on beside the render meanwhile. Nothing but the
        tick reads the inbox (the keepalives between ticks only re-send the command)."""
        for device in self.devices:
            device.hand_over_due()

    def wait_ready(self) -> None:
        """Until every sensor device can produce (a rig's lidar cast process has started: it
        starts with the bench, beside the controller's build)."""
        for device in self.devices:
            device.wait_ready()

    def close(self) -> None:
        try:
            for device in self.devices:
                device.close()
        finally:
            self.controller_bus.shutdown()
            self.sim_bus.shutdown()


def _sensor_rig(world, robot, config, injector, sensors, seed, sensor_calibration):
    from hil_sim.world.sensor_rig import SensorRig, SensorRigConfig

    rig_config = SensorRigConfig(seed=seed) if sensors is True else sensors
    if config.uses_camera:
        # The VLM's eyes: 2 images a second with ground-truth segmentation for the sim-oracle,
        # arriving CAMERA_LATENCY_S after their instant. A rig config that sets its own camera
        # keeps it (`dct vpp eval`: its listeners read the ground truth at the frame's instant).
        # The sim-oracle answers from the segmentation: its RGB (kept only by a recording) renders
        # without multisampling, at half the cost.
        update = {"camera_segmentation": True}
        if not rig_config.model_fields_set & {"camera_rate_hz", "camera_async", "camera_latency_s"}:
            update |= {"camera_rate_hz": DCT_CAMERA_RATE_HZ, "camera_async": True, "camera_latency_s": CAMERA_LATENCY_S}
        elif not rig_config.camera_rate_hz:
            update["camera_rate_hz"] = DCT_CAMERA_RATE_HZ
        if "camera_antialias" not in rig_config.model_fields_set and config.vpp.backend.kind == "sim-oracle":
            update["camera_antialias"] = False
        rig_config = rig_config.model_copy(update=update)
    if "lidar_process" not in rig_config.model_fields_set:  # the same frames, cast beside the physics
        rig_config = rig_config.model_copy(update={"lidar_process": True})
    if rig_config.camera_async and rig_config.camera_latency_s == 0:
        raise ValueError("lockstep: SensorRigConfig.camera_async needs camera_latency_s > 0 (an image handed "
                         "over when its render is done would reach the controller at a wall-clock moment)")
    intrinsics = None
    if sensor_calibration is not None:  # the images carry what the controller believes, as on the robot
        intrinsics = (sensor_calibration.camera.K, sensor_calibration.camera.dist)
    return SensorRig(world, robot, injector, rig_config, intrinsics=intrinsics)


class _Operator:
    """Between ticks (the loop asks before every tick and once at the end): the observer, the
    goal-when-ready clock, the patrol's next goal, and when the episode ends."""

    def __init__(self, sim, controller, scenario, settle_s, progress, observe, seed: int = 0) -> None:
        self.sim, self.controller, self.scenario = sim, controller, scenario
        self.settle_s, self.progress, self.observe = settle_s, progress, observe
        self.t_switch_on = sim.time_s
        self.clock_start = sim.time_s  # where the navigation clock starts (moved on by goal_when_ready)
        self.finished_at: float | None = None
        self.patrol = PatrolSequencer(scenario, self.t_switch_on, seed) if scenario.is_patrol else None
        self.end_requested: Callable[[], bool] | None = None

    def should_stop(self) -> bool:
        controller, snap = self.controller, self.controller.snapshot
        if self.observe is not None and snap is not None:
            self.observe(controller)  # after each tick
        now = self.sim.time_s
        if self.progress is not None:
            self.progress(now)
        if self.end_requested is not None and self.end_requested():
            return True
        if (not controller.goal_given and controller.state is ControllerState.ACTIVE
                and controller.partition.ready(now)):
            controller.give_goal(now)  # this coming tick plans
            self.clock_start = now
        time_up = now >= self.clock_start + self.scenario.time_limit_s
        if self.patrol is not None:  # the operator: the next goal once the controller is done with this one
            return self._patrol(now, snap) or time_up
        if time_up:
            return True
        if controller.finished:
            if self.finished_at is None:
                self.finished_at = now
            return now >= self.finished_at + self.settle_s
        return False

    def _patrol(self, now: float, snap) -> bool:
        controller = self.controller
        goal = controller.goal if snap is None else snap.goal
        finished = controller.finished if snap is None else snap.finished
        state = controller.state if snap is None else snap.state
        pose = controller.pose if snap is None else snap.pose
        nxt = self.patrol.update(now, self.sim.world.robot_pose(), (goal.x_m, goal.y_m), finished,
                                 state is ControllerState.STOPPED, pose)
        if nxt is not None:
            controller.request_goal(nxt, "patrol")
        return self.patrol.done


def _result(ep: "_Episode", wall: float) -> EpisodeResult:
    bench, sim, parts, operator = ep.bench, ep.sim, ep.parts, ep.operator
    controller, telemetry, world, scenario = parts.controller, parts.telemetry, bench.world, operator.scenario
    t_start, patrol = operator.clock_start, operator.patrol
    if patrol is not None:
        reached = patrol.succeeded
        nav_time = sim.time_s - t_start
        x, y, _ = world.robot_pose()
        final_distance = patrol.distance_to_current_m((x, y))
    else:
        reached = controller.state is ControllerState.GOAL_REACHED and world_goal_reached(world, scenario)
        if controller.goal_reached_at_s is not None:
            nav_time = controller.goal_reached_at_s - t_start
        else:
            nav_time = sim.time_s - t_start
        final_distance = world_distance_to_goal(world, scenario)
    report = controller.describe()
    result_metrics = bench.metrics.to_dict(
        goal_reached=reached,
        navigation_time_s=nav_time,
        deadline_misses=telemetry.deadline_misses,
        extra=_extra_metrics(ep, report, final_distance),
    )
    result_metrics["failure_reason"] = failure_reason(result_metrics, report)
    return EpisodeResult(
        metrics=result_metrics,
        telemetry=telemetry.summary(),
        controller=report,
        wall_time_s=wall,
        sim_time_s=sim.time_s - operator.t_switch_on,
        extra={
            "keepalives_sent": parts.loop.keepalives_sent,
            "heap_trim": parts.loop.heap.summary(),
            "firmware_frames_rejected": bench.firmware.frames_rejected,
            "physics_steps": sim.steps,
            "timestep_s": world.timestep_s,
            "sensor_errors": dict(bench.inbox.error_counts),
            "sensor_frames": dict(bench.inbox.accepted),
            "faults_applied": dict(bench.injector.applied),
            "odometry_wall_clock": controller.odometry.wall_clock(),
        },
        tick_records=telemetry.snapshot(),
    )


@dataclass
class _Episode:
    """An episode that ran: what its result is read from."""

    bench: _SimulatedBench
    sim: LockstepSimulation
    parts: object  # runtime.controller.builder.Assembly
    operator: _Operator
    config: ControllerConfig
    faults: tuple
    goal_when_ready: bool


def _extra_metrics(ep: _Episode, report: dict, final_distance: float) -> dict:
    bench, sim, operator, controller = ep.bench, ep.sim, ep.operator, ep.parts.controller
    config, faults, goal_when_ready = ep.config, ep.faults, ep.goal_when_ready
    world, t_start, patrol = bench.world, operator.clock_start, operator.patrol
    return {
        "controller_state": controller.state.name,
        # {reason, since_s, configured} once a calibration mismatch made the partition all-fixed
        "partition_fallback": report.get("partition_fallback"),
        "stop_reason": controller.stop_reason,
        "final_distance_to_goal_m": final_distance,
        "final_pose_world": [float(v) for v in world.robot_pose()],
        "sim_time_s": sim.time_s - operator.t_switch_on,
        # the navigation clock: "switch-on" (the goal given at start) or "goal-when-ready"
        "navigation_clock": "goal-when-ready" if goal_when_ready else "switch-on",
        "standby_s": t_start - operator.t_switch_on,
        "planner": config.preset,
        # each fault's window, what it acted on, and when the base first obeyed a zero command
        # after it began and drove again after it ended (FaultInjector.reactions; fault times)
        "faults": [{**r, "acted_on": bench.injector.applied[r["name"]]} for r in bench.injector.reactions()],
        "events": controller.events.to_list(t0_s=t_start),
        # DCT correcting mode (runtime.modes.correcting): how often, and each one's start,
        # duration, object relabelled fixed (None) and reason.
        "correcting_events": int(report.get("correcting_events", 0)),
        "correcting": controller.modes.correcting_report(t0_s=t_start),
        "controller": report,
        # What ICP's range gate dropped (counts, fractions, the warning above a quarter).
        "icp_range_gate": report.get("odometry", {}).get("icp_range_gate"),
        "sensor_errors": dict(sorted(bench.inbox.error_counts.items())),
        "firmware_frames_rejected": bench.firmware.frames_rejected,
        "scenario_warnings": list(world.scenario_warnings),
        **({"patrol": patrol.report(sim.time_s)} if patrol is not None else {}),
        **({"robot_variant": world.robot_variant.to_dict()} if world.robot_variant is not None else {}),
    }


def world_distance_to_goal(world: World, scenario: Scenario) -> float:
    x, y, _ = world.robot_pose()
    return float(((x - scenario.goal.x_m) ** 2 + (y - scenario.goal.y_m) ** 2) ** 0.5)


def world_goal_reached(world: World, scenario: Scenario) -> bool:
    return world_distance_to_goal(world, scenario) <= scenario.goal.tolerance_m
