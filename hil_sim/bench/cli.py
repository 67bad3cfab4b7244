"""`dct bench`: benchmarks that print figures (no pass/fail, but for the regression gate `dct bench tick --budget`)."""
from __future__ import annotations

import contextlib
from pathlib import Path

import click

from hil_sim.episode.cli_checks import InputError, check_scenario_and_output
from runtime.common.provenance import with_provenance


@click.group(name="bench")
def bench_group() -> None:
    """Benchmarks: each prints its figures (no pass/fail, but for the gate of tick --budget)."""


@bench_group.command("sim-speed")
@click.option("--scenario", default="case1", show_default=True)
@click.option("--seconds", default=10.0, show_default=True, help="Simulated seconds per run.")
@click.option("--repeats", default=3, show_default=True)
@click.option("--sensors", is_flag=True, help="Sensors on (lidar 10 Hz, IMU 200 Hz, camera 2 Hz), robot driven by "
              "constant 0x111 commands (no planner); also times the same loop without sensors.")
def sim_speed_command(*, scenario: str, seconds: float, repeats: int, sensors: bool) -> None:
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
def realtime_bench_command(*, scenario: str, runs: int, seed: int, config_path: Path | None, json_path: Path | None,
                           force: bool) -> None:
    """Real-time HIL episodes in a row (`dct hil run --realtime`, two processes each): success count, the
    controller's tick and sensor-to-command latency (end of lidar frame -> the 0x111 written from it), deadline
    misses, simulator lag."""
    from calibration.outputs import atomic_write_json
    from hil_sim.episode.realtime import run_realtime_benchmark

    check_scenario_and_output(scenario, seed, json_path, force)
    out = run_realtime_benchmark(scenario, runs, seed, config_path, echo=click.echo)
    if json_path is not None:
        atomic_write_json(json_path, with_provenance(out))


@bench_group.command("sensors")
@click.option("--frames", default=10, show_default=True, help="Lidar frames to time.")
@click.option("--renders", default=10, show_default=True, help="RGB and segmentation renders to time.")
@click.option("--boxes", default=60, show_default=True, help="Clutter boxes in the benchmark room.")
def sensors_command(*, frames: int, renders: int, boxes: int) -> None:
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
def odometry_bench_command(*, scenario: str, seconds: float, hogs: tuple[int, ...], json_path: Path | None) -> None:
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
        atomic_write_json(json_path, with_provenance(out))


@bench_group.command("odom-settings")
@click.option("--sequence", "sequences", multiple=True, type=click.Path(file_okay=False, path_type=Path),
              metavar="DIR", help="A recorded sequence's scan folder (repeatable; each with a --poses, in order).")
@click.option("--poses", "poses", multiple=True, type=click.Path(dir_okay=False, path_type=Path), metavar="FILE",
              help="The KITTI poses of the --sequence at the same position.")
@click.option("--scenario", "scenarios", multiple=True, metavar="NAME",
              help="A scenario with a route, recorded in lockstep first (repeatable; e.g. odom_loop, odom_corridor).")
@click.option("--seed", default=0, show_default=True, type=click.IntRange(0, 2**32 - 1), help="Seed of the scenarios.")
@click.option("--voxel", "voxels", multiple=True, type=click.FloatRange(0.05, 5.0), metavar="M",
              help="Grid voxels (repeatable).  [default: 0.3, 0.5, 1.0]")
@click.option("--max-range", "ranges", multiple=True, type=click.FloatRange(1.0, 500.0), metavar="M",
              help="Grid max ranges (repeatable).  [default: 12, 60, 100]")
@click.option("--iterations", "iterations", multiple=True, type=click.IntRange(1, 500), metavar="N",
              help="Grid iteration caps (repeatable).  [default: 50, 500]")
@click.option("--json", "json_path", type=click.Path(dir_okay=False, path_type=Path),
              help="Write the figures as JSON (checked before the run, written atomically after it).")
