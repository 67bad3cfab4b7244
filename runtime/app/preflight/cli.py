"""`dct preflight`: the command (the checks are runtime.app.preflight.run)."""
from __future__ import annotations

import click

from runtime.app.preflight.computer import DEFAULT_MIN_FREE_GB
from runtime.app.preflight.run import SKIPPABLE, PreflightOptions, checks_json, run_preflight, summary_line


@click.command(name="preflight")
@click.option("--robot", "robot", type=click.Path(dir_okay=False), default=None,
              help="robot description YAML (default: the shipped LIMO)")
@click.option("--calibration", type=click.Path(dir_okay=False), default=None, help="calibration YAML")
@click.option("--config", "config", type=click.Path(dir_okay=False), default=None,
              help="controller config YAML (default: the shipped one)")
@click.option("--can-interface", type=click.Choice(["socketcan", "udp_multicast", "virtual", "limo_serial"]),
              default=None, help="default: the --config's can_bus when --config is given, else socketcan")
@click.option("--can-channel", default=None,
              help="can0, a multicast group or a serial port (default per interface, or the --config's can_bus)")
@click.option("--can-udp-port", type=click.IntRange(1, 65535), default=None, help="udp_multicast port")
@click.option("--ros-domain", type=click.IntRange(0, 232), default=None,
              help="DDS domain of the sensor topics (default: the config's, else 0)")
@click.option("--listen-s", type=click.FloatRange(0.2, 60.0), default=2.0, show_default=True,
              help="how long to listen to each sensor topic")
@click.option("--log-dir", type=click.Path(file_okay=False), default=".", show_default=True,
              help="where the run's logs go (free space is checked)")
@click.option("--min-free-gb", type=click.FloatRange(0.0), default=DEFAULT_MIN_FREE_GB, show_default=True)
@click.option("--skip", type=click.Choice(SKIPPABLE), multiple=True,
              help="leave a check out (reported as WARN: not checked)")
@click.option("--manifest", type=click.Path(dir_okay=False), default=None,
              help="the installed bundle's MANIFEST.json: which ROS 2 it carries, checked as ros:install "
                   "(default: the one beside this venv, when there is one)")
@click.option("--json", "json_path", type=click.Path(dir_okay=False), default=None,
              help='write {"checks": [{"name", "ok", "message"}, ...]} here')
@click.option("--sys-root", default="/", hidden=True, help="root of /sys (tests)")
@click.pass_context
def preflight_command(ctx, *, robot, calibration, config, can_interface, can_channel, can_udp_port, ros_domain,
                      listen_s, log_dir, min_free_gb, skip, manifest, json_path, sys_root) -> None:
    """Check this computer, the robot's files, CAN, the base and the sensors before driving.

    One line per check (PASS / WARN / FAIL, and how to fix it). Exit code 0 only when no
    check fails; WARNs do not fail.
    """
    from calibration.outputs import OutputPathError, atomic_write_json, check_output_path

    if json_path is not None:
        try:
            check_output_path(json_path, what="--json", inputs=[robot, calibration, config])
        except OutputPathError as exc:
            raise click.ClickException(str(exc)) from None
    opts = PreflightOptions(robot=robot, calibration=calibration, config=config, can_interface=can_interface,
                            can_channel=can_channel, can_udp_port=can_udp_port, ros_domain=ros_domain,
                            listen_s=listen_s, log_dir=log_dir, min_free_gb=min_free_gb, sys_root=sys_root,
                            skip=tuple(skip), manifest=manifest)
    checks = run_preflight(opts, echo=click.echo)
    click.echo(summary_line(checks))
    if json_path is not None:
        atomic_write_json(json_path, checks_json(checks))
    ctx.exit(0 if all(c.ok for c in checks) else 1)
