"""`dct run`: the controller as the robot runs it, in its own process.

    sensors (ROS 2 over DDS) -> RosSensorReceiver thread -> SensorInbox -> the tick
    the tick -> AgileXBaseHardware -> CAN bus (socketcan, limo_serial or udp_multicast)
    (--record: the receiver thread also queues each sample's raw bytes for the recorder)
    the tick -> after_tick -> bounded queue -> RosPublisher thread -> odometry, plan, P_fix/P_mov,
                                                                       diagnostics (DDS)

One code path against the robot and against the real-time simulator (`dct hil serve`): the
process cannot tell them apart, it only knows a CAN bus and DDS topics.

Start-up loads and validates everything first (robot description, calibration, config, the
distance net, the bus): a problem is one line naming the file and the field, exit status 2,
and the base is never enabled. Then the base is activated and the fixed-rate loop runs on the
wall clock until SIGINT/SIGTERM: the command goes to zero, the base is deactivated (zero 0x111
frames), the publisher and the recorder are flushed, exit 0.

The pieces are wired by runtime.controller.builder (the same wiring as the lockstep HIL); the
clock is runtime.loop.clocks.EpochMonotonicClock (ROS time that never jumps); what happens after
each tick (latency, recorder, publisher, goals) is runtime.app.run_observer's; the inputs are
loaded and checked by runtime.app.run_inputs.

Goals: `--goal X Y YAW` in the odometry frame (the robot's pose at start), or the first
geometry_msgs/PoseStamped on the goal topic (Nav2's /goal_pose) when none is given. Every later
/goal_pose replaces the goal, while driving or waiting at the last one
(`NavigationController.request_goal`, applied at the next tick's read stage); one in another
frame than the odometry's, one outside the configured goal workspace (ros.inputs.goal.workspace;
`--goal` outside it is refused before the base is enabled), or one the controller refuses (not
finite, out of range), is counted in `goals_ignored` and said on stderr. The diagnostics carry
the current goal (`goal_x`, `goal_y`), `finished` (at it with a zero command) and the pose
(`pose_x`, `pose_y`, `pose_yaw`), so that an operator (the simulator's patrol, hil_sim.episode.patrol) knows when to send the next.

The vpp partition needs a contact-tolerance backend it can build outside the simulator
(vpp.backend kind openai-compatible); the sim-oracle backend exists only inside the lockstep
simulator's process, so `dct run` refuses it. In the real-time HIL `dct hil serve` serves the
oracle over HTTP (hil_sim.vlm.service) and `dct hil run --realtime` gives this process a config
whose backend is openai-compatible at that server: the same client as on the robot.
"""
from __future__ import annotations

import json
import os
import signal
import sys
import threading
import time

import numpy as np

from runtime.app.run_inputs import Loaded, RunInputError, RunOptions, load_inputs
from runtime.loop.clocks import EpochMonotonicClock


class _StoppedBeforeStart(Exception):
    """SIGINT/SIGTERM before the base was enabled (waiting for a goal, or during start-up): exit 0."""


def _percentiles(values_s: np.ndarray) -> dict:
    ms = np.asarray(values_s, dtype=np.float64) * 1e3
    if not len(ms):
        return {"count": 0, "p50": None, "p99": None, "max": None}
    return {"count": int(len(ms)), "p50": float(np.percentile(ms, 50)), "p99": float(np.percentile(ms, 99)),
            "max": float(ms.max())}


def _open_outputs(opts: RunOptions):
    """The --json path checked and the recorder opened (RunInputError before anything moves)."""
    if opts.json_path is not None:
        from calibration.outputs import OutputPathError, check_output_path

        try:
            check_output_path(opts.json_path, what="--json", overwrite=opts.force)
        except OutputPathError as exc:
            raise RunInputError(str(exc)) from None
    if opts.record_path is None:
        return None
    from runtime.io.recording import RecordingError, RunRecorder

    try:
        return RunRecorder(opts.record_path, force=opts.force,
                           split_every_s=opts.record_part_min * 60.0 if opts.record_part_min > 0 else None)
    except RecordingError as exc:
        raise RunInputError(str(exc)) from None


