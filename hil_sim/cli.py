"""`dct hil`: run scenarios in the simulator (lockstep, or real time in two processes), serve one.

The benchmarks (`dct bench`) are in hil_sim/bench/cli.py.
"""
from __future__ import annotations

import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import click

from hil_sim.episode.cli_checks import InputError, check_scenario_and_output
from runtime.config import presets


@click.group(name="hil")
def hil_group() -> None:
    """Hardware-in-the-loop simulation: scenarios, episodes, metrics."""


@hil_group.command("list")
def list_command() -> None:
    """List the scenario library."""
    from hil_sim.world.scenario import list_scenarios, load_scenario

    for name in list_scenarios():
        sc = load_scenario(name)
        click.echo(f"{name:12s} {sc.description or ''}".rstrip())
    from hil_sim.world.scene_generators import GENERATORS, list_generators

    click.echo("generated from --seed (hil_sim/world/scene_generators.py):")
    for name in list_generators():
        click.echo(f"{name:26s} {GENERATORS[name].summary}")


@hil_group.command("run")
@click.argument("scenario")
@click.option("--json", "json_path", type=click.Path(dir_okay=False, path_type=Path),
              help="Write the episode metrics here (checked before the run, written atomically after it).")
@click.option("--seed", default=0, show_default=True, type=click.IntRange(0, 2**32 - 1),
              help="Seed for every random source (deterministic).")
@click.option("--config", "config_path", type=click.Path(exists=True, dir_okay=False, path_type=Path), help="Controller config YAML.")
@click.option("--robot", "robot_path", type=click.Path(exists=True, dir_okay=False, path_type=Path), help="Robot description YAML.")
@click.option("--calibration", "calibration_path", type=click.Path(exists=True, dir_okay=False, path_type=Path),
              help="The robot's calibration file: its wheel_odometry section (dct calibrate wheels) sets the "
                   "odometry's effective track and wheel scale.")
@click.option(
    "--planner",
    type=click.Choice(list(presets.PRESETS)),
    help="Override the config's planner mode (default dct: the MPC on the VLM partition's P_fix only, with the "
         "config's backend (the sim-oracle) and a 2 Hz camera; all-fixed: every lidar point fixed, the NeuPAN-like "
         "baseline; grid-astar: inflated occupancy grid + A* + pure pursuit, the Ellis22-like baseline; "
         "pure-pursuit: the blind placeholder).",
)
@click.option(
    "--fault", "fault_texts", multiple=True, metavar="NAME:START_S[:DURATION_S]",
    help="Inject a fault (repeatable): one of docs/faults.md (lidar-blind, imu-stuck, drop-0x311, 0x221-garbage, "
         "cmd-off, estop, ...). Times in simulated seconds from the start (with --realtime: from when the "
         "controller enabled the base); no duration = to the end.",
)
@click.option("--record", "record_path", type=click.Path(dir_okay=False, path_type=Path),
              help="Record the run to this MCAP file (ticks, poses, CAN frames, P_fix, plan); "
                   "`dct report latency` reads it. Written under a temporary name, renamed at the end.")
@click.option("--force", is_flag=True, help="Overwrite an existing --record file.")
@click.option("--realtime", is_flag=True,
              help="Two processes on the wall clock, as on the robot: `dct hil serve` (simulator, CAN over "
                   "udp_multicast, sensors over DDS) and `dct run` (the controller). The JSON adds `realtime` "
                   "(tick and sensor-to-command latency, deadline misses, pids). Not deterministic. With --record "
                   "the controller process records the run.")
@click.option("--duration", "duration_s", type=click.FloatRange(0.0, 86400.0, min_open=True), metavar="SECONDS",
              help="A patrol scenario (goals:): patrol for this long instead of the file's patrol (loops or "
                   "duration_s); the time limit becomes this duration.")
@click.option("--middleware", type=click.Choice(["auto", "rclpy", "cyclonedds"]),
              help="With --realtime: the ROS 2 middleware of both processes (default: the config's ros.middleware).")
@click.option("--robot-variant", "robot_variant", metavar="SPEC",
              help="Simulate the robot as built, not as described: nominal, a seed (departures drawn within "
                   "build tolerances), or a variant YAML file (docs/simulator.md#robot-variants); overrides the "
                   "scenario's robot_variant. The controller is not told (give it --calibration).")
