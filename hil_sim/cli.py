"""`dct hil` (run scenarios in the simulator) and `dct bench` (benchmarks that print figures)."""
from __future__ import annotations

import sys
from pathlib import Path

import click


class InputError(click.ClickException):
    """Bad input (file, option): one line on stderr, exit status 2 (1 means: the episode failed)."""

    exit_code = 2


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
    type=click.Choice(["pure-pursuit", "all-fixed", "dct", "grid-astar"]),
    help="Override the config's planner mode (default dct: the MPC on the VLM partition's P_fix only, with the "
         "config's backend (the sim-oracle) and a 2 Hz camera; all-fixed: every lidar point fixed, the NeuPAN-like "
         "baseline; grid-astar: inflated occupancy grid + A* + pure pursuit, the Ellis22-like baseline; "
         "pure-pursuit: the blind placeholder).",
)
@click.option(
    "--fault", "fault_texts", multiple=True, metavar="NAME:START_S[:DURATION_S]",
    help="Inject a fault (repeatable): lidar-blind, lidar-far, lidar-frozen, drop-0x311, drop-0x211, drop-0x221, "
         "imu-silent, estop. Times in simulated seconds from the start; no duration = to the end.",
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
@click.option("--duration", "duration_s", type=click.FloatRange(0.0, 3600.0, min_open=True), metavar="SECONDS",
              help="A patrol scenario (goals:): patrol for this long instead of the file's patrol (loops or "
                   "duration_s); the time limit becomes this duration.")
def run_command(
    scenario: str, json_path: Path | None, seed: int, config_path: Path | None, robot_path: Path | None,
    planner: str | None, fault_texts: tuple[str, ...], calibration_path: Path | None = None,
    record_path: Path | None = None, force: bool = False, realtime: bool = False, duration_s: float | None = None,
) -> None:
    """Run one lockstep episode of SCENARIO (a library name such as case1, or a YAML path).

    The metrics JSON is deterministic (same inputs and seed, same file, under any machine load);
    the wall-clock timing the computer spent is in its `wall_clock` section, a measurement.
    Exit status 0 on success, 1 when the episode failed (the JSON says why: failure_reason), 2 on
    bad input (nothing is run, nothing is written).
    """
    from calibration.errors import ConfigFileError
    from calibration.outputs import OutputPathError, atomic_write_json, check_output_path
    from calibration.robot_description import load_robot_description
    from hil_sim.episode.faults import FaultSpec, FaultSpecError
    from hil_sim.episode.patrol import PatrolError, with_duration
    from hil_sim.episode.lockstep import run_episode
    from hil_sim.world.scenario import load_scenario
    from runtime.config import load_controller_config

    try:
        faults = [FaultSpec.parse(t) for t in fault_texts]
        sc = load_scenario(scenario, seed=seed)  # a generated scene (dct_f2m2) is drawn from the seed
        sc = with_duration(sc, duration_s)
        robot = load_robot_description(robot_path)
        config = load_controller_config(config_path)
        if planner is not None:
            config = config.with_planner_mode(planner)
        wheel_calibration = camera_calibration = None
        if calibration_path is not None:
            from calibration.calibration_file import camera_for_robot, load_calibration
            from calibration.wheel_odometry import wheel_params

            cal = load_calibration(calibration_path)
            camera_calibration = camera_for_robot(cal, robot, calibration_path)
            params = wheel_params(robot, cal)
            wheel_calibration = (params.effective_track_m, params.wheel_scale)
            click.echo(f"wheel odometry: effective track {params.effective_track_m:.4f} m, scale "
                       f"{params.wheel_scale:.4f} ({params.source})", err=True)
        from hil_sim.world.scenario import check_scenario_against_robot

        warnings = check_scenario_against_robot(
            sc, robot, ground_clearance_m=config.planner.obstacle_points.ground_clearance_m
        )
        inputs = [p for p in (config_path, robot_path, calibration_path, Path(scenario))
                  if p is not None and Path(p).is_file()]
        if json_path is not None:
            check_output_path(json_path, what="--json", inputs=inputs)
        if record_path is not None:
            check_output_path(record_path, what="--record", inputs=inputs, overwrite=force)
            if json_path is not None and record_path.resolve() == json_path.resolve():
                raise InputError(f"--record {record_path} is also the --json file; write them to two files")
        if config.uses_distance_net:  # the distance net must fit this robot (checked again at start-up)
            from models.distance_net import DistanceNet
            from models.errors import DistanceNetError

            try:
                DistanceNet.load(config.planner.distance_net_path, robot=robot)
            except DistanceNetError as exc:
                raise InputError(str(exc)) from exc
    except (ConfigFileError, FaultSpecError, OutputPathError, PatrolError) as exc:
        raise InputError(str(exc)) from exc
    warnings += [f"--fault {f}: starts at or after the time limit ({sc.time_limit_s:g} s); it will never act"
                 for f in faults if f.start_s >= sc.time_limit_s]
    for w in warnings:
        click.echo(f"warning: {w}", err=True)
    if realtime:
        _run_realtime(sc, scenario, seed, json_path, config_path, robot_path, calibration_path, planner,
                      fault_texts, record_path, force, duration_s)
        return
    recorder = None
    if record_path is not None:
        from runtime.io.recording import RecordingError, RunRecorder

        try:
            recorder = RunRecorder(record_path, force=force)
        except RecordingError as exc:
            raise InputError(str(exc)) from exc
    try:
        try:
            result = run_episode(sc, robot=robot, config=config, seed=seed, faults=faults,
                                 wheel_calibration=wheel_calibration, recorder=recorder,
                                 camera_calibration=camera_calibration)
        except BaseException as exc:  # the log of a failed run is kept (it says how it ended)
            if recorder is not None:
                recorder.note_run_end(exc)
                close_recording(recorder)
            raise
        if recorder is not None:
            close_recording(recorder)
    except ConfigFileError as exc:  # a scenario the robot cannot start in, a bad model file
        raise InputError(str(exc)) from exc
    m = result.metrics
    if json_path is not None:
        payload = dict(m)
        payload["wall_clock"] = wall_clock_report(result)
        atomic_write_json(json_path, payload)
    click.echo(summary_line(sc.name, m, result.realtime_factor))
    if not m["success"]:
        sys.exit(1)


def _run_realtime(sc, scenario: str, seed: int, json_path: Path | None, config_path: Path | None,
                  robot_path: Path | None, calibration_path: Path | None, planner: str | None,
                  fault_texts: tuple[str, ...], record_path: Path | None, force: bool = False,
                  duration_s: float | None = None) -> None:
    """`dct hil run --realtime`: hil_sim.episode.realtime (two processes); --record: the controller's."""
    from calibration.outputs import atomic_write_json
    from hil_sim.episode.realtime import run_realtime_episode

    for what, given in (("--fault", fault_texts),):
        if given:
            raise InputError(f"{what} is not supported with --realtime yet")
    if planner not in (None, "dct", "all-fixed"):
        raise InputError(f"--planner {planner} is not supported with --realtime (dct or all-fixed: `dct run` runs those)")
    try:
        m = run_realtime_episode(scenario, seed, config_path, robot_path, calibration_path,
                                 echo=lambda s: click.echo(s, err=True), planner=planner, duration_s=duration_s,
                                 record_path=record_path.resolve() if record_path is not None else None,
                                 force=force)
    except RuntimeError as exc:
        raise click.ClickException(str(exc)) from None
    if json_path is not None:
        atomic_write_json(json_path, m)
    click.echo(realtime_line(sc.name, m))
    if not m["success"]:
        sys.exit(1)


def realtime_line(name: str, m: dict) -> str:
    """summary_line plus the real-time figures."""
    rt = m["realtime"]

    def f(d):
        return "/".join("-" if d[k] is None else f"{d[k]:.1f}" for k in ("p50", "p99", "max"))

    line = summary_line(name, m, 1.0).rsplit(" realtime=", 1)[0]
    return (f"{line} realtime: tick_ms(p50/p99/max)={f(rt['tick_ms'])} "
            f"sensor_to_command_ms={f(rt['sensor_to_command_ms'])} pids={rt['pids']['simulator']},"
            f"{rt['pids']['controller']}")


def _check_scenario_and_output(scenario: str, seed: int, json_path: Path | None, force: bool,
                               duration_s: float | None = None) -> None:
    """Before a long real-time run: the scenario loads (a generated one from its seed; a --duration
    only for a patrol) and the --json output may be written (an existing file only with --force);
    else one line, exit 2."""
    from calibration.errors import ConfigFileError
    from calibration.outputs import OutputPathError, check_output_path
    from hil_sim.episode.patrol import PatrolError, with_duration
    from hil_sim.world.scenario import load_scenario

    try:
        with_duration(load_scenario(scenario, seed=seed), duration_s)
        if json_path is not None:
            check_output_path(json_path, what="--json", overwrite=force)
    except (ConfigFileError, OutputPathError, PatrolError) as exc:
        raise InputError(str(exc)) from exc


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
@click.option("--can-channel", help="CAN udp_multicast group (default: python-can's).")
@click.option("--can-port", type=click.IntRange(1, 65535), help="CAN udp_multicast port.")
@click.option("--camera-rate", "camera_rate_hz", default=0.0, show_default=True, type=click.FloatRange(0.0, 30.0),
              help="Camera images per second (0: no camera; rendering is costly).")
@click.option("--connect-timeout", "connect_timeout_s", default=120.0, show_default=True,
              type=click.FloatRange(1.0, 3600.0), help="End the episode if no controller enables the base by then.")
@click.option("--duration", "duration_s", type=click.FloatRange(0.0, 3600.0, min_open=True), metavar="SECONDS",
              help="A patrol scenario (goals:): patrol for this long instead of the file's patrol.")
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
def serve_command(scenario: str, seed: int, json_path: Path | None, config_path: Path | None,
                  robot_path: Path | None, domain_id: int | None, can_channel: str | None, can_port: int | None,
                  camera_rate_hz: float, connect_timeout_s: float, force: bool, oracle: bool | None,
                  oracle_precision: float | None, oracle_recall: float | None, oracle_latency_s: float | None,
                  oracle_failure_rate: float | None, duration_s: float | None = None) -> None:
    """The simulator of SCENARIO in real time, as its own process: the emulated base on a udp_multicast CAN bus,
    the sensors as ROS 2 DDS topics (Livox CustomMsg, Imu, Image); for planner mode dct also the sim-oracle as a VLM
    over HTTP on 127.0.0.1 (hil_sim/vlm/service.py). The episode starts when a controller enables
    the base; the metrics are written when it ends. Exit 0 when it ran (whatever the outcome), 2 on bad input."""
    import signal
    import threading

    from calibration.errors import ConfigFileError
    from hil_sim.episode.serve import ServeOptions, serve

    _check_scenario_and_output(scenario, seed, json_path, force, duration_s)
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
                               camera_rate_hz, connect_timeout_s, oracle=oracle_config, duration_s=duration_s), stop,
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


