"""`dct run`: the controller as the robot runs it, in its own process.

    sensors (ROS 2 over DDS) -> RosSensorReceiver thread -> SensorInbox -> the tick
    the tick -> AgileXBaseHardware -> CAN bus (socketcan, limo_serial or udp_multicast)
    the tick -> after_tick -> bounded queue -> RosPublisher thread -> odometry, plan, P_fix/P_mov,
                                                                       diagnostics (DDS)

One code path against the robot and against the real-time simulator (`dct hil serve`): the
process cannot tell them apart, it only knows a CAN bus and DDS topics.

Start-up loads and validates everything first (robot description, calibration, config, the
distance net, the bus): a problem is one line naming the file and the field, exit status 2,
and the base is never enabled. Then the base is activated and the fixed-rate loop runs on the
wall clock until SIGINT/SIGTERM: the command goes to zero, the base is deactivated (zero 0x111
frames), the publisher and the recorder are flushed, exit 0.

The clock: sensor stamps are ROS time (the system clock; the Livox driver stamps its frames with
it), the loop needs a monotonic clock. `EpochMonotonicClock` is time.monotonic shifted once, at
start, onto the system clock: it never jumps, and a stamp and a loop time can be compared (the
input watchdogs, the deskew, the sensor-to-command latency).

Sensor-to-command latency: for each tick that used a new lidar frame (the input monitor's good
frame), the loop-clock time at which its command was written minus the end of that frame (its
last point's time). It is measured here, outside the tick (the loop's after_tick hook).

Goals: `--goal X Y YAW` in the odometry frame (the robot's pose at start), or the first
geometry_msgs/PoseStamped on the goal topic (Nav2's /goal_pose) when none is given. Every later
/goal_pose replaces the goal, while driving or waiting at the last one
(`NavigationController.request_goal`, applied at the next tick's read stage); one in another
frame than the odometry's, or one the controller refuses (not finite, out of range), is counted
in `goals_ignored` and said on stderr. The diagnostics carry the current goal (`goal_x`,
`goal_y`), `finished` (at it with a zero command) and the pose (`pose_x`, `pose_y`, `pose_yaw`),
so that an operator (the simulator's patrol, hil_sim.episode.patrol) knows when to send the next.

Planner mode dct needs a contact-tolerance backend it can build outside the simulator (vpp.backend
kind openai-compatible); the sim-oracle backend exists only inside the lockstep simulator's
process, so `dct run` refuses mode dct with it. In the real-time HIL `dct hil serve` serves the
oracle over HTTP (hil_sim.vlm.service) and `dct hil run --realtime` gives this process a config
whose backend is openai-compatible at that server: the same client as on the robot.
"""
from __future__ import annotations

import json
import signal
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from runtime.loop.fixed_rate import MonotonicClock


class RunInputError(ValueError):
    """Bad input to `dct run`: one line naming the file and the field (exit status 2)."""


class _StoppedBeforeStart(Exception):
    """SIGINT/SIGTERM while waiting for the first goal: nothing to stop, exit 0."""


class EpochMonotonicClock(MonotonicClock):
    """time.monotonic shifted once onto the system clock (ROS time): see the module docstring.
    A MonotonicClock, so the loop treats it as the wall clock."""

    def __init__(self) -> None:
        self.offset_s = time.time() - time.monotonic()

    def now(self) -> float:
        return time.monotonic() + self.offset_s

    def sleep_until(self, t_s: float) -> None:
        while True:
            remaining = t_s - self.now()
            if remaining <= 0.0:
                return
            time.sleep(remaining)


@dataclass
class RunOptions:
    robot_path: Path | None = None
    calibration_path: Path | None = None
    config_path: Path | None = None
    goal: tuple[float, float, float] | None = None
    record_path: Path | None = None
    json_path: Path | None = None
    force: bool = False
    #: Overrides of the config (`dct hil run --realtime` gives each run its own domain and group).
    domain_id: int | None = None
    can_interface: str | None = None
    can_channel: str | None = None
    can_port: int | None = None
    #: Without --goal: how long to wait for the first goal on the goal topic (None: forever).
    goal_wait_s: float | None = None
    #: Override of planner.mode.
    planner: str | None = None
    #: Leave the loop thread at normal priority (config `realtime:` not asked for): real-time HIL
    #: on a machine shared with the simulator, where SCHED_FIFO could starve it.
    normal_priority: bool = False
    #: Let planner mode pure-pursuit run (it has no obstacle awareness: tests and benches only).
    allow_pure_pursuit: bool = False