def _wait_for_goal(opts: RunOptions, ros, receiver, notifier, stop, echo) -> tuple[float, float, float]:
    """--goal, or the first PoseStamped in the odometry frame on the goal topic."""
    if opts.goal is not None:
        return opts.goal
    topic = ros.inputs.goal.topic if ros.inputs.goal else None
    echo(f"dct run: waiting for a goal on {topic or '(no goal topic)'}")
    t_end = None if opts.goal_wait_s is None else time.monotonic() + opts.goal_wait_s
    while not stop.is_set() and (t_end is None or time.monotonic() < t_end):
        for refused in receiver.take_goal_rejections():  # malformed, or outside the goal workspace
            echo(f"dct run: goal refused: {refused}")
        g = receiver.take_goal()
        if g is not None and g.frame_id not in ("", ros.outputs.odom_frame):
            echo(f"dct run: goal in frame {g.frame_id!r} ignored: goals are taken in the odometry frame "
                 f"({ros.outputs.odom_frame!r}); there is no map frame yet")
        elif g is not None:
            return (g.pose.x_m, g.pose.y_m, g.pose.yaw_rad)
        else:
            notifier.watchdog()
            stop.wait(0.05)
    if stop.is_set():
        raise _StoppedBeforeStart
    raise RunInputError("no goal: give --goal X Y YAW or publish a geometry_msgs/PoseStamped on "
                        f"{topic or 'the goal topic'}")


def _load_resume(opts: RunOptions, echo):
    """The saved state of `--resume-file` (runtime.app.resume), said in one line; None without it."""
    if opts.resume_path is None:
        return None
    from runtime.app.resume import load_resume

    folder = opts.resume_path.resolve().parent
    if not folder.is_dir():
        raise RunInputError(f"--resume-file {opts.resume_path}: the folder {folder} does not exist")
    resume = load_resume(opts.resume_path, opts.resume_max_age_s)
    echo(f"dct run: {resume.line()}")
    return resume


def run_controller(opts: RunOptions, loaded: Loaded | None = None, stop: threading.Event | None = None,
                   echo=lambda s: print(s, file=sys.stderr, flush=True)) -> dict:
    """Run the controller process until `stop` is set (SIGINT/SIGTERM set it); returns the summary
    (also written to opts.json_path). Raises RunInputError before anything moves."""
    from firmware_bridge.buses import BusOpenError, open_bus
    from runtime.app.deploy.sd_notify import SystemdNotifier
    from runtime.io.ros.publisher import RosPublisher
    from runtime.io.ros.receiver import RosSensorReceiver
    from runtime.io.sensor_inbox import SensorInbox

    loaded = loaded or load_inputs(opts)
    stop = stop or threading.Event()
    if loaded.config.realtime.malloc_arena_max is not None:  # before any of its threads allocate
        from runtime.loop.heap import limit_arenas

        limit_arenas(loaded.config.realtime.malloc_arena_max)  # said on the real-time line
    recorder = _open_outputs(opts)
    try:
        bus = open_bus(loaded.bus_config)
    except BusOpenError as exc:
        if recorder is not None:
            recorder.close()
        raise RunInputError(f"{opts.config_path or 'the shipped controller config'}: can_bus: {exc}") from None
    ros = loaded.config.ros
    # One loop clock for the whole process: the recorder stamps the raw sensor samples with it as
    # the loop stamps its ticks (a replay compares the two); the inbox puts the sensors' stamps
    # back onto it when the system clock is stepped.
    clock = EpochMonotonicClock()
    inbox = SensorInbox(stamp_clock=clock)
    # systemd (the deploy bundle's unit: Type=notify, WatchdogSec): ready once inputs are up, a
    # watchdog ping every tick and while waiting for a goal; a no-op outside systemd.
    notifier = SystemdNotifier()
    receiver = publisher = transport = None
    summary: dict = {"pid": None}
    try:
        transport = _open_transport(ros, echo)
        receiver = RosSensorReceiver(ros.inputs, inbox, transport, camera_K=loaded.camera_K,
                                     camera_distortion=loaded.camera_dist,
                                     tap=recorder.sensor_tap(clock.now) if recorder is not None else None)
        publisher = RosPublisher(transport, ros.outputs, static_transforms=sensor_mounts(loaded),
                                 zones=safety_zones(loaded.robot, loaded.config.safety_supervisor))
        _say_routes(transport, echo)
        receiver.start()
        notifier.ready()
        resume = _load_resume(opts, echo)
        if opts.goal is None and resume is not None and resume.state is not None and resume.state.goal is not None \
                and not resume.state.goal_reached:
            goal = resume.state.goal
            echo(f"dct run: driving on to the saved goal {goal[0]:.3f} {goal[1]:.3f} {goal[2]:.3f} (odom frame)")
        else:
            goal = _wait_for_goal(opts, ros, receiver, notifier, stop, echo)
        summary = _drive(opts, loaded, goal, (bus, inbox, receiver, publisher, recorder, notifier, clock), stop, echo,
                         resume)
    except _StoppedBeforeStart:
        echo("dct run: stopped before the start (waiting for a goal, or during the start-up work); the base was never enabled")
        summary = {"state": "NOT_STARTED"}
    finally:
        _shut_down(summary, (receiver, publisher, transport), recorder, bus, notifier)
    summary["pid"] = os.getpid()
    if opts.json_path is not None:
        from calibration.outputs import atomic_write_json

        atomic_write_json(opts.json_path, summary)
    return summary