@click.group(name="bench")
def bench_group() -> None:
    """Benchmarks: each prints its figures (no pass/fail)."""


@bench_group.command("sim-speed")
@click.option("--scenario", default="case1", show_default=True)
@click.option("--seconds", default=10.0, show_default=True, help="Simulated seconds per run.")
@click.option("--repeats", default=3, show_default=True)
@click.option("--sensors", is_flag=True, help="Sensors on (lidar 10 Hz, IMU 200 Hz, camera 2 Hz), robot driven by "
              "constant 0x111 commands (no planner); also times the same loop without sensors.")
def sim_speed_command(scenario: str, seconds: float, repeats: int, sensors: bool) -> None:
    """Lockstep speed as a multiple of real time, with the robot driving (controller in the loop)."""
    if sensors:
        from hil_sim.bench.sim import run_sensor_sim_speed_benchmark

        run_sensor_sim_speed_benchmark(scenario, seconds, repeats, echo=click.echo)
        return
    from hil_sim.bench.sim import run_sim_speed_benchmark

    run_sim_speed_benchmark(scenario, seconds, repeats, echo=click.echo)


@bench_group.command("realtime")
@click.option("--scenario", default="case3", show_default=True)
@click.option("--runs", default=10, show_default=True, type=click.IntRange(1, 100))
@click.option("--seed", default=0, show_default=True, type=click.IntRange(0, 2**32 - 1),
              help="Seed of the first run (run k uses seed + k).")