@dataclass
class Loaded:
    robot: object
    config: object
    wheel_calibration: tuple[float, float] | None
    camera_K: np.ndarray
    camera_dist: np.ndarray
    bus_config: object
    #: The calibration file's camera (CameraModel) and lidar-to-camera extrinsic (4x4) for the
    #: VPP partition; None: the robot description's nominal camera and mounts.
    camera: object = None
    T_cam_lidar: np.ndarray | None = None
    notes: list[str] = field(default_factory=list)


def load_inputs(opts: RunOptions) -> Loaded:
    """Load and validate every file and option; RunInputError (one line) on the first problem."""
    from pydantic import ValidationError

    from calibration.errors import ConfigFileError
    from calibration.robot_description import load_robot_description
    from firmware_bridge.buses import BusConfig
    from runtime.config import load_controller_config

    try:
        robot = load_robot_description(opts.robot_path)
        config = load_controller_config(opts.config_path)
        cal = None
        if opts.calibration_path is not None:
            from calibration.calibration_file import load_calibration

            cal = load_calibration(opts.calibration_path)
        from calibration.wheel_odometry import wheel_params

        params = wheel_params(robot, cal)
        wheel_calibration = (params.effective_track_m, params.wheel_scale)
    except ConfigFileError as exc:
        raise RunInputError(str(exc)) from None
    cfg_name = str(opts.config_path or "the shipped controller config")
    camera = T_cam_lidar = None
    if cal is not None:
        from calibration.calibration_file import camera_for_robot

        try:
            camera, T_cam_lidar = camera_for_robot(cal, robot, opts.calibration_path)
        except ConfigFileError as exc:
            raise RunInputError(str(exc)) from None
        K, dist = np.asarray(camera.K, float), np.asarray(camera.dist, float)
    else:
        K, dist = robot.sensors.camera.nominal_intrinsics(), np.zeros(5)
    if opts.planner is not None:
        config = config.with_planner_mode(opts.planner)
    if config.planner.mode == "pure-pursuit" and not opts.allow_pure_pursuit:
        raise RunInputError(f"{cfg_name}: planner.mode pure-pursuit has no obstacle awareness (it drives at the goal "
                            "through whatever is there): only with --allow-pure-pursuit, never on a robot among people")
    if config.planner.mode == "dct" and config.vpp.backend.kind == "sim-oracle":
        raise RunInputError(f"{cfg_name}: planner.mode dct with vpp.backend.kind sim-oracle: the sim-oracle exists "
                            "only inside the lockstep simulator's process; set vpp.backend.kind: openai-compatible "
                            "(README, Choosing the VLM backend) or run --planner all-fixed")
    if opts.goal is not None:
        from runtime.controller.navigation import GoalError, check_goal
        from runtime.common.geometry import Pose2D

        try:
            check_goal(Pose2D(*opts.goal), "--goal")
        except (GoalError, TypeError) as exc:
            raise RunInputError(f"--goal: {opts.goal}: {exc}") from None
    # The bus: the config's, with the command line's overrides.
    bus = config.can_bus.model_dump()
    if opts.can_interface is not None:
        bus = {"interface": opts.can_interface, "channel": None}
    if opts.can_channel is not None:
        bus["channel"] = opts.can_channel
    if opts.can_port is not None:
        bus["udp_port"] = opts.can_port
    try:
        bus_config = BusConfig(**bus)
    except ValidationError as exc:
        err = exc.errors()[0]
        where = ".".join(str(p) for p in err["loc"]) or "can_bus"
        raise RunInputError(f"{cfg_name}: can_bus.{where}: {err['msg']}") from None
    if opts.domain_id is not None:
        inputs = config.ros.inputs.model_copy(update={"domain_id": opts.domain_id})
        config = config.model_copy(update={"ros": config.ros.model_copy(update={"inputs": inputs})})
    if config.ros.inputs.lidar is None and config.uses_lidar:
        raise RunInputError(f"{cfg_name}: ros.inputs.lidar: planner mode {config.planner.mode} needs a lidar topic")
    if config.uses_mpc:  # the distance net must fit this robot
        from models.distance_net import DistanceNet
        from models.errors import DistanceNetError

        try:
            DistanceNet.load(config.planner.distance_net_path, robot=robot)
        except DistanceNetError as exc:
            raise RunInputError(f"{cfg_name}: planner.distance_net_path: {exc}") from None
    return Loaded(robot, config, wheel_calibration, K, dist, bus_config, camera=camera, T_cam_lidar=T_cam_lidar)