@click.option("--normal-priority", is_flag=True,
              help="With --realtime: the controller's loop thread does not ask for SCHED_FIFO (`dct run "
                   "--normal-priority`); by default it asks, as on the robot, and runs at normal priority where "
                   "that is refused. The JSON's realtime.scheduling says what it got.")
def run_command(*, scenario: str, json_path: Path | None, seed: int, config_path: Path | None,
                robot_path: Path | None, planner: str | None, fault_texts: tuple[str, ...],
                calibration_path: Path | None = None, record_path: Path | None = None, force: bool = False,
                realtime: bool = False, duration_s: float | None = None, middleware: str | None = None,
                robot_variant: str | None = None, normal_priority: bool = False) -> None:
    """Run one lockstep episode of SCENARIO (a library name such as case1, or a YAML path).

    The metrics JSON is deterministic (same inputs and seed, same file, under any machine load);
    the wall-clock timing the computer spent is in its `wall_clock` section, a measurement.
    Exit status 0 on success, 1 when the episode failed (the JSON says why: failure_reason), 2 on
    bad input (nothing is run, nothing is written).
    """
    from calibration.outputs import atomic_write_json

    run = _load_run(scenario=scenario, seed=seed, config_path=config_path, robot_path=robot_path,
                    calibration_path=calibration_path, planner=planner, fault_texts=fault_texts,
                    duration_s=duration_s, json_path=json_path, record_path=record_path, force=force,
                    robot_variant=robot_variant)
    for w in run.warnings:
        click.echo(f"warning: {w}", err=True)
    if realtime:
        _run_realtime(run.scenario.name, scenario=scenario, seed=seed, json_path=json_path, config_path=config_path,
                      robot_path=robot_path, calibration_path=calibration_path, planner=planner,
                      fault_texts=fault_texts, record_path=record_path, force=force, duration_s=duration_s,
                      middleware=middleware, robot_variant=robot_variant, normal_priority=normal_priority)
        return
    if middleware is not None:
        raise InputError("--middleware applies to --realtime runs (lockstep has no ROS 2 in between)")
    if normal_priority:
        raise InputError("--normal-priority applies to --realtime runs (a lockstep tick is judged on simulated time)")
    from hil_sim.episode.faults import FAULTS

    for f in run.faults:
        if FAULTS[f.name].realtime_only:
            raise InputError(f"--fault {f.name}: real time only (add --realtime): a lockstep episode has the "
                             "controller in the simulator's process")
    result = _run_lockstep(run, seed, record_path, force)
    m = result.metrics
    if json_path is not None:
        payload = dict(m)
        payload["wall_clock"] = wall_clock_report(result)
        atomic_write_json(json_path, payload)
    click.echo(summary_line(run.scenario.name, m, result.realtime_factor))
    from runtime.odometry.icp_settings import gate_lines

    for line in gate_lines(m.get("icp_range_gate")):
        click.echo(line, err=True)
    if not m["success"]:
        sys.exit(1)


@dataclass(frozen=True)
class _RunInputs:
    """What `dct hil run` loaded and checked before its episode."""

    scenario: Any
    robot: Any
    config: Any
    faults: list
    wheel_calibration: tuple[float, float] | None
    sensor_calibration: Any  # calibration.sensor_calibration.SensorCalibration
    warnings: list[str]
    #: The simulated robot as built (hil_sim.world.robot_variant.RobotVariant), or None.
    variant: Any = None