@click.option("--config", "config_path", type=click.Path(exists=True, dir_okay=False, path_type=Path))
@click.option("--json", "json_path", type=click.Path(dir_okay=False, path_type=Path), help="Write the figures as JSON.")
@click.option("--force", is_flag=True, help="Overwrite an existing --json file.")
def realtime_bench_command(scenario: str, runs: int, seed: int, config_path: Path | None, json_path: Path | None,
                           force: bool) -> None:
    """Real-time HIL episodes in a row (`dct hil run --realtime`, two processes each): success count, the
    controller's tick and sensor-to-command latency (end of lidar frame -> the 0x111 written from it), deadline
    misses, simulator lag."""
    from calibration.outputs import atomic_write_json
    from hil_sim.episode.realtime import run_realtime_benchmark

    _check_scenario_and_output(scenario, seed, json_path, force)
    out = run_realtime_benchmark(scenario, runs, seed, config_path, echo=click.echo)
    if json_path is not None:
        atomic_write_json(json_path, out)


@bench_group.command("sensors")
@click.option("--frames", default=10, show_default=True, help="Lidar frames to time.")
@click.option("--renders", default=10, show_default=True, help="RGB and segmentation renders to time.")
@click.option("--boxes", default=60, show_default=True, help="Clutter boxes in the benchmark room.")
def sensors_command(frames: int, renders: int, boxes: int) -> None:
    """ms per 20k-point lidar frame, per RGB render and per segmentation render."""
    from hil_sim.bench.sensors import run_sensor_benchmark

    result = run_sensor_benchmark(n_frames=frames, n_renders=renders, n_boxes=boxes)
    for key, value in result.items():
        click.echo(f"{key}: {value:.3f}" if isinstance(value, float) else f"{key}: {value}")