def _percentiles(values_s: np.ndarray) -> dict:
    ms = np.asarray(values_s, dtype=np.float64) * 1e3
    if not len(ms):
        return {"count": 0, "p50": None, "p99": None, "max": None}
    return {"count": int(len(ms)), "p50": float(np.percentile(ms, 50)), "p99": float(np.percentile(ms, 99)),
            "max": float(ms.max())}


class LatencyTracker:
    """Sensor-to-command latency per new lidar frame (see the module docstring); preallocated."""

    def __init__(self, capacity: int = 1 << 16) -> None:
        self._buf = np.zeros(capacity)
        self._n = 0
        self._last_scan = None

    def note(self, scan, written_s: float | None) -> None:
        if scan is None or scan is self._last_scan or written_s is None:
            return
        self._last_scan = scan
        offs = scan.point_time_offsets_s
        frame_end = float(scan.stamp_s) + (float(offs.max()) if len(offs) else float(scan.frame_duration_s))
        self._buf[self._n % len(self._buf)] = written_s - frame_end
        self._n += 1

    def values(self) -> np.ndarray:
        return self._buf[: min(self._n, len(self._buf))].copy()


def run_controller(opts: RunOptions, loaded: Loaded | None = None, stop: threading.Event | None = None,
                   echo=lambda s: print(s, file=sys.stderr, flush=True)) -> dict:
    """Run the controller process until `stop` is set (SIGINT/SIGTERM set it); returns the summary
    (also written to opts.json_path). Raises RunInputError before anything moves."""
    from cyclonedds.domain import DomainParticipant

    from firmware_bridge.base_driver import AgileXBaseDriver
    from firmware_bridge.buses import BusOpenError, open_bus
    from runtime.controller.navigation import GoalError, NavigationController
    from runtime.common.geometry import Pose2D
    from runtime.io.hardware import AgileXBaseHardware
    from runtime.loop.fixed_rate import FixedRateLoop
    from runtime.io.ros.publisher import RosPublisher, TickView
    from runtime.io.ros.receiver import RosSensorReceiver
    from runtime.io.sensor_inbox import SensorInbox
    from runtime.loop.telemetry import TickTelemetry

    loaded = loaded or load_inputs(opts)
    robot, config = loaded.robot, loaded.config
    stop = stop or threading.Event()
    if opts.json_path is not None or opts.record_path is not None:
        from calibration.outputs import OutputPathError, check_output_path

        try:
            if opts.json_path is not None:
                check_output_path(opts.json_path, what="--json", overwrite=opts.force)
        except OutputPathError as exc:
            raise RunInputError(str(exc)) from None
    recorder = None
    if opts.record_path is not None:
        from runtime.io.recording import RecordingError, RunRecorder

        try:
            recorder = RunRecorder(opts.record_path, force=opts.force)
        except RecordingError as exc:
            raise RunInputError(str(exc)) from None
    try:
        bus = open_bus(loaded.bus_config)
    except BusOpenError as exc:
        if recorder is not None:
            recorder.close()
        raise RunInputError(f"{opts.config_path or 'the shipped controller config'}: can_bus: {exc}") from None

    ros = config.ros
    participant = DomainParticipant(ros.inputs.domain_id)
    inbox = SensorInbox()
    receiver = RosSensorReceiver(ros.inputs, inbox, camera_K=loaded.camera_K, camera_distortion=loaded.camera_dist,
                                 participant=participant)
    publisher = RosPublisher(participant, ros.outputs)
    receiver.start()
    clock = EpochMonotonicClock()
    summary: dict = {"pid": None}
    controller = None
    # systemd (the deploy bundle's unit: Type=notify, WatchdogSec): ready once inputs are up, a
    # watchdog ping every tick and while waiting for a goal; a no-op outside systemd.
    from runtime.app.deploy.sd_notify import SystemdNotifier

    notifier = SystemdNotifier()
    notifier.ready()
    try:
        goal = opts.goal
        if goal is None:
            echo(f"dct run: waiting for a goal on {ros.inputs.goal.topic if ros.inputs.goal else '(no goal topic)'}")
            t_end = None if opts.goal_wait_s is None else time.monotonic() + opts.goal_wait_s
            while goal is None and not stop.is_set() and (t_end is None or time.monotonic() < t_end):
                g = receiver.take_goal()
                if g is not None and g.frame_id not in ("", ros.outputs.odom_frame):
                    echo(f"dct run: goal in frame {g.frame_id!r} ignored: goals are taken in the odometry frame "
                         f"({ros.outputs.odom_frame!r}); there is no map frame yet")
                elif g is not None:
                    goal = (g.pose.x_m, g.pose.y_m, g.pose.yaw_rad)
                else:
                    notifier.watchdog()
                    stop.wait(0.05)
            if goal is None and stop.is_set():
                raise _StoppedBeforeStart
            elif goal is None:
                raise RunInputError("no goal: give --goal X Y YAW or publish a geometry_msgs/PoseStamped on "
                                    f"{ros.inputs.goal.topic if ros.inputs.goal else 'the goal topic'}")
        driver_bus = recorder.wrap_bus(bus, clock.now) if recorder is not None else bus
        driver = AgileXBaseDriver(driver_bus, clock=clock.now, feedback_timeout_s=robot.can.feedback_timeout_s)
        hardware = AgileXBaseHardware(driver, robot.drive.skid_steer_yaw_factor)
        controller = NavigationController(
            robot, config, hardware, Pose2D(*goal), clock=clock.now,
            sensors=inbox if config.uses_lidar else None, lockstep=False,
            wheel_calibration=loaded.wheel_calibration, camera=loaded.camera, T_cam_lidar=loaded.T_cam_lidar,
        )
        telemetry = TickTelemetry()
        latency = LatencyTracker()
        out = ros.outputs
        record_hook = (recorder.attach(controller, config, {"clock": "wall", "goal": json.dumps(list(goal))})
                       if recorder is not None else None)
        loop_box: list = []
        ignored_goals = [0]

        def after_tick(row: np.void) -> None:
            """Outside the tick's timings: latency, recorder, publisher (all O(1), non-blocking)."""
            loop = loop_box[0]
            scan = controller.monitor.good_scan
            latency.note(scan, loop.stage_clock.write_done_loop_s)
            if record_hook is not None:
                record_hook(row)
            k = int(row["tick"])
            clouds = k % out.clouds_every_ticks == 0
            plan = getattr(getattr(controller.modes, "normal", None), "last_plan", None)
            # P_mov as the partition labelled it: the scan deskewed to the tick (the raw scan's
            # points lie up to 14 cm off along the motion; obstacle_points.deskew)
            mov = controller.vpp.movable_points_lidar() if clouds and controller.vpp is not None else None
            publisher.offer(TickView(
                stamp_s=float(row["scheduled_s"]), pose=controller.pose, v_mps=controller.command[0],
                omega_radps=controller.command[1], state=controller.state.name,
                stage_ms={s: float(row["stage_s"][i]) * 1e3 for i, s in enumerate(telemetry.stages)},
                tick_ms=float(row["tick_s"]) * 1e3,
                extra={"deadline_misses": telemetry.deadline_misses, "hold_reason": controller.hold_reason or "",
                       "active_mode": controller.modes.mode_name, "finished": controller.finished,
                       "goal_x": controller.goal.x_m, "goal_y": controller.goal.y_m, "pose_x": controller.pose.x_m,
                       "pose_y": controller.pose.y_m, "pose_yaw": controller.pose.yaw_rad},
                points_fix=controller.points_fix if clouds else None,
                plan_states=plan.states if clouds and plan is not None else None,
                points_mov=mov,
            ))
            g = receiver.take_goal()  # a new goal: validated now, taken by the next tick
            if g is not None:
                if g.frame_id not in ("", ros.outputs.odom_frame):
                    ignored_goals[0] += 1
                    echo(f"dct run: goal in frame {g.frame_id!r} ignored: goals are taken in the odometry frame "
                         f"({ros.outputs.odom_frame!r})")
                else:
                    try:
                        controller.request_goal(g.pose, ros.inputs.goal.topic)
                    except GoalError as exc:
                        ignored_goals[0] += 1
                        echo(f"dct run: {exc}: ignored")
            notifier.watchdog()

        loop = FixedRateLoop(
            clock, period_s=config.loop.period_s, stage_budgets_s=config.loop.stage_budgets_s,
            command_deadline_s=config.loop.command_deadline_s, keepalive_period_s=config.loop.keepalive_period_s,
            telemetry=telemetry, slack_work_min_s=config.loop.slack_work_min_s, after_tick=after_tick,
        )
        loop_box.append(loop)
        echo(f"dct run: goal {goal[0]:.3f} {goal[1]:.3f} {goal[2]:.3f} (odom frame); bus "
             f"{loaded.bus_config.interface}:{loaded.bus_config.channel}; DDS domain {ros.inputs.domain_id}; "
             f"planner {config.planner.mode}")
        # SCHED_FIFO and CPU pinning for this (the loop's) thread, when allowed; said at start.
        from runtime.loop.realtime_setup import request_realtime_from_config

        if opts.normal_priority:
            echo("dct run: real-time: not asked for (--normal-priority): the loop thread stays SCHED_OTHER")
        else:
            echo(f"dct run: {request_realtime_from_config(config.realtime).summary()}")
        wall0 = time.monotonic()
        try:
            controller.activate()
            loop.run(controller, stop.is_set)
        finally:
            controller.deactivate()  # zero command frames; the ICP worker ends
        wall = time.monotonic() - wall0
        records = telemetry.snapshot()
        report = controller.describe()
        summary = {
            "pid": None,
            "state": controller.state.name,
            "goal_odom": list(goal),
            "goal_reached_at_s": controller.goal_reached_at_s,
            "activated_at_s": controller._activated_at_s,
            "wall_time_s": wall,
            "cpu_time_s": time.process_time(),  # this process (the ICP worker's is its own)
            "controller": report,
            "events": controller.events.to_list(t0_s=controller._activated_at_s),
            "stop_reason": controller.stop_reason,
            "telemetry": telemetry.summary(),
            "realtime": {
                "tick_ms": _percentiles(records["tick_s"]),
                "sensor_to_command_ms": _percentiles(latency.values()),
                "deadline_misses": int(telemetry.deadline_misses),
                "wall_deadline_misses": int(telemetry.wall_deadline_misses),
                "ticks": int(telemetry.ticks),
                "ticks_skipped": int(telemetry.ticks_skipped),
                "lateness_ms": _percentiles(records["lateness_s"]),
            },
            #: Every frame's sensor-to-command latency in ms, in order (for a closer look at the tail).
            "sensor_to_command_values_ms": [round(float(v) * 1e3, 3) for v in latency.values()],
            "sensor_frames": dict(inbox.accepted),
            "sensor_errors": {**dict(sorted(inbox.error_counts.items())),
                              **{f"ros.{k}": v for k, v in receiver.error_counts.items()}},
            "ros_received": dict(receiver.received),
            "goals_ignored": ignored_goals[0],
            "keepalives_sent": loop.keepalives_sent,
        }
    except _StoppedBeforeStart:
        echo("dct run: stopped before any goal arrived; the base was never enabled")
        summary = {"state": "NOT_STARTED"}
    finally:
        # Each step on its own: one that fails (a receiver thread that will not stop) must not skip
        # the others (the recording's rename, the bus) nor hide the error that brought us here.
        notifier.stopping()
        cleanup_errors = []
        for name, step in (("receiver", receiver.stop), ("publisher", publisher.close)):
            try:
                step()
            except Exception as exc:  # noqa: BLE001 - recorded in the summary
                cleanup_errors.append(f"{name}: {type(exc).__name__}: {exc}")
        if summary.get("state") is not None:
            summary["publisher"] = publisher.stats()
        if recorder is not None:
            try:
                rec = recorder.close()
                summary["recording"] = {"path": str(rec.get("path")), "dropped": rec.get("dropped_total")}
            except Exception as exc:  # noqa: BLE001 - the summary is still written
                summary["recording"] = {"error": str(exc)}
        try:
            bus.shutdown()
        except Exception as exc:  # noqa: BLE001 - recorded in the summary
            cleanup_errors.append(f"bus: {type(exc).__name__}: {exc}")
        if cleanup_errors:
            summary["cleanup_errors"] = cleanup_errors
    import os

    summary["pid"] = os.getpid()
    if opts.json_path is not None:
        from calibration.outputs import atomic_write_json

        atomic_write_json(opts.json_path, summary)
    return summary