def _load_run(*, scenario: str, seed: int, config_path: Path | None, robot_path: Path | None,
              calibration_path: Path | None, planner: str | None, fault_texts: tuple[str, ...],
              duration_s: float | None, json_path: Path | None, record_path: Path | None,
              force: bool, robot_variant: str | None = None) -> _RunInputs:
    """Load and check every input of `dct hil run`: InputError (one line, exit 2) on the first problem."""
    from calibration.errors import ConfigFileError
    from calibration.outputs import OutputPathError
    from calibration.robot_description import load_robot_description
    from hil_sim.episode.faults import FaultSpec, FaultSpecError
    from hil_sim.episode.patrol import PatrolError, with_duration
    from hil_sim.world.scenario import load_scenario
    from hil_sim.world.scenario_checks import check_scenario_against_robot
    from runtime.config import check_against_robot, load_controller_config

    try:
        faults = [FaultSpec.parse(t) for t in fault_texts]
        sc = load_scenario(scenario, seed=seed)  # a generated scene (dct_f2m2) is drawn from the seed
        sc = with_duration(sc, duration_s)
        robot = load_robot_description(robot_path)
        config = load_controller_config(config_path)
        if planner is not None:
            config = config.with_planner_mode(planner)
        try:
            check_against_robot(config, robot)
        except ValueError as exc:
            raise InputError(f"{config_path or 'the shipped controller config'}: {exc}") from None
        wheel_calibration, sensor_calibration = _load_calibration(calibration_path, robot, robot_path)
        variant = _load_variant(robot_variant, sc, robot)
        warnings = check_scenario_against_robot(
            sc, robot, ground_clearance_m=config.planner.obstacle_points.ground_clearance_m
        )
        inputs = [p for p in (config_path, robot_path, calibration_path, Path(scenario))
                  if p is not None and Path(p).is_file()]
        _check_outputs(json_path, record_path, force, inputs)
        if config.uses_distance_net:  # the distance net must fit this robot (checked again at start-up)
            _check_distance_net(config, robot)
    except (ConfigFileError, FaultSpecError, OutputPathError, PatrolError) as exc:
        raise InputError(str(exc)) from exc
    warnings += [f"--fault {f}: starts at or after the time limit ({sc.time_limit_s:g} s); it will never act"
                 for f in faults if f.start_s >= sc.time_limit_s]
    return _RunInputs(sc, robot, config, faults, wheel_calibration, sensor_calibration, warnings, variant)


def _load_variant(spec: str | None, scenario, robot):
    """--robot-variant (else the scenario's robot_variant) resolved for the robot, said on stderr; None
    without either. A bad SPEC is a ConfigFileError (hil_sim.world.robot_variant.VariantError)."""
    from hil_sim.world.robot_variant import resolve_variant

    spec = spec if spec is not None else scenario.robot_variant
    if spec is None:
        return None
    variant = resolve_variant(spec, robot)
    click.echo(variant_line(variant), err=True)
    return variant


def variant_line(variant) -> str:
    """One line about a robot variant: its camera and mount departures."""
    if variant.is_nominal:
        return f"robot variant {variant.label}: the robot as described"
    cam, d = variant.true_camera(), variant.departures
    return (f"robot variant {variant.label}: camera fx {cam.fx:.2f} fy {cam.fy:.2f} cx {cam.cx:.2f} cy {cam.cy:.2f} "
            f"distortion [{', '.join(f'{k:.4g}' for k in cam.dist)}]; lidar mount moved "
            f"{[round(x * 1000, 1) for x in d.lidar_mount.dxyz_m]} mm, {[round(a, 2) for a in d.lidar_mount.drpy_deg]} "
            f"deg; camera mount moved {[round(x * 1000, 1) for x in d.camera_mount.dxyz_m]} mm, "
            f"{[round(a, 2) for a in d.camera_mount.drpy_deg]} deg")


def _load_calibration(calibration_path: Path | None, robot, robot_path: Path | None = None
                      ) -> tuple[tuple[float, float] | None, Any]:
    """--calibration: (effective track, wheel scale) of its wheel odometry and the sensors as it
    calibrates them (calibration.sensor_calibration), said on stderr; (None, the description's
    nominal sensors) without the option."""
    from calibration.sensor_calibration import sensor_calibration

    source = f"robot description {robot_path}" if robot_path is not None else None
    if calibration_path is None:
        return None, sensor_calibration(robot, robot_source=source)
    from calibration.calibration_file import load_calibration
    from calibration.wheel_odometry import wheel_params

    cal = load_calibration(calibration_path)
    sensors = sensor_calibration(robot, cal, calibration_path, robot_source=source)
    params = wheel_params(robot, cal)
    click.echo(f"wheel odometry: effective track {params.effective_track_m:.4f} m, scale "
               f"{params.wheel_scale:.4f} ({params.source})", err=True)
    click.echo(f"sensors: camera from {sensors.sources['camera']}; lidar mount from {sensors.sources['lidar_mount']}; "
               f"camera mount from {sensors.sources['camera_mount']}", err=True)
    return (params.effective_track_m, params.wheel_scale), sensors