@bench_group.command("odometry")
@click.option("--scenario", default="odom_loop", show_default=True, help="Scenario with a route (recorded in lockstep).")
@click.option("--seconds", default=30.0, show_default=True, type=click.FloatRange(1.0, 600.0))
@click.option("--hog", "hogs", multiple=True, type=click.IntRange(0, 64), default=(0, 2), show_default=True,
              help="Busy processes beside it (repeat for several runs).")
@click.option("--json", "json_path", type=click.Path(dir_okay=False, path_type=Path), help="Write the figures as JSON.")
def odometry_bench_command(scenario: str, seconds: float, hogs: tuple[int, ...], json_path: Path | None) -> None:
    """The odometry stage on the wall clock with 20k-point frames: time in the tick, ICP time
    per frame in its worker process, pose latency (frame end -> pose), with N busy processes."""
    from calibration.errors import ConfigFileError
    from calibration.outputs import OutputPathError, atomic_write_json, check_output_path
    from hil_sim.bench.odometry import print_odometry_benchmark
    from hil_sim.world.scenario import load_scenario

    try:
        if load_scenario(scenario).route is None:
            raise InputError(f"dct bench odometry: scenario {scenario} has no route to drive (odom_loop has one)")
        if json_path is not None:
            check_output_path(json_path, what="--json")
    except (ConfigFileError, OutputPathError) as exc:
        raise InputError(str(exc)) from exc
    out = print_odometry_benchmark(scenario, seconds, hogs, click.echo)
    if json_path is not None:
        atomic_write_json(json_path, out)


@bench_group.command("tick")
@click.option("--scenario", "scenarios", multiple=True, metavar="NAME",
              help="Scene to run (repeatable): a library name, a scenario .yaml, or odom_loop_far (odom_loop with "
                   "its goal 5.8 m along its route). Default: corridor_boxes, case1, case3, odom_loop_far "
                   "(increasing clutter).")
@click.option("--seed", default=0, show_default=True, type=click.IntRange(0, 2**32 - 1),
              help="Seed of the first run of each scene (run k uses seed + k).")