def install_stop_signals(stop: threading.Event) -> None:
    """SIGINT and SIGTERM end the loop at the next tick boundary (never inside a tick)."""
    def handler(signum, frame):  # noqa: ARG001
        stop.set()

    signal.signal(signal.SIGINT, handler)
    signal.signal(signal.SIGTERM, handler)


def summary_line(s: dict) -> str:
    rt = s["realtime"]
    t, lat = rt["tick_ms"], rt["sensor_to_command_ms"]

    def f(d, k):
        return "-" if d[k] is None else f"{d[k]:.1f}"

    return (f"dct run: stopped in state {s['state']} after {s['wall_time_s']:.1f} s, {rt['ticks']} ticks; tick ms "
            f"p50 {f(t, 'p50')} p99 {f(t, 'p99')} max {f(t, 'max')}; sensor-to-command ms p50 {f(lat, 'p50')} "
            f"p99 {f(lat, 'p99')} max {f(lat, 'max')} ({lat['count']} frames); deadline misses {rt['deadline_misses']}")


def _make_command():
    import click

    class InputError(click.ClickException):
        exit_code = 2

    @click.command("run")
    @click.option("--robot", "robot_path", type=click.Path(dir_okay=False, path_type=Path),
                  help="Robot description YAML (default: the shipped LIMO).")
    @click.option("--calibration", "calibration_path", type=click.Path(dir_okay=False, path_type=Path),
                  help="The robot's calibration file (camera intrinsics, wheel odometry); default: nominal values.")
    @click.option("--config", "config_path", type=click.Path(dir_okay=False, path_type=Path),
                  help="Controller config YAML (default: the shipped one); its ros: and can_bus: sections.")
    @click.option("--goal", nargs=3, type=float, metavar="X Y YAW",
                  help="Goal in the odometry frame (m, m, rad). Default: the first PoseStamped on the goal topic.")
    @click.option("--record", "record_path", type=click.Path(dir_okay=False, path_type=Path),
                  help="Record the run to this MCAP file (`dct report latency` reads it).")
    @click.option("--json", "json_path", type=click.Path(dir_okay=False, path_type=Path),
                  help="Write the run's summary here at exit (state, tick and sensor-to-command latency).")
    @click.option("--force", is_flag=True, help="Overwrite an existing --record or --json file.")
    @click.option("--domain-id", type=click.IntRange(0, 232), help="Override ros.inputs.domain_id.")
    @click.option("--can-interface", type=click.Choice(["socketcan", "limo_serial", "udp_multicast", "virtual"]),
                  help="Override can_bus.interface (the channel then defaults for it).")
    @click.option("--can-channel", help="Override can_bus.channel.")
    @click.option("--can-port", type=click.IntRange(1, 65535), help="Override can_bus.udp_port (udp_multicast).")
    @click.option("--planner", type=click.Choice(["dct", "all-fixed"]), default=None,
                  help="Override the config's planner.mode.")
    @click.option("--allow-pure-pursuit", is_flag=True,
                  help="Let planner mode pure-pursuit run: no obstacle awareness (tests and benches only).")
    @click.option("--normal-priority", is_flag=True,
                  help="Do not ask for SCHED_FIFO / CPU pinning (config realtime:), e.g. beside a simulator.")
    @click.option("--goal-wait", "goal_wait_s", type=click.FloatRange(0.0, None),
                  help="Without --goal: give up after this many seconds without a goal (default: wait).")
    def run_command(robot_path, calibration_path, config_path, goal, record_path, json_path, force, domain_id,
                    can_interface, can_channel, can_port, goal_wait_s, planner, normal_priority,
                    allow_pure_pursuit) -> None:
        """The controller process: sensors over ROS 2 DDS, the base over CAN, the fixed-rate loop on the wall
        clock until SIGINT/SIGTERM (then: zero command, deactivate, flush, exit 0). Exit 2 on bad input."""
        for what, p in (("--robot", robot_path), ("--calibration", calibration_path), ("--config", config_path)):
            if p is not None and not p.is_file():
                raise InputError(f"{what}: {p}: no such file")
        opts = RunOptions(robot_path, calibration_path, config_path, tuple(goal) if goal else None, record_path,
                          json_path, force, domain_id, can_interface, can_channel, can_port, goal_wait_s, planner,
                          normal_priority, allow_pure_pursuit)
        stop = threading.Event()
        install_stop_signals(stop)
        try:
            loaded = load_inputs(opts)
            summary = run_controller(opts, loaded, stop, echo=lambda s: click.echo(s, err=True))
        except RunInputError as exc:
            raise InputError(str(exc)) from None
        if summary.get("state") != "NOT_STARTED":
            click.echo(summary_line(summary), err=True)

    return run_command


run_command = _make_command()

__all__ = ["run_command", "run_controller", "load_inputs", "RunOptions", "EpochMonotonicClock", "RunInputError"]