@click.option("--force", is_flag=True, help="Overwrite an existing --json file.")
def odom_settings_bench_command(*, sequences: tuple[Path, ...], poses: tuple[Path, ...], scenarios: tuple[str, ...],
                                seed: int, voxels: tuple[float, ...], ranges: tuple[float, ...],
                                iterations: tuple[int, ...], json_path: Path | None, force: bool) -> None:
    """KISS-ICP alone with the default (auto) settings beside the best of a grid (voxel x max range x
    iteration cap) on each recorded sequence and scenario: end error, relative pose error, the settings
    auto chose, and the time per frame (p50/p99)."""
    from calibration.errors import ConfigFileError
    from calibration.outputs import atomic_write_json
    from hil_sim.bench.odom_settings import (GRID_ITERATIONS, GRID_MAX_RANGES_M, GRID_VOXELS_M, BenchInput,
                                             grid_configs, run_odom_settings_bench)
    from hil_sim.world.scenario import load_scenario
    from runtime.common.cli_support import checked_output
    from runtime.odometry.sequence import SequenceInputError, load_sequence

    if len(sequences) != len(poses):
        raise InputError(f"dct bench odom-settings: {len(sequences)} --sequence and {len(poses)} --poses: give one --poses "
                         f"per --sequence, in the same order")
    if not sequences and not scenarios:
        raise InputError("dct bench odom-settings: nothing to run: give --sequence DIR --poses FILE and/or --scenario NAME")
    items = []
    try:
        for scans, pose_file in zip(sequences, poses):
            load_sequence(scans, pose_file)  # checks every count and pose before anything runs
            items.append(BenchInput(scans.name if scans.name not in ("scans", "frames", "velodyne", "points") else scans.parent.name, scans, pose_file))
        for name in scenarios:
            if load_scenario(name).route is None:
                raise InputError(f"dct bench odom-settings: scenario {name} has no route to drive (odom_loop has one)")
    except (SequenceInputError, ConfigFileError) as exc:
        raise InputError(str(exc)) from None
    checked_output(json_path, "--json", [*poses], force)
    configs = grid_configs(tuple(sorted(set(voxels))) or GRID_VOXELS_M, tuple(sorted(set(ranges))) or GRID_MAX_RANGES_M,
                           tuple(sorted(set(iterations))) or GRID_ITERATIONS)
    out = run_odom_settings_bench(items, list(scenarios), seed, configs, echo=click.echo)
    if json_path is not None:
        atomic_write_json(json_path, with_provenance(out))


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
@click.option("--short", is_flag=True,
              help="The CI run: case1, 6 runs of at most 8 simulated seconds, no odometry table (not with --scenario, "
                   "--runs, --seconds).")
@click.option("--budget", "budget_flag", is_flag=True,
              help="Regression gate: exit 1 when the tick p99, in units of a reference workload timed in this "
                   "process, exceeds the calibrated budget for these settings beyond this machine's noise and "
                   "the margin (hil_sim/bench/tick_budget.yaml).")
@click.option("--budget-ms", type=click.FloatRange(0.1, 10_000.0), metavar="MS",
              help="Gate against MS: exit 1 when the tick p99 on this machine exceeds it (no normalization).")
@click.option("--budget-file", type=click.Path(exists=True, dir_okay=False, path_type=Path),
              help="The calibrations --budget reads (default: the shipped tick_budget.yaml).")
@click.option("--write-budget", "write_budget", type=click.Path(dir_okay=False, path_type=Path), metavar="FILE",
              help="Measure the calibration of these settings on this machine and write it into FILE "
                   "(other settings' calibrations kept).")
@click.option("--profile", "profile_dir", type=click.Path(file_okay=False, path_type=Path), metavar="DIR",
              help="Also where the tick's CPU time goes, part by part (printed, and in the JSON), with cProfile of "
                   "the tick alone in DIR/tick.prof and DIR/tick_profile.txt (not with the gate: it slows the tick).")