def _check_outputs(json_path: Path | None, record_path: Path | None, force: bool, inputs: list) -> None:
    """--json and --record may be written (OutputPathError), and are two files (InputError)."""
    from calibration.outputs import check_output_path

    if json_path is not None:
        check_output_path(json_path, what="--json", inputs=inputs)
    if record_path is not None:
        check_output_path(record_path, what="--record", inputs=inputs, overwrite=force)
        if json_path is not None and record_path.resolve() == json_path.resolve():
            raise InputError(f"--record {record_path} is also the --json file; write them to two files")


def _check_distance_net(config, robot) -> None:
    """The config's distance net loads for this robot, else InputError."""
    from models.distance_net import DistanceNet
    from models.errors import DistanceNetError

    try:
        DistanceNet.load(config.planner.distance_net_path, robot=robot)
    except DistanceNetError as exc:
        raise InputError(str(exc)) from exc


def _run_lockstep(run: _RunInputs, seed: int, record_path: Path | None, force: bool):
    """The lockstep episode (recorded to --record when given); its EpisodeResult."""
    from calibration.errors import ConfigFileError
    from hil_sim.episode.lockstep import run_episode

    recorder = None
    if record_path is not None:
        from runtime.app.run_inputs import DEFAULT_RECORD_PART_MIN
        from runtime.io.recording import RecordingError, RunRecorder

        try:
            recorder = RunRecorder(record_path, force=force, split_every_s=DEFAULT_RECORD_PART_MIN * 60.0)
        except RecordingError as exc:
            raise InputError(str(exc)) from exc
    try:
        try:
            result = run_episode(run.scenario, robot=run.robot, config=run.config, seed=seed, faults=run.faults,
                                 wheel_calibration=run.wheel_calibration, recorder=recorder,
                                 sensor_calibration=run.sensor_calibration, robot_variant=run.variant)
        except BaseException as exc:  # the log of a failed run is kept (it says how it ended)
            if recorder is not None:
                recorder.note_run_end(exc)
                close_recording(recorder)
            raise
        if recorder is not None:
            close_recording(recorder)
    except ConfigFileError as exc:  # a scenario the robot cannot start in, a bad model file
        raise InputError(str(exc)) from exc
    return result


def _run_realtime(name: str, *, scenario: str, seed: int, json_path: Path | None, config_path: Path | None,
                  robot_path: Path | None, calibration_path: Path | None, planner: str | None,
                  fault_texts: tuple[str, ...], record_path: Path | None, force: bool = False,
                  duration_s: float | None = None, middleware: str | None = None,
                  robot_variant: str | None = None, normal_priority: bool = False) -> None:
    """`dct hil run --realtime` of scenario `name`: hil_sim.episode.realtime (two processes); --record: the
    controller's."""
    from calibration.outputs import atomic_write_json
    from hil_sim.episode.realtime import run_realtime_episode

    if planner is not None and presets.blind(planner):
        raise InputError(f"--planner {planner} is not supported with --realtime: `dct run` refuses a planner blind to "
                         "obstacles")
    try:
        m = run_realtime_episode(scenario, seed, config_path, robot_path, calibration_path,
                                 echo=lambda s: click.echo(s, err=True), planner=planner, duration_s=duration_s,
                                 record_path=record_path.resolve() if record_path is not None else None,
                                 force=force, middleware=middleware, robot_variant=robot_variant,
                                 faults=tuple(fault_texts), normal_priority=normal_priority)
    except RuntimeError as exc:
        raise click.ClickException(str(exc)) from None
    if json_path is not None:
        atomic_write_json(json_path, m)
    click.echo(realtime_line(name, m))
    if not m["success"]:
        sys.exit(1)


def realtime_line(name: str, m: dict) -> str:
    """summary_line plus the real-time figures."""
    rt = m["realtime"]

    def f(d):
        return "/".join("-" if d[k] is None else f"{d[k]:.1f}" for k in ("p50", "p99", "max"))

    line = summary_line(name, m, 1.0).rsplit(" realtime=", 1)[0]
    return (f"{line} realtime: tick_ms(p50/p99/max)={f(rt['tick_ms'])} "
            f"sensor_to_command_ms={f(rt['sensor_to_command_ms'])} middleware={rt.get('middleware')} "
            f"pids={rt['pids']['simulator']},{rt['pids']['controller']}")


@hil_group.command("serve")
@click.argument("scenario")
@click.option("--seed", default=0, show_default=True, type=click.IntRange(0, 2**32 - 1))
@click.option("--json", "json_path", type=click.Path(dir_okay=False, path_type=Path),
              help="Write the episode metrics here when it ends (goal, time limit, SIGINT/SIGTERM).")