@click.option("--runs", default=2, show_default=True, type=click.IntRange(1, 100), help="Episodes per scene.")
@click.option("--hog", "hogs", default=0, show_default=True, type=click.IntRange(0, 64),
              help="Busy processes beside the benchmark (the robot's other software), killed at the end.")
@click.option("--seconds", type=click.FloatRange(0.5, 600.0),
              help="Cap on each episode's simulated seconds (default: the scene's time limit; episodes end at "
                   "the goal).")
@click.option("--odometry-scaling/--no-odometry-scaling", default=True, show_default=True,
              help="Also the odometry table: ICP time per frame against lidar points per frame.")
@click.option("--scaling-rays", multiple=True, type=click.IntRange(100, 200_000), metavar="N",
              help="Rays per frame of the odometry table (repeatable; default 5000, 10000, 20000, 40000).")
@click.option("--json", "json_path", type=click.Path(dir_okay=False, path_type=Path),
              help="Write the figures as JSON (checked before the run, written atomically after it).")
@click.option("--force", is_flag=True, help="Overwrite an existing --json file.")
def tick_bench_command(scenarios: tuple[str, ...], seed: int, runs: int, hogs: int, seconds: float | None,
                       odometry_scaling: bool, scaling_rays: tuple[int, ...], json_path: Path | None,
                       force: bool) -> None:
    """The whole controller tick (read, odometry, partition, planner, safety, write) on the wall clock,
    in lockstep episodes with 20k-ray lidar frames: per stage and per tick p50/p90/p99/max against the
    budgets, deadline misses, points per frame, capped QP solves; and ICP time against points per frame."""
    from calibration.errors import ConfigFileError
    from calibration.outputs import OutputPathError, atomic_write_json, check_output_path
    from hil_sim.bench.tick import DEFAULT_SCALING_RAYS, DEFAULT_SCENES, resolve_scene, run_tick_benchmark

    names = scenarios or DEFAULT_SCENES
    try:
        for name in names:
            resolve_scene(name)
        if json_path is not None:
            check_output_path(json_path, what="--json", inputs=[Path(n) for n in names if Path(n).is_file()],
                              overwrite=force)
    except (ConfigFileError, OutputPathError) as exc:
        raise InputError(str(exc)) from exc
    rays = (scaling_rays or DEFAULT_SCALING_RAYS) if odometry_scaling else ()
    out = run_tick_benchmark(tuple(names), seed, runs, hogs, seconds, rays, echo=click.echo)
    if json_path is not None:
        atomic_write_json(json_path, out)


@bench_group.command("vpp")
@click.option("--masks", "mask_counts", multiple=True, type=click.IntRange(1, 64), metavar="N",
              help="Movable masks in memory (repeatable).  [default: 1, 4, 8]")
@click.option("--repeats", default=300, show_default=True, type=click.IntRange(10, 100000), help="Timed scans per row.")
@click.option("--points", "n_points", default=20000, show_default=True, type=click.IntRange(100, 1000000),
              help="Lidar points per scan.")
@click.option("--seed", default=0, show_default=True, type=click.IntRange(0, 2**32 - 1))
@click.option("--cpu", type=click.IntRange(0, 1023), help="Pin the process to this core.")
@click.option("--json", "json_path", type=click.Path(dir_okay=False, path_type=Path),
              help="Write the figures as JSON (checked before the run, written atomically after it).")
@click.option("--force", is_flag=True, help="Overwrite an existing --json file.")
def vpp_bench_command(mask_counts: tuple[int, ...], repeats: int, n_points: int, seed: int, cpu: int | None,
                      json_path: Path | None, force: bool) -> None:
    """The whole VPP stage per scan (VppStage.update: Phase I, partition, tracking), single-threaded,
    with 1, 4 and 8 movable masks in memory and the camera moving: p50/p99/max and the split."""
    import os

    from calibration.outputs import OutputPathError, atomic_write_json, check_output_path
    from hil_sim.bench.vpp import DEFAULT_MASK_COUNTS, run_vpp_benchmark

    try:
        if cpu is not None and cpu not in os.sched_getaffinity(0):
            raise InputError(f"--cpu {cpu}: not one of this process's cores {sorted(os.sched_getaffinity(0))}")
        if json_path is not None:
            check_output_path(json_path, what="--json", overwrite=force)
    except OutputPathError as exc:
        raise InputError(str(exc)) from exc
    counts = tuple(sorted(set(mask_counts))) or DEFAULT_MASK_COUNTS
    if n_points // 4 // max(counts) < 32:  # synthetic_frame: a quarter of the points on the boxes
        raise InputError(f"--points {n_points}: too few for {max(counts)} masks (each box needs 32 points for its "
                         f"plane; at least {128 * max(counts)})")
    out = run_vpp_benchmark(counts, repeats, n_points, seed, cpu, echo=click.echo)
    if json_path is not None:
        atomic_write_json(json_path, out)


