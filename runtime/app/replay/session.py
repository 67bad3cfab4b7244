"""One replay: the controller assembled as `dct run` assembles it, fed from a recording, open loop.

    recording -> ReplayTransport -> RosSensorReceiver (decode, validate) -> SensorInbox -> the tick
    recording -> ReplayCanBus (the base's frames) -> AgileX driver -> the tick
    ReplayClock (the recording's ticks) -> FixedRateLoop -> the tick -> commands -> ReplayCanBus
    the tick -> after_tick -> RunRecorder (replay.mcap), the odometry trajectory

Open loop: the commands go nowhere; the base's feedback is what the robot reported live. The
controller is built with lockstep timing (iteration caps, work beside the tick waited for), and
ICP registers the frames the live run registered, delivered at the live ticks
(runtime.app.replay.icp), the VPP's backend runner hands over the live runner's answers at the live
ticks (runtime.app.replay.vlm), so the replay's odometry is the live run's and two replays are the same.
A bag of the drivers has no ticks and no base: ticks every period from its first message, every
lidar frame registered with the lockstep latency, and the controller waits for the base it never
hears (its watchdogs say so).
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from pathlib import Path

from runtime.app.replay.source import ReplaySource, Sample


@dataclass
class ReplaySetup:
    """What the replay runs: the source and the controller's inputs (runtime.app.run_inputs.Loaded)."""

    source: ReplaySource
    loaded: object
    goal: tuple[float, float, float] | None  # None: standby (a bag without --goal)
    recording_path: Path  # the replay's own recording (replay.mcap)
    pace: bool = False
    record_part_s: float | None = None  # its parts' length (runtime.io.recording.recorder); None: one file


@dataclass
class ReplayResult:
    poses: list[tuple[float, float, float, float]] = field(default_factory=list)  # (t, x, y, yaw)
    ticks: int = 0
    wall_s: float = 0.0
    samples_fed: int = 0
    samples_missing: int = 0
    can_frames_fed: int = 0
    frames_sent: int = 0
    icp: dict = field(default_factory=dict)
    vlm: dict | None = None
    recording: dict = field(default_factory=dict)
    controller: dict = field(default_factory=dict)
    sensor_errors: dict = field(default_factory=dict)


class _Feeder:
    """Hands the recorded sensor samples to the receiver one at a time, in their order."""

    def __init__(self, samples, transport, receiver) -> None:
        self._it = iter(samples)
        self._next: Sample | None = next(self._it, None)
        self.transport, self.receiver = transport, receiver
        self.fed = 0
        self.missing = 0  # numbers absent from the recording (the recorder dropped them)
        self._last_seq = 0

    def _feed(self, s: Sample) -> None:
        if s.seq > self._last_seq + 1:
            self.missing += s.seq - self._last_seq - 1
        self._last_seq = max(self._last_seq, s.seq)
        self.transport.push(s.topic, s.data)
        self.receiver.poll(0.0)
        self.fed += 1
        self._next = next(self._it, None)

    def through(self, count: int) -> None:
        """Every sample numbered up to `count` (what the live tick had taken in)."""
        while self._next is not None and self._next.seq <= count:
            self._feed(self._next)

    def until(self, t_s: float) -> None:
        """Every sample received by t_s (a bag)."""
        while self._next is not None and self._next.t_s <= t_s:
            self._feed(self._next)


def run_replay(setup: ReplaySetup, echo) -> ReplayResult:
    """Run the controller over the whole recording; the replay's recording is closed at the end."""
    from runtime.app.replay.clock import ReplayClock, grid_plans, recorded_plans
    from runtime.app.replay.inject import ReplayCanBus, ReplayTransport
    from runtime.io.recording import RunRecorder
    from runtime.io.ros.receiver import RosSensorReceiver
    from runtime.io.sensor_inbox import SensorInbox

    src, ld = setup.source, setup.loaded
    inbox, transport, bus = SensorInbox(), ReplayTransport(), ReplayCanBus()
    result = ReplayResult()
    holder: dict = {}
    period = ld.config.loop.period_s
    plans = recorded_plans(src.ticks) if src.ticks else grid_plans(src.first_s, period, src.last_s + 1.0)
    clock = ReplayClock(plans, lambda plan, after: _before_tick(plan, after, holder, result), period, pace=setup.pace)
    recorder = RunRecorder(setup.recording_path, force=True, split_every_s=setup.record_part_s)
    # The replay's recording carries the inputs as the controller took them, as `dct run --record`
    # does: it can itself be replayed (with other settings, or to check that it replays the same).
    receiver = RosSensorReceiver(ld.config.ros.inputs, inbox, transport, camera_K=ld.camera_K,
                                 camera_distortion=ld.camera_dist, tap=recorder.sensor_tap(clock.now))
    holder.update(src=src, bus=bus, feeder=_Feeder(src.samples(), transport, receiver))
    with recorder:
        parts, scripted = _assemble(setup, clock, recorder, (bus, inbox), result.poses)
        controller = holder["controller"] = parts.controller
        if src.ticks:  # what the live driver drained before its first tick (discarded at start-up)
            result.can_frames_fed += _queue_can(holder, src.ticks[0].now_s)
        wall0 = time.perf_counter()
        try:
            parts.run(lambda: clock.done)
        finally:
            bus.shutdown()
        result.wall_s = time.perf_counter() - wall0
    feeder = holder["feeder"]
    result.ticks = clock.ticks
    result.samples_fed, result.samples_missing = feeder.fed, feeder.missing
    result.frames_sent = len(bus.sent)
    result.recording = recorder.summary()
    result.controller = controller.describe()
    result.sensor_errors = {**dict(sorted(inbox.error_counts.items())),
                            **{f"ros.{k}": v for k, v in receiver.error_counts.items()}}
    result.icp = _icp_account(controller.odometry, scripted)
    result.vlm = vlm_account(controller)
    return result