@click.pass_context
def tick_bench_command(ctx: click.Context, *, scenarios: tuple[str, ...], seed: int, runs: int, hogs: int,
                       seconds: float | None, odometry_scaling: bool, scaling_rays: tuple[int, ...],
                       json_path: Path | None, force: bool, short: bool, budget_flag: bool, budget_ms: float | None,
                       budget_file: Path | None, write_budget: Path | None, profile_dir: Path | None) -> None:
    """The whole controller tick (read, odometry, partition, planner, safety, write) on the wall clock,
    in lockstep episodes with 20k-ray lidar frames: per stage and per tick p50/p90/p99/max against the
    budgets, deadline misses, points per frame, capped QP solves; and ICP time against points per frame.
    With --budget: the regression gate (exit 1 on a regression)."""
    from calibration.errors import ConfigFileError
    from calibration.outputs import OutputPathError, atomic_write_json, check_output_path
    from hil_sim.bench.tick import DEFAULT_SCALING_RAYS, DEFAULT_SCENES, resolve_scene, run_tick_benchmark
    from hil_sim.bench.tick_gate import SHORT, WARMUP_TICKS, GateInputError, RunSettings, prepare_gate

    if short:
        explicit = [f"--{n}" for n in ("scenario", "runs", "seconds")
                    if ctx.get_parameter_source(n if n != "scenario" else "scenarios").name == "COMMANDLINE"]
        if explicit:
            raise InputError(f"--short sets the scene, runs and seconds: not with {', '.join(explicit)}")
        scenarios, runs, seconds, odometry_scaling = SHORT.scenes, SHORT.runs, SHORT.seconds, False
    names = scenarios or DEFAULT_SCENES
    if profile_dir is not None and (budget_flag or budget_ms is not None or write_budget is not None):
        raise InputError("--profile slows the tick it measures: not with --budget, --budget-ms or --write-budget")
    if profile_dir is not None and profile_dir.exists() and any(profile_dir.iterdir()) and not force:
        raise InputError(f"--profile {profile_dir}: the folder is not empty (--force to write into it)")
    settings = RunSettings(scenes=tuple(names), runs=runs, seconds=seconds, seed=seed, hogs=hogs,
                           warmup_ticks=WARMUP_TICKS)
    try:
        gate = prepare_gate(settings, budget_flag, budget_ms, budget_file, write_budget)
    except GateInputError as exc:
        raise InputError(str(exc)) from None
    try:
        for name in names:
            resolve_scene(name)
        if json_path is not None:
            check_output_path(json_path, what="--json", inputs=[Path(n) for n in names if Path(n).is_file()],
                              overwrite=force)
    except (ConfigFileError, OutputPathError) as exc:
        raise InputError(str(exc)) from exc
    rays = (scaling_rays or DEFAULT_SCALING_RAYS) if odometry_scaling else ()
    profile = None
    if profile_dir is not None:
        from hil_sim.bench.tick_profile import TickProfile

        profile = TickProfile()
    with profile.installed() if profile is not None else contextlib.nullcontext():
        out = run_tick_benchmark(tuple(names), seed, runs, hogs, seconds, rays, echo=click.echo,
                                 gate=gate.probe if gate is not None else None)
    if profile is not None:
        from hil_sim.bench.tick_profile import parts_lines

        out["profile"] = profile.table()
        for line in parts_lines(out["profile"]):
            click.echo(line)
        profile.write(profile_dir)
        click.echo(f"cProfile of the tick: {profile_dir / 'tick.prof'}, {profile_dir / 'tick_profile.txt'}")
    try:
        passed = gate is None or gate.finish(out, click.echo)
    except GateInputError as exc:
        raise InputError(str(exc)) from None
    if json_path is not None:
        atomic_write_json(json_path, with_provenance(out))
    if not passed:
        ctx.exit(1)


@bench_group.command("icp-parts")
@click.option("--rays", "rays", multiple=True, type=click.IntRange(100, 200_000), metavar="N",
              help="Rays per lidar frame (repeatable).  [default: 5000, 10000, 20000, 40000]")
@click.option("--seconds", default=8.0, show_default=True, type=click.FloatRange(1.0, 120.0),
              help="Simulated seconds of the drive per density.")
@click.option("--seed", default=0, show_default=True, type=click.IntRange(0, 2**32 - 1))
@click.option("--repeats", default=3, show_default=True, type=click.IntRange(1, 20),
              help="Registrations of each frame (its fastest counts).")