@bench_group.command("planner")
@click.option("--repeats", default=300, show_default=True, type=click.IntRange(10, 100000),
              help="Planner steps per (horizon, points).")
@click.option("--cvxpy-repeats", default=20, show_default=True, type=click.IntRange(0, 10000),
              help="cvxpy planner steps per (horizon, points); 0 skips cvxpy.")
@click.option("--horizon", "horizons", multiple=True, type=click.IntRange(2, 60),
              help="Horizon H (repeatable).  [default: 10, 20, 30]")
@click.option("--points", "point_counts", multiple=True, type=click.IntRange(1, 1000000),
              help="Points in range N (repeatable).  [default: 100, 300, 1000, 3000, 10000]")
@click.option("--net", "net_path", type=click.Path(exists=True, dir_okay=False), help="Distance net (default: shipped).")
@click.option("--json", "json_path", type=click.Path(dir_okay=False, path_type=Path), help="Write the rows as JSON.")
@click.option("--force", is_flag=True, help="Overwrite an existing --json file.")
def planner_command(repeats: int, cvxpy_repeats: int, horizons: tuple[int, ...], point_counts: tuple[int, ...],
                    net_path: str | None, json_path: Path | None, force: bool) -> None:
    """Planner step time (selection + net + QP, one thread) against points in range and horizon,
    with the share of each part and the constraint set's size, against cvxpy (ECOS, Clarabel)."""
    from calibration.outputs import OutputPathError, atomic_write_json, check_output_path
    from hil_sim.bench.planner import HORIZONS, POINT_COUNTS, cap_warnings, print_planner_benchmark

    if json_path is not None:
        try:
            check_output_path(json_path, what="--json", overwrite=force)
        except OutputPathError as exc:
            raise InputError(str(exc)) from exc
    rows = print_planner_benchmark(
        echo=click.echo, repeats=repeats, cvxpy_repeats=cvxpy_repeats, distance_net_path=net_path,
        horizons=tuple(sorted(set(horizons))) or HORIZONS, point_counts=tuple(sorted(set(point_counts))) or POINT_COUNTS,
        progress=lambda what: click.echo(f"... {what}", err=True),
    )
    if json_path is not None:
        atomic_write_json(json_path, {"rows": rows, "warnings": cap_warnings(rows)})


def _campaign_options(func):
    """The options `dct bench paper` and `dct bench beacon` share."""
    options = [
        click.option("--seeds", default=10, show_default=True, type=click.IntRange(1, 10000),
                     help="Episodes per row (seeds --seed .. --seed + N - 1)."),
        click.option("--seed", "first_seed", default=0, show_default=True, type=click.IntRange(0, 2**32 - 1),
                     help="Seed of the first episode of each row."),
        click.option("--methods", default=None, metavar="M1,M2",
                     help="Comma-separated methods: dct, all-fixed, grid-astar, fixed-labels.  [default: all]"),
        click.option("--only", multiple=True, metavar="SCENE",
                     help="Run only this scene of the campaign (repeatable; e.g. case1, F2M2, sparse)."),
        click.option("--workers", type=click.IntRange(1, 1024),
                     help="Episodes in parallel (worker processes; the rows do not depend on it).  [default: all "
                          "cores]"),
        click.option("--ray", "ray_address", metavar="ADDRESS",
                     help="Run the episodes as Ray tasks: 'local' (a private Ray on this machine, --workers CPUs), "
                          "'auto', 'ray://HEAD:10001' or 'HEAD:6379' (optional dependency: the [ray] extra)."),
        click.option("--config", "config_path", type=click.Path(exists=True, dir_okay=False, path_type=Path),
                     help="Base controller config (each method sets its planner mode and belief switch on it)."),
        click.option("--json", "json_path", type=click.Path(dir_okay=False, path_type=Path),
                     help="Write rows, episodes and the papers' figures as JSON (checked before the run, written "
                          "atomically after it)."),
        click.option("--force", is_flag=True, help="Overwrite an existing --json file."),
        click.option("--clock", type=click.Choice(["switch-on", "goal-when-ready"]), default="switch-on",
                     show_default=True,
                     help="Navigation clock: switch-on gives the goal at start (start-up and the VLM's first answer "
                          "count); goal-when-ready gives it once the controller runs and the VLM has answered once "
                          "(a robot switched on before it is sent)."),
    ]
    for option in reversed(options):
        func = option(func)
    return func