@click.option("--config", "config_path", type=click.Path(exists=True, dir_okay=False, path_type=Path),
              help="Controller config YAML: its ros.inputs topics are what the simulator publishes.")
@click.option("--robot", "robot_path", type=click.Path(exists=True, dir_okay=False, path_type=Path),
              help="Robot description YAML.")
@click.option("--domain-id", type=click.IntRange(0, 232), help="DDS domain (default: the config's).")
@click.option("--middleware", type=click.Choice(["auto", "rclpy", "cyclonedds"]),
              help="ROS 2 middleware of the simulator (default: the config's ros.middleware).")
@click.option("--discovery", type=click.Choice(["localhost", "subnet"]), default="localhost", show_default=True,
              help="Who hears the simulated robot's topics: processes on this machine, or the network.")
@click.option("--can-channel", help="CAN udp_multicast group (default: python-can's).")
@click.option("--can-port", type=click.IntRange(1, 65535), help="CAN udp_multicast port.")
@click.option("--camera-rate", "camera_rate_hz", default=0.0, show_default=True, type=click.FloatRange(0.0, 30.0),
              help="Camera images per second (0: no camera; rendering is costly).")
@click.option("--connect-timeout", "connect_timeout_s", default=120.0, show_default=True,
              type=click.FloatRange(1.0, 3600.0), help="End the episode if no controller enables the base by then.")
@click.option("--duration", "duration_s", type=click.FloatRange(0.0, 86400.0, min_open=True), metavar="SECONDS",
              help="A patrol scenario (goals:): patrol for this long instead of the file's patrol.")
@click.option("--fault", "fault_texts", multiple=True, metavar="NAME:START_S[:DURATION_S]",
              help="Inject a fault (repeatable; docs/faults.md), times from when the controller enabled the base.")
@click.option("--force", is_flag=True, help="Overwrite an existing --json file.")
@click.option("--oracle/--no-oracle", "oracle", default=None,
              help="Serve the sim-oracle as a VLM over HTTP (chat completions + grounding /detect) with a 2 Hz camera "
                   "(default: when the config's planner.mode is dct).")
@click.option("--oracle-precision", type=click.FloatRange(0.0, 1.0, min_open=True),
              help="The oracle's precision (default: the config's vpp.backend sim-oracle section, else 1).")
@click.option("--oracle-recall", type=click.FloatRange(0.0, 1.0), help="The oracle's recall (default: the config's, else 1).")
@click.option("--oracle-latency", "oracle_latency_s", type=click.FloatRange(0.0, 120.0),
              help="Seconds before each answer (default: the config's, 1.5).")
@click.option("--oracle-failure-rate", type=click.FloatRange(0.0, 1.0),
              help="Chance an answer fails (HTTP 503) (default: the config's, 0).")
@click.option("--robot-variant", "robot_variant", metavar="SPEC",
              help="Simulate the robot as built, not as described: nominal, a seed (departures drawn within "
                   "build tolerances), or a variant YAML file (docs/simulator.md#robot-variants); overrides the "
                   "scenario's robot_variant. The controller is not told (give it --calibration).")
