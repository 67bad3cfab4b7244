"""`dct run`: the command line of the controller process (runtime.app.run_process)."""
from __future__ import annotations

import threading
from pathlib import Path

import click

from runtime.app.run_inputs import DEFAULT_RECORD_PART_MIN, RunInputError, RunOptions, load_inputs
from runtime.app.run_process import install_stop_signals, run_controller, summary_line
from runtime.config import presets


class InputError(click.ClickException):
    exit_code = 2


_FILE = click.Path(dir_okay=False, path_type=Path)


@click.command("run")
@click.option("--robot", "robot_path", type=_FILE, help="Robot description YAML (default: the shipped LIMO).")
@click.option("--calibration", "calibration_path", type=_FILE,
              help="The robot's calibration file (camera intrinsics, wheel odometry); default: nominal values.")
@click.option("--config", "config_path", type=_FILE,
              help="Controller config YAML (default: the shipped one); its ros: and can_bus: sections.")
@click.option("--goal", nargs=3, type=float, metavar="X Y YAW",
              help="Goal in the odometry frame (m, m, rad). Default: the first PoseStamped on the goal topic.")
@click.option("--record", "record_path", type=_FILE,
              help="Record the run to this MCAP file (`dct report latency` reads it).")
@click.option("--record-part-minutes", "record_part_min", type=click.FloatRange(0.0, min_open=False),
              default=DEFAULT_RECORD_PART_MIN, show_default=True, metavar="MINUTES",
              help="Record in parts of this many minutes (NAME.mcap, NAME.part1.mcap, ...: the readers join "
                   "them), so that a long run's recording index does not grow in memory; 0: one file.")
@click.option("--json", "json_path", type=_FILE,
              help="Write the run's summary here at exit (state, tick and sensor-to-command latency).")
@click.option("--force", is_flag=True, help="Overwrite an existing --record or --json file.")
@click.option("--domain-id", type=click.IntRange(0, 232), help="Override ros.inputs.domain_id.")
@click.option("--middleware", type=click.Choice(["auto", "rclpy", "cyclonedds"]),
              help="Override ros.middleware (auto: rclpy when it imports, else cyclonedds).")
@click.option("--discovery", type=click.Choice(["subnet", "localhost"]),
              help="Override ros.discovery (localhost: only processes on this machine see the topics).")
@click.option("--can-interface", type=click.Choice(["socketcan", "limo_serial", "udp_multicast", "virtual"]),
              help="Override can_bus.interface (the channel then defaults for it).")
@click.option("--can-channel", help="Override can_bus.channel.")
@click.option("--can-port", type=click.IntRange(1, 65535), help="Override can_bus.udp_port (udp_multicast).")
@click.option("--planner", type=click.Choice(list(presets.PRESETS)), default=None,
              help="A preset in place of the config's planner and partition (dct: the MPC on the VLM partition; "
                   "all-fixed: the MPC on every point; grid-astar: the grid baseline; pure-pursuit: blind, only "
                   "with --allow-pure-pursuit).")
@click.option("--allow-pure-pursuit", is_flag=True,
              help="Let planner mode pure-pursuit run: no obstacle awareness (tests and benches only).")
@click.option("--normal-priority", is_flag=True,
              help="Do not ask for SCHED_FIFO / CPU pinning (config realtime:), e.g. beside a simulator.")
@click.option("--goal-wait", "goal_wait_s", type=click.FloatRange(0.0, None),
              help="Without --goal: give up after this many seconds without a goal (default: wait).")
@click.option("--resume-file", "resume_path", type=_FILE,
              help="Save the odometry frame and the goal here twice a second; at start, continue from a state "
                   "saved there within --resume-max-age (a restart after a crash: the goals given in the old "
                   "frame stay right). Without --goal, an unreached saved goal is driven on to.")
@click.option("--resume-max-age", "resume_max_age_s", type=click.FloatRange(0.0, 3600.0, min_open=True),
              default=60.0, show_default=True, metavar="SECONDS",
              help="A saved state older than this (wall clock) starts a new odometry frame.")
def run_command(**options) -> None:
    """The controller process: sensors over ROS 2 DDS, the base over CAN, the fixed-rate loop on the wall
    clock until SIGINT/SIGTERM (then: zero command, deactivate, flush, exit 0). Exit 2 on bad input."""
    for what, key in (("--robot", "robot_path"), ("--calibration", "calibration_path"), ("--config", "config_path")):
        p = options[key]
        if p is not None and not p.is_file():
            raise InputError(f"{what}: {p}: no such file")
    opts = RunOptions(**{**options, "goal": tuple(options["goal"]) if options["goal"] else None})
    stop = threading.Event()
    install_stop_signals(stop)
    try:
        summary = run_controller(opts, load_inputs(opts), stop, echo=lambda s: click.echo(s, err=True))
    except RunInputError as exc:
        raise InputError(str(exc)) from None
    if summary.get("state") != "NOT_STARTED":
        click.echo(summary_line(summary), err=True)
        from runtime.odometry.icp_settings import gate_lines

        for line in gate_lines(summary.get("controller", {}).get("odometry", {}).get("icp_range_gate")):
            click.echo(f"dct run: {line}", err=True)