@click.option("--json", "json_path", type=click.Path(dir_okay=False, path_type=Path),
              help="Write the figures as JSON (checked before the run, written atomically after it).")
@click.option("--force", is_flag=True, help="Overwrite an existing --json file.")
def icp_parts_bench_command(*, rays: tuple[int, ...], seconds: float, seed: int, repeats: int,
                            json_path: Path | None, force: bool) -> None:
    """ICP time per lidar frame by part (preprocess and deskew, downsampling, degeneracy analysis,
    registration, map update; the job's pickling) at several densities, on `dct bench tick`'s drive."""
    from calibration.outputs import OutputPathError, atomic_write_json, check_output_path
    from hil_sim.bench.icp_parts import DEFAULT_RAYS, run_icp_parts

    try:
        if json_path is not None:
            check_output_path(json_path, what="--json", overwrite=force)
    except OutputPathError as exc:
        raise InputError(str(exc)) from exc
    out = run_icp_parts(tuple(sorted(set(rays))) or DEFAULT_RAYS, seconds, seed, repeats, click.echo)
    if json_path is not None:
        atomic_write_json(json_path, with_provenance(out))


@bench_group.command("vpp")
@click.option("--masks", "mask_counts", multiple=True, type=click.IntRange(1, 64), metavar="N",
              help="Movable masks in memory (repeatable).  [default: 1, 4, 8]")
@click.option("--repeats", default=300, show_default=True, type=click.IntRange(10, 100000), help="Timed scans per row.")
@click.option("--points", "n_points", default=20000, show_default=True, type=click.IntRange(100, 1000000),
              help="Lidar points per scan.")
@click.option("--seed", default=0, show_default=True, type=click.IntRange(0, 2**32 - 1))
@click.option("--cpu", type=click.IntRange(0, 1023), help="Pin the process to this core.")
@click.option("--first-answer", is_flag=True,
              help="Time the scans right after the first answer (masks captured before the tracker followed the "
                   "objects: their warped areas are counted), not the steady state.")
@click.option("--json", "json_path", type=click.Path(dir_okay=False, path_type=Path),
              help="Write the figures as JSON (checked before the run, written atomically after it).")
@click.option("--force", is_flag=True, help="Overwrite an existing --json file.")
def vpp_bench_command(*, mask_counts: tuple[int, ...], repeats: int, n_points: int, seed: int, cpu: int | None,
                      first_answer: bool, json_path: Path | None, force: bool) -> None:
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
    out = run_vpp_benchmark(counts, repeats, n_points, seed, cpu, echo=click.echo, first_answer=first_answer)
    if json_path is not None:
        atomic_write_json(json_path, with_provenance(out))


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
@click.option("--neupan", "neupan_path", type=click.Path(path_type=Path),
              help="Also time NeuPAN's own planner against ours: the folder of NeuPAN's source (the one that holds "
                   "its neupan/ package; GPL-3.0, never part of this repository), its dependencies installed.")
@click.option("--neupan-model", "neupan_model", type=click.Path(exists=True, dir_okay=False, path_type=Path),
              help="NeuPAN's DUNE model (.pth) for our footprint.  [default: NeuPAN's diff_robot_default, "
                   "trained for another footprint]")
@click.option("--neupan-repeats", default=100, show_default=True, type=click.IntRange(10, 100000),
              help="NeuPAN's warm steps per (horizon, points).")
@click.option("--neupan-cold-runs", default=20, show_default=True, type=click.IntRange(1, 1000),
              help="Fresh planners per (horizon, points) for the cold steps (their first 3 steps each).")
@click.option("--neupan-d-max", default=0.3, show_default=True, type=click.FloatRange(0.01, 10.0),
              help="NeuPAN's d_max (m), the distance up to which it rewards clearance; its corridor example's "
                   "1.0 exceeds the benchmark corridor's 0.34 m per side.")
@click.option("--neupan-autograd", is_flag=True,
              help="Step NeuPAN with autograd on, as its examples do (default: under torch.no_grad, its faster "
                   "way: a planning step needs no gradients).")