def sensor_mounts(loaded: Loaded) -> list:
    """base_link -> lidar and -> camera as the stages place them (the calibration's mounts where it
    has them), named as the config's ros.outputs frames: /tf_static and the recording's."""
    from runtime.io.ros.outbound import robot_sensor_mounts

    out = loaded.config.ros.outputs
    return robot_sensor_mounts(loaded.sensor_calibration, base_frame=out.base_frame, lidar_frame=out.lidar_frame,
                               camera_frame=out.camera_frame)


def safety_zones(robot, supervisor) -> tuple:
    """(footprint, stop zone) polygons in base_link for the safety markers: the footprint, and the
    footprint grown by the supervisor's stop distance (a point inside it stops the robot)."""
    import numpy as np

    footprint = np.asarray(robot.footprint.vertices(), dtype=float)
    return footprint, footprint + np.sign(footprint) * float(supervisor.stop_distance_m)


def _open_transport(ros, echo):
    """The ROS 2 middleware's node (runtime.io.ros.transport); RunInputError when it cannot run."""
    from runtime.io.ros.transport import MiddlewareError, effective_discovery, open_transport

    try:
        transport = open_transport(ros.transport_options())
    except MiddlewareError as exc:
        raise RunInputError(f"ros.middleware: {exc}") from None
    reach, why = effective_discovery(ros.discovery)
    echo(f"dct run: ROS 2 via {transport.name}, DDS domain {transport.domain_id}, discovery "
         f"{'this machine only' if reach == 'localhost' else 'the network: any host there can send goals'} ({why})")
    return transport


def _say_routes(transport, echo) -> None:
    """One line per topic carried by a path other than the chosen middleware (which reads the lidar)."""
    for r in transport.routes():
        if r.via != transport.name:
            echo(f"dct run: {r.topic} ({r.type_name}) {'read' if r.direction == 'in' else 'published'} through "
                 f"{r.via}: {r.note}")


def _drive(opts: RunOptions, loaded: Loaded, goal, io, stop: threading.Event, echo, resume=None) -> dict:
    """Assemble the controller on the bus, run it until `stop`, return the summary. resume: the
    `--resume-file` state (runtime.app.resume.Resume), None without the option."""
    from runtime.app.run_observer import RunObserver
    from runtime.common.geometry import Pose2D
    from runtime.controller.builder import RobotSetup, Wiring, assemble
    from runtime.loop import heap
    from runtime.loop.realtime_setup import apply_switch_interval, request_realtime_from_config

    bus, inbox, receiver, publisher, recorder, notifier, clock = io
    config = loaded.config
    driver_bus = recorder.wrap_bus(bus, clock.now) if recorder is not None else bus
    parts = assemble(RobotSetup(loaded.robot, config, loaded.wheel_calibration, loaded.sensor_calibration),
                     Wiring(driver_bus, clock, Pose2D(*goal), inbox if config.uses_lidar else None, lockstep=False,
                            start_odometry=True))
    record_hook = None
    if recorder is not None:
        record_hook = recorder.attach(parts.controller, config, {"clock": "wall", "goal": json.dumps(list(goal))},
                                      static_transforms=sensor_mounts(loaded))
    observer = RunObserver(parts, config.ros, publisher, receiver, notifier, echo, record_hook)
    parts.loop.after_tick = observer
    writer = _start_resume(opts, resume, parts.controller.odometry)
    observer.resume_writer = writer
    if stop.is_set():  # SIGINT/SIGTERM during the start-up work: the base is never enabled
        parts.controller.partition.close()
        parts.controller.odometry.close()
        raise _StoppedBeforeStart
    echo(f"dct run: goal {goal[0]:.3f} {goal[1]:.3f} {goal[2]:.3f} (odom frame); bus "
         f"{loaded.bus_config.interface}:{loaded.bus_config.channel}; DDS domain {config.ros.inputs.domain_id}; "
         f"planner {config.preset}")
    # SCHED_FIFO and CPU pinning for this (the loop's) thread, when allowed; said at start.
    if opts.normal_priority:
        scheduling = ("real-time: not asked for (--normal-priority): the loop thread stays SCHED_OTHER; GIL switch "
                      f"interval {apply_switch_interval(config.realtime):g} ms")
    else:
        scheduling = request_realtime_from_config(config.realtime).summary()
    scheduling += (f"; malloc arenas at most {heap.arena_limit}" if heap.arena_limit is not None
                   else "; malloc arenas as glibc's default")
    echo(f"dct run: {scheduling}")
    wall0 = time.monotonic()
    try:
        parts.run(stop.is_set)
    finally:
        if writer is not None:
            writer.close()
    summary = _summary(parts, observer, inbox, receiver, goal, time.monotonic() - wall0, scheduling)
    if resume is not None:
        summary["resume"] = {"saved_state": resume.state is not None, "why": resume.why,
                             "outcome": parts.controller.odometry.resume_outcome,
                             "writes": writer.writes, "write_error": writer.error}
    return summary