def _before_tick(plan, after, holder: dict, result: ReplayResult) -> None:
    """What the tick must find (samples, CAN frames, a new goal), and the work beside the tick
    due by its time (runtime.app.replay.clock)."""
    from runtime.common.geometry import Pose2D

    controller, feeder = holder["controller"], holder["feeder"]
    if plan.live is not None:
        feeder.through(plan.live.sensor_samples)
        result.can_frames_fed += _queue_can(holder, after.now_s if after is not None else math.inf)
        g = plan.live.goal
        if (g[0], g[1], g[2]) != (controller.goal.x_m, controller.goal.y_m, controller.goal.yaw_rad):
            controller.request_goal(Pose2D(*g), "the recording")
    else:
        feeder.until(plan.now_s)
    controller.odometry.settle(plan.now_s)
    controller.settle(plan.now_s)


def _assemble(setup: ReplaySetup, clock, recorder, io: tuple, poses: list):
    """The controller as `dct run` assembles it (lockstep timing) on io = (the CAN bus, the sensor
    inbox), its ICP scripted, the recorder and the trajectory (each tick's pose appended to `poses`)
    on the loop's after_tick hook. Returns (the assembly, the scripted ICP worker or None)."""
    from runtime.app.replay.inject import ReplayVlm
    from runtime.app.run_process import sensor_mounts
    from runtime.common.geometry import Pose2D
    from runtime.controller.builder import RobotSetup, Wiring, assemble

    ld, config = setup.loaded, setup.loaded.config
    bus, inbox = io
    goal = setup.goal if setup.goal is not None else (0.0, 0.0, 0.0)
    parts = assemble(RobotSetup(ld.robot, config, ld.wheel_calibration, ld.sensor_calibration),
                     Wiring(recorder.wrap_bus(bus, clock.now), clock, Pose2D(*goal),
                            inbox if config.uses_lidar else None, lockstep=True,
                            vlm_backend=ReplayVlm() if config.uses_vlm_backend else None,
                            goal_given=setup.goal is not None))
    controller = parts.controller
    scripted = _script_icp(controller.odometry, setup.source)
    _script_vlm(controller, setup.source)
    info = {"clock": "replay", "replay_of": str(setup.source.path), "goal": list(goal), "standby": setup.goal is None}
    hook = recorder.attach(controller, config, info, static_transforms=sensor_mounts(ld))

    def after_tick(row) -> None:
        hook(row)
        p = controller.snapshot.pose
        poses.append((float(row["scheduled_s"]), p.x_m, p.y_m, p.yaw_rad))
        clock.after_tick()

    parts.loop.after_tick = after_tick
    return parts, scripted


def _queue_can(holder: dict, before_s: float) -> int:
    """Queue the received CAN frames stamped before `before_s` (the next tick's clock)."""
    i = holder.get("can_i", 0)
    n = 0
    rx, bus = holder["src"].can_rx, holder["bus"]
    while i < len(rx) and rx[i][0] < before_s:
        bus.queue(*rx[i])
        i += 1
        n += 1
    holder["can_i"] = i
    return n


def _script_icp(odometry, src: ReplaySource):
    """Start the ICP worker now, with lockstep delivery; for a dct recording, scripted from the
    live run's results (runtime.app.replay.icp). Returns the scripted worker (None: not scripted)."""
    from runtime.app.replay.icp import ScriptedIcpWorker, icp_schedule

    odometry.start()  # activate() finds it started
    if odometry.worker is None or not src.ticks:
        return None
    odometry.worker = ScriptedIcpWorker(odometry.worker, icp_schedule(src.ticks))
    return odometry.worker


def _script_vlm(controller, src: ReplaySource) -> None:
    """The VPP stage's backend runner, for a recording that carries the live runner's answers:
    those answers at the live ticks (runtime.app.replay.vlm). Else the ReplayVlm backend stays:
    every request fails at once."""
    from runtime.app.replay.vlm import ScriptedVlmRunner

    vpp = controller.partition.vpp
    if vpp is None or src.vlm_answers is None:
        return
    runner = ScriptedVlmRunner(src.vlm_answers)
    runner.post = vpp.runner.post  # the stage's Phase II preparation, as live
    vpp.runner = runner


def vlm_account(controller) -> dict | None:
    """What the replay's VLM runner did (None without the VPP)."""
    vpp = controller.partition.vpp
    if vpp is None:
        return None
    from runtime.app.replay.vlm import ScriptedVlmRunner

    runner = vpp.runner
    scripted = isinstance(runner, ScriptedVlmRunner)
    return {"scripted": scripted, **runner.counters(), **({"not_delivered": runner.left} if scripted else {})}


def _icp_account(odometry, scripted) -> dict:
    d = odometry.describe()
    return {"frames_submitted": d["icp_frames_submitted"], "results": d["icp_results"], "fused": d["icp_fused"],
            "refused": d["icp_refused"],
            # frames the live run did not register (scripted), or dropped by the worker (a bag: none)
            "not_registered": d["icp_dropped"],
            "out_of_step": scripted.mismatched if scripted is not None else 0}