def planner_command(*, repeats: int, cvxpy_repeats: int, horizons: tuple[int, ...], point_counts: tuple[int, ...],
                    net_path: str | None, json_path: Path | None, force: bool, neupan_path: Path | None,
                    neupan_model: Path | None, neupan_repeats: int, neupan_cold_runs: int,
                    neupan_d_max: float, neupan_autograd: bool) -> None:
    """Planner step time (selection + net + QP, one thread) against points in range and horizon,
    with the share of each part and the constraint set's size, against cvxpy (ECOS, Clarabel);
    with --neupan, against NeuPAN's own planner too (hil_sim.bench.neupan_peer), warm and cold."""
    from calibration.extras import require
    from calibration.outputs import OutputPathError, atomic_write_json, check_output_path
    from hil_sim.bench.planner import HORIZONS, POINT_COUNTS, cap_warnings, print_planner_benchmark

    if cvxpy_repeats > 0:  # checked before the OSQP rows, which take minutes
        require("cvxpy", "ecos", "clarabel", what="dct bench planner (its cvxpy rows; --cvxpy-repeats 0 skips them)")
    if neupan_model is not None and neupan_path is None:
        raise InputError("--neupan-model needs --neupan PATH")
    if neupan_path is not None:  # also before the OSQP rows
        from hil_sim.bench.neupan_peer import SHIPPED_MODEL, NeupanUnavailable, import_neupan

        try:
            import_neupan(neupan_path)
        except NeupanUnavailable as exc:
            raise InputError(str(exc)) from exc
        if neupan_model is None and not (neupan_path / SHIPPED_MODEL).is_file():
            raise InputError(f"NeuPAN's DUNE model {neupan_path / SHIPPED_MODEL} is not a file (--neupan-model PATH)")
    if json_path is not None:
        try:
            check_output_path(json_path, what="--json", overwrite=force)
        except OutputPathError as exc:
            raise InputError(str(exc)) from exc
    horizons = tuple(sorted(set(horizons))) or HORIZONS
    point_counts = tuple(sorted(set(point_counts))) or POINT_COUNTS

    def progress(what: str) -> None:
        click.echo(f"... {what}", err=True)

    rows = print_planner_benchmark(
        echo=click.echo, repeats=repeats, cvxpy_repeats=cvxpy_repeats, distance_net_path=net_path,
        horizons=horizons, point_counts=point_counts, progress=progress,
    )
    out = {"rows": rows, "warnings": cap_warnings(rows)}
    if neupan_path is not None:
        from hil_sim.bench.neupan_peer import NeupanUnavailable, format_neupan_table, run_neupan_comparison

        try:
            neupan_rows = run_neupan_comparison(
                neupan_path=neupan_path, model_path=neupan_model, horizons=horizons, point_counts=point_counts,
                repeats=repeats, neupan_repeats=neupan_repeats, cold_runs=neupan_cold_runs, d_max_m=neupan_d_max,
                autograd=neupan_autograd,
                distance_net_path=net_path, progress=progress,
            )
        except NeupanUnavailable as exc:
            raise InputError(str(exc)) from exc
        click.echo(format_neupan_table(neupan_rows))
        out["neupan_rows"] = neupan_rows
    if json_path is not None:
        atomic_write_json(json_path, with_provenance(out))


def _campaign_options(func):
    """The options `dct bench paper` and `dct bench beacon` share (their callbacks take them as **options,
    _run_campaign_command's keywords)."""
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