def _start_resume(opts: RunOptions, resume, odometry):
    """Hand the odometry the saved frame to continue, start the writer; None without --resume-file."""
    if resume is None:
        return None
    from runtime.app.resume import ResumeWriter
    from runtime.common.geometry import Pose2D
    from runtime.odometry.wheels import MAX_WHEEL_SPEED_MPS, WHEEL_STEP_MARGIN_M

    if resume.state is not None:
        # the most the base could have driven since the state was saved (its first reading comes
        # within a few ticks of now: two seconds of margin)
        since_s = max(0.0, time.time() - resume.state.written_at_s) + 2.0
        odometry.resume_from(Pose2D(*resume.state.pose), resume.state.wheels_m,
                             MAX_WHEEL_SPEED_MPS * since_s + WHEEL_STEP_MARGIN_M)
    writer = ResumeWriter(opts.resume_path)
    writer.start()
    return writer


def _summary(parts, observer, inbox, receiver, goal, wall: float, scheduling: str) -> dict:
    controller, telemetry, loop = parts.controller, parts.telemetry, parts.loop
    records = telemetry.snapshot()
    latency = observer.latency.values()
    report = controller.describe()
    return {
        "pid": None,
        "state": controller.state.name,
        "goal_odom": list(goal),
        "goal_reached_at_s": controller.goal_reached_at_s,
        "activated_at_s": controller._activated_at_s,
        "wall_time_s": wall,
        "cpu_time_s": time.process_time(),  # this process (the ICP worker's is its own)
        "controller": report,
        # {reason, since_s, configured} once a calibration mismatch made the partition all-fixed
        "partition_fallback": report.get("partition_fallback"),
        "events": controller.events.to_list(t0_s=controller.switched_on_at_s),
        "stop_reason": controller.stop_reason,
        "telemetry": telemetry.summary(),
        "realtime": {
            "tick_ms": _percentiles(records["tick_s"]),
            "sensor_to_command_ms": _percentiles(latency),
            "deadline_misses": int(telemetry.deadline_misses),
            "wall_deadline_misses": int(telemetry.wall_deadline_misses),
            "ticks": int(telemetry.ticks),
            "ticks_skipped": int(telemetry.ticks_skipped),
            "lateness_ms": _percentiles(records["lateness_s"]),
            "scheduling": scheduling,  # what the loop thread asked the OS for and got
        },
        #: Every frame's sensor-to-command latency in ms, in order (for a closer look at the tail).
        "sensor_to_command_values_ms": [round(float(v) * 1e3, 3) for v in latency],
        "sensor_frames": dict(inbox.accepted),
        # steps of the system clock seen (the stamps were moved back onto the loop's clock)
        "clock_steps": {"count": inbox.clock_steps, "in_force_s": round(inbox.clock_step_s, 6),
                        "last": inbox.last_clock_step},
        "sensor_errors": {**dict(sorted(inbox.error_counts.items())),
                          **{f"ros.{k}": v for k, v in receiver.error_counts.items()}},
        "ros_received": dict(receiver.received),
        "ros": {"middleware": receiver.transport.name, "domain_id": receiver.transport.domain_id,
                "discovery": receiver.transport.discovery,
                "routes": [{"direction": r.direction, "topic": r.topic, "type": r.type_name, "via": r.via,
                            "qos": r.qos.describe()} for r in receiver.transport.routes()],
                "qos_mismatches": dict(receiver.transport.qos_mismatches),
                "executor_errors": getattr(receiver.transport, "spin_errors", 0)},
        "goals_ignored": observer.goals_ignored,
        "keepalives_sent": loop.keepalives_sent,
        "heap_trim": loop.heap.summary(),
    }


def _shut_down(summary: dict, ros_parts, recorder, bus, notifier) -> None:
    """Each step on its own: one that fails (a receiver thread that will not stop) must not skip
    the others (the recording's rename, the bus) nor hide the error that brought us here."""
    notifier.stopping()
    cleanup_errors = []
    receiver, publisher, transport = ros_parts
    for name, part, step in (("receiver", receiver, "stop"), ("publisher", publisher, "close"),
                             ("ros", transport, "close")):
        if part is None:  # (DDS did not come up)
            continue
        try:
            getattr(part, step)()
        except Exception as exc:  # noqa: BLE001 - recorded in the summary
            cleanup_errors.append(f"{name}: {type(exc).__name__}: {exc}")
    if summary.get("state") is not None and publisher is not None:
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


__all__ = ["install_stop_signals", "run_controller", "summary_line", "load_inputs", "RunOptions", "RunInputError"]