def _run_campaign_command(name: str, seeds: int, first_seed: int, methods: str | None, only: tuple[str, ...],
                          workers: int | None, ray_address: str | None, config_path: Path | None,
                          json_path: Path | None, force: bool, clock: str = "switch-on") -> None:
    """Check the inputs (one line, exit 2), run with a rich progress bar, print the table, write the JSON."""
    from calibration.errors import ConfigFileError
    from calibration.outputs import atomic_write_json
    from hil_sim.bench.campaign import CAMPAIGNS, CampaignError, RichProgress, format_table, parse_methods, \
        run_campaign, select_scenes
    from runtime.common.cli_support import checked_output
    from runtime.config import load_controller_config

    try:
        method_list = parse_methods(methods)
        select_scenes(CAMPAIGNS[name], only)
        load_controller_config(config_path)
    except (CampaignError, ConfigFileError) as exc:
        raise InputError(str(exc)) from None
    if ray_address is not None:
        import importlib.util

        if importlib.util.find_spec("ray") is None:
            raise InputError("--ray: Ray is not installed (pip install 'dct-controller[ray]', or run without --ray "
                             "for local worker processes)") from None
    checked_output(json_path, "--json", [config_path], force)
    progress = RichProgress(name)
    try:
        result = run_campaign(name, method_list, seeds, first_seed, workers, ray_address, only,
                              str(config_path) if config_path is not None else None,
                              on_done=progress.done, on_start=progress.start, clock=clock)
    except CampaignError as exc:
        raise InputError(str(exc)) from None
    finally:
        progress.close()
    for line in format_table(result):
        click.echo(line)
    if json_path is not None:
        atomic_write_json(json_path, result)


@bench_group.command("paper")
@click.option("--table", type=click.Choice(["1", "2"]), required=True,
              help="1: DCT Table I (cases 1-3); 2: DCT Table II (layouts F4M0, F3M1, F2M2, F1M3, drawn per seed).")
@_campaign_options
def paper_command(table: str, seeds: int, first_seed: int, methods: str | None, only: tuple[str, ...],
                  workers: int | None, ray_address: str | None, config_path: Path | None, json_path: Path | None,
                  force: bool, clock: str) -> None:
    """The DCT paper's tables in the simulator: success, navigation time, average speed, navigation distance
    (plus fixed contacts, path cost, fragile damage, correcting events, deadline misses) for dct, all-fixed
    (NeuPAN-like), grid-astar (Ellis22-like) and fixed-labels, next to the paper's figures."""
    _run_campaign_command(f"table{table}", seeds, first_seed, methods, only, workers, ray_address, config_path,
                          json_path, force, clock)


@bench_group.command("beacon")
@_campaign_options
def beacon_command(seeds: int, first_seed: int, methods: str | None, only: tuple[str, ...], workers: int | None,
                   ray_address: str | None, config_path: Path | None, json_path: Path | None, force: bool,
                   clock: str) -> None:
    """BEACON's four families (sparse, cluttered, collision-required, collision-shortcut), drawn per seed: the
    same figures per family and overall, next to BEACON's published success and path length."""
    _run_campaign_command("beacon", seeds, first_seed, methods, only, workers, ray_address, config_path,
                          json_path, force, clock)