def _run_campaign_command(name: str, *, seeds: int, first_seed: int, methods: str | None, only: tuple[str, ...],
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
        from calibration.extras import require

        require("ray", what="--ray (without it the campaign runs in local worker processes)")
    checked_output(json_path, "--json", [config_path], force)
    progress = RichProgress(name)
    try:
        result = run_campaign(name, method_list, seeds=seeds, first_seed=first_seed, workers=workers,
                              ray_address=ray_address, only=only,
                              config_path=str(config_path) if config_path is not None else None,
                              on_done=progress.done, on_start=progress.start, clock=clock)
    except CampaignError as exc:
        raise InputError(str(exc)) from None
    finally:
        progress.close()
    for line in format_table(result):
        click.echo(line)
    if json_path is not None:
        atomic_write_json(json_path, with_provenance(result))


@bench_group.command("paper")
@click.option("--table", type=click.Choice(["1", "2"]), required=True,
              help="1: DCT Table I (cases 1-3); 2: DCT Table II (layouts F4M0, F3M1, F2M2, F1M3, drawn per seed).")
@_campaign_options
def paper_command(*, table: str, **options) -> None:
    """The DCT paper's tables in the simulator: success, navigation time, average speed, navigation distance
    (plus fixed contacts, path cost, fragile damage, correcting events, deadline misses) for dct, all-fixed
    (NeuPAN-like), grid-astar (Ellis22-like) and fixed-labels, next to the paper's figures."""
    _run_campaign_command(f"table{table}", **options)


@bench_group.command("beacon")
@_campaign_options
def beacon_command(**options) -> None:
    """BEACON's four families (sparse, cluttered, collision-required, collision-shortcut), drawn per seed: the
    same figures per family and overall, next to BEACON's published success and path length."""
    _run_campaign_command("beacon", **options)


@bench_group.command("faults")
@click.option("--scenes", "scenes", multiple=True, metavar="NAME",
              help="Scenes (repeatable, or comma-separated).  [default: case3, corridor_boxes, gap_wedged]")
@click.option("--seeds", default=5, show_default=True, type=click.IntRange(1, 10000), help="Seeds per scene and fault.")
@click.option("--first-seed", default=0, show_default=True, type=click.IntRange(0, 2**32 - 1))
@click.option("--fault", "faults", multiple=True, metavar="NAME",
              help="Faults to run (repeatable, or comma-separated).  [default: every fault]")
@click.option("--start", "start_s", default=2.0, show_default=True, type=click.FloatRange(0.0, 600.0),
              help="Simulated seconds from the episode's start to the injection.")
@click.option("--duration", "duration_s", default=1.0, show_default=True, type=click.FloatRange(0.01, 600.0),
              help="How long each fault lasts (s).")
@click.option("--workers", type=click.IntRange(1, 256),
              help="Episodes in parallel (worker processes; the rows do not depend on it).  [default: all cores]")
@click.option("--ray", "ray_address", metavar="ADDRESS",
              help="Run the episodes as Ray tasks: 'local', 'auto', 'ray://HEAD:10001' or 'HEAD:6379' (the [ray] "
                   "extra).")
@click.option("--json", "json_path", type=click.Path(dir_okay=False, path_type=Path),
              help="Write the rows and the episodes as JSON (checked before the run, written atomically after it).")
@click.option("--force", is_flag=True, help="Overwrite an existing --json file.")
@click.option("--realtime", is_flag=True, help="Each episode as `dct hil run --realtime` (two processes on the wall "
              "clock, the simulator injecting the fault), one at a time; not deterministic.")
def faults_bench_command(*, scenes: tuple[str, ...], seeds: int, first_seed: int, faults: tuple[str, ...],
                         start_s: float, duration_s: float, workers: int | None, ray_address: str | None,
                         json_path: Path | None, force: bool, realtime: bool = False) -> None:
    """Every fault (docs/faults.md) on a few scenes in lockstep (or --realtime): per fault, how many episodes stopped and how
    soon after the injection (to the zero command the base obeyed), how soon it drove again after the fault,
    fixed contacts, goals reached, the stop reasons; a row whose reaction differs from the documented one is
    marked and the command exits 1."""
    from calibration.outputs import atomic_write_json
    from hil_sim.bench.campaign import default_workers
    from hil_sim.bench.faults import DEFAULT_SCENES, FaultCampaignError, format_fault_table, run_fault_campaign
    from hil_sim.episode.faults import FAULT_NAMES, LOCKSTEP_FAULT_NAMES
    from runtime.common.cli_support import checked_output

    def split(values: tuple[str, ...]) -> tuple[str, ...]:
        return tuple(x.strip() for v in values for x in v.split(",") if x.strip())

    scene_list = split(scenes) or DEFAULT_SCENES
    for scene in scene_list:
        check_scenario_and_output(scene, first_seed, None, False)
    if ray_address is not None:
        from calibration.extras import require

        require("ray", what="--ray (without it the campaign runs in local worker processes)")
    checked_output(json_path, "--json", [], force)
    try:
        result = run_fault_campaign(scenes=scene_list, seeds=seeds, first_seed=first_seed,
                                    faults=split(faults) or (FAULT_NAMES if realtime else LOCKSTEP_FAULT_NAMES), start_s=start_s, duration_s=duration_s,
                                    workers=workers or (1 if realtime else default_workers()),
                                    ray_address=ray_address, realtime=realtime,
                                    on_done=lambda r: click.echo(f"  {r['fault']} {r['scene']} seed {r['seed']}: "
                                                                 f"{'error' if 'error' in r else 'done'}", err=True))
    except FaultCampaignError as exc:
        raise InputError(str(exc)) from None
    for line in format_fault_table(result):
        click.echo(line)
    if json_path is not None:
        atomic_write_json(json_path, with_provenance(result))
    if result["differs"]:
        raise SystemExit(1)


@bench_group.command("replay")
@click.option("--scenario", default="case3", show_default=True)
@click.option("--seed", default=0, show_default=True, type=click.IntRange(0, 2**32 - 1))
@click.option("--planner", type=click.Choice(["dct", "all-fixed", "grid-astar"]), default=None,
              help="A preset in place of the config's.")
@click.option("--domain-id", type=click.IntRange(1, 232), help="The live run's DDS domain (default: a random one).")
@click.option("--out", "out_dir", type=click.Path(file_okay=False, path_type=Path), required=True,
              help="Folder for live.mcap, replay/ and latency.png.")
@click.option("--json", "json_path", type=click.Path(dir_okay=False, path_type=Path), help="Write the figures as JSON.")
@click.option("--force", is_flag=True, help="Overwrite an existing --json file.")
def replay_bench_command(*, scenario: str, seed: int, planner: str | None, domain_id: int | None, out_dir: Path,
                         json_path: Path | None, force: bool) -> None:
    """`dct replay`'s acceptance: a real-time episode recorded by the controller, then replayed; the replay's
    odometry against the live run's (max, mean), the replay's time against the recording's length, the
    recording's size per minute, the replay's latency report (and a screenshot of it with chromium)."""
    from calibration.outputs import atomic_write_json
    from hil_sim.bench.replay import replay_bench, summary_lines

    check_scenario_and_output(scenario, seed, json_path, force)
    result = replay_bench(scenario, out_dir, seed=seed, planner=planner, domain_id=domain_id,
                          echo=lambda s: click.echo(s, err=True))
    for line in summary_lines(result):
        click.echo(line)
    if json_path is not None:
        atomic_write_json(json_path, with_provenance(result))


@bench_group.command("soak")
@click.option("--minutes", default=60.0, show_default=True, type=click.FloatRange(1.0, 1440.0),
              help="How long to patrol (simulated minutes in lockstep, wall-clock minutes with --realtime).")
@click.option("--realtime", is_flag=True, help="The two processes of `dct hil run --realtime` on the wall clock (the "
              "controller records the run into --out).")
@click.option("--scene", default="patrol_people", show_default=True,
              help="A patrol scenario (goals:); the default has people, movable boxes and random goals.")
@click.option("--seed", default=0, show_default=True, type=click.IntRange(0, 2**32 - 1))
@click.option("--fault-every", "fault_every_s", default=180.0, show_default=True, type=click.FloatRange(10.0, 86400.0),
              help="Mean seconds between two injected faults (each one of docs/faults.md, for 1-5 s).")
@click.option("--no-faults", is_flag=True, help="Patrol without faults.")
@click.option("--config", "config_path", type=click.Path(exists=True, dir_okay=False, path_type=Path),
              help="Controller config YAML.")
@click.option("--out", "out_dir", type=click.Path(file_okay=False, path_type=Path), required=True,
              help="A new (or empty) folder: soak.json, soak.md, and with --realtime controller.mcap and latency.html. "
                   "The figures so far are written to soak.partial.json every 10 minutes.")
@click.option("--force", is_flag=True, help="Use --out even if it holds files (those of the same names are replaced).")
def soak_bench_command(*, minutes: float, realtime: bool, scene: str, seed: int, fault_every_s: float, no_faults: bool,
                       config_path: Path | None, out_dir: Path, force: bool) -> None:
    """Patrol a cluttered scene with people and movable boxes for MINUTES with faults injected at random, and
    measure what grows: every 10 s each process's resident memory, open files and threads (and the recorder's
    queue), every 10 minutes the tick p50/p99/max and deadline misses. Prints growth per hour, the tick p99 of
    each 10 minutes and its trend, goals reached and missed, contacts; writes soak.json and soak.md to --out."""
    from calibration.outputs import atomic_write_json, atomic_write_text
    from hil_sim.bench.soak import SoakError, SoakOptions, format_soak, run_soak
    from hil_sim.episode.patrol import PatrolError, with_duration
    from hil_sim.world.scenario import load_scenario

    check_scenario_and_output(scene, seed, None, False)
    try:
        with_duration(load_scenario(scene, seed=seed), minutes * 60.0)
    except PatrolError as exc:
        raise InputError(str(exc)) from None
    if out_dir.exists() and (not out_dir.is_dir() or (any(out_dir.iterdir()) and not force)):
        raise InputError(f"--out {out_dir}: exists and is not an empty folder (give --force to use it anyway)")
    out_dir.mkdir(parents=True, exist_ok=True)
    try:
        result = run_soak(SoakOptions(minutes=minutes, seed=seed, scene=scene, realtime=realtime,
                                      fault_every_s=fault_every_s, faults=not no_faults, out_dir=out_dir,
                                      config_path=config_path, force=force, echo=lambda s: click.echo(s, err=True)))
    except SoakError as exc:
        raise InputError(str(exc)) from None
    lines = format_soak(result)
    for line in lines:
        click.echo(line)
    atomic_write_json(out_dir / "soak.json", with_provenance(result))
    atomic_write_text(out_dir / "soak.md", "\n".join(lines) + "\n")
    (out_dir / "soak.partial.json").unlink(missing_ok=True)


@bench_group.command("mislabel")
@click.option("--seeds", default=10, show_default=True, type=click.IntRange(1, 1000))
@click.option("--first-seed", default=0, show_default=True, type=click.IntRange(0, 2**32 - 1))
@click.option("--workers", type=click.IntRange(1, 64), help="Worker processes (default: the CPUs, at most 8).")
@click.option("--ray", "ray_address", metavar="ADDRESS", help="Run the episodes on a Ray cluster (`auto`, or its address).")
@click.option("--json", "json_path", type=click.Path(dir_okay=False, path_type=Path), help="Write the figures as JSON.")
@click.option("--force", is_flag=True, help="Overwrite an existing --json file.")
def mislabel_bench_command(*, seeds: int, first_seed: int, workers: int | None, ray_address: str | None,
                           json_path: Path | None, force: bool) -> None:
    """The dangerous mislabel: the VLM calls a fixed cabinet (mislabel_cabinet) and a 30 kg look-alike box
    (push_30kg) movable. Per seed and per scene: the peak contact force on the object and how far the robot
    travelled against it, whether it was relabelled fixed, the correcting mode's stuck and back-off, the goal."""
    from calibration.outputs import atomic_write_json
    from hil_sim.bench.campaign import default_workers
    from hil_sim.bench.mislabel import format_mislabel, run_mislabel_campaign
    from runtime.common.cli_support import checked_output

    if ray_address is not None:
        from calibration.extras import require

        require("ray", what="--ray (without it the campaign runs in local worker processes)")
    checked_output(json_path, "--json", [], force)
    result = run_mislabel_campaign(seeds=seeds, first_seed=first_seed, workers=workers or default_workers(),
                                   ray_address=ray_address,
                                   on_done=lambda r: click.echo(f"  {r['scene']} seed {r['seed']}: "
                                                                f"{'error' if 'error' in r else 'done'}", err=True))
    for line in format_mislabel(result):
        click.echo(line)
    if json_path is not None:
        atomic_write_json(json_path, with_provenance(result))