def serve_command(*, scenario: str, seed: int, json_path: Path | None, config_path: Path | None,
                  robot_path: Path | None, domain_id: int | None, middleware: str | None, discovery: str,
                  can_channel: str | None, can_port: int | None, camera_rate_hz: float, connect_timeout_s: float, force: bool, oracle: bool | None,
                  oracle_precision: float | None, oracle_recall: float | None, oracle_latency_s: float | None,
                  oracle_failure_rate: float | None, duration_s: float | None = None,
                  robot_variant: str | None = None, fault_texts: tuple[str, ...] = ()) -> None:
    """The simulator of SCENARIO in real time, as its own process: the emulated base on a udp_multicast CAN bus,
    the sensors as ROS 2 DDS topics (Livox CustomMsg or PointCloud2, Imu, Image); for planner mode dct also the
    sim-oracle as a VLM over HTTP on 127.0.0.1 (hil_sim/vlm/service.py). The episode starts when a controller enables
    the base; the metrics are written when it ends. Exit 0 when it ran (whatever the outcome), 2 on bad input."""
    import signal
    import threading

    from calibration.errors import ConfigFileError
    from hil_sim.episode.faults import FaultSpec, FaultSpecError
    from hil_sim.episode.serve import ServeOptions, serve

    check_scenario_and_output(scenario, seed, json_path, force, duration_s)
    try:
        faults = tuple(FaultSpec.parse(t) for t in fault_texts)
    except FaultSpecError as exc:
        raise InputError(str(exc)) from None
    try:
        oracle_config = _serve_oracle_config(config_path, seed, oracle, {
            "precision": oracle_precision, "recall": oracle_recall, "latency_s": oracle_latency_s,
            "failure_rate": oracle_failure_rate})
    except ConfigFileError as exc:
        raise InputError(str(exc)) from exc
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    try:
        m = serve(ServeOptions(scenario, seed, json_path, robot_path, config_path, domain_id, can_channel, can_port,
                               camera_rate_hz, connect_timeout_s, oracle=oracle_config, duration_s=duration_s,
                               middleware=middleware, discovery=discovery, robot_variant=robot_variant,
                               faults=faults), stop,
                  echo=lambda s: click.echo(s, err=True))
    except (ConfigFileError, ValueError) as exc:
        raise InputError(str(exc)) from exc
    click.echo(f"dct hil serve: episode ended ({m['end_reason']}): goal_reached(world)={m['goal_reached']} "
               f"fixed_contacts={m['fixed_contacts']} time={m['navigation_time_s']:.2f}s", err=True)


def _serve_oracle_config(config_path: Path | None, seed: int, oracle: bool | None, overrides: dict):
    """`dct hil serve`'s sim-oracle settings, or None when it serves none: the config's
    vpp.backend sim-oracle section (its seed added to the episode's, as lockstep does) with the
    command line's overrides; served when asked for, or by default in planner mode dct."""
    from models.vlm.sim_oracle import SimOracleConfig
    from runtime.config import load_controller_config

    config = load_controller_config(config_path)
    if oracle is None:
        oracle = config.uses_vlm_backend
    if not oracle:
        return None
    backend = config.vpp.backend
    base = backend.oracle_config(episode_seed=seed) if backend.kind == "sim-oracle" else SimOracleConfig(seed=seed)
    return SimOracleConfig(**{**base.model_dump(), **{k: v for k, v in overrides.items() if v is not None}})


def close_recording(recorder) -> None:
    """Finish the MCAP file and say on stderr what it holds (or why it is not where asked)."""
    from runtime.io.recording import RecordingError

    try:
        click.echo(recording_line(recorder.close()), err=True)
    except RecordingError as exc:  # the output appeared during the run: the recording is kept beside it
        click.echo(f"error: {exc}", err=True)


def recording_line(summary: dict) -> str:
    """One line about a finished recording: what it holds and what it had to drop."""
    line = (f"recorded {summary['path']}: {summary['written']['tick']} ticks, {summary['written']['can']} CAN frames, "
            f"{summary['written']['points']} point sets, {summary['written']['plan']} plans; "
            f"dropped {summary['dropped_total']}")
    if summary["dropped_total"]:
        line += f" (queue full: {summary['dropped_queue_full']}, write error: {summary['dropped_write_error']})"
    if summary["write_error"]:
        line += f"; write error: {summary['write_error']}"
    return line


def wall_clock_report(result) -> dict:
    """What the computer spent: measurements, not verdicts (they vary with the machine's load)."""
    return {
        "wall_time_s": result.wall_time_s,
        "realtime_factor": result.realtime_factor,
        **result.telemetry,
        "odometry": result.extra.get("odometry_wall_clock"),
    }


def summary_line(name: str, m: dict, realtime_factor: float) -> str:
    verdict = "SUCCESS" if m["success"] else f"FAIL ({m.get('failure_reason') or 'no reason recorded'})"
    line = (
        f"{name}: {verdict}"
        f" goal_reached={m['goal_reached']} time={m['navigation_time_s']:.2f}s"
        f" path={m['path_length_m']:.2f}m speed={m['average_speed_mps']:.3f}m/s"
        f" fixed_contacts={m['fixed_contacts']} movable_contacts={m.get('movable_contacts', 0)}"
        f" min_fixed_clearance={m['min_fixed_clearance_m'] * 100:.1f}cm"
        f" deadline_misses={m['deadline_misses']} state={m.get('controller_state')}"
        f" events={len(m.get('events', []))} realtime={realtime_factor:.1f}x"
    )
    return line
