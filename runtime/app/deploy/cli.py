"""`dct deploy`: the offline bundle for the robot's computer (runtime.app.deploy.bundle)."""
from __future__ import annotations

import click


@click.group(name="deploy")
def deploy_group() -> None:
    """Deployment to the robot's computer: an offline install bundle."""


@deploy_group.command(name="bundle")
@click.option("--robot", type=click.Path(exists=True, dir_okay=False), default=None,
              help="robot description YAML (default: the shipped LIMO)")
@click.option("--calibration", type=click.Path(exists=True, dir_okay=False), default=None,
              help="calibration YAML (default: a NOMINAL one made from the robot description)")
@click.option("--config", "config", type=click.Path(exists=True, dir_okay=False), default=None,
              help="controller config YAML (default: the shipped one)")
@click.option("--out", required=True, type=click.Path(dir_okay=False), help="the archive to write, *.tar.gz")
@click.option("--force", is_flag=True, help="replace an existing --out")
@click.option("--ros", "ros", type=click.Choice(["wheels", "system", "none"]), default="wheels", show_default=True,
              help="ROS 2 for the controller: wheels (rclpy and the message packages in the bundle), system (the "
                   "robot's ROS 2 Jazzy, sourced from /opt/ros/jazzy), none (cyclonedds only)")
@click.option("--python-version", default=None,
              help="the robot's CPython (X.Y); default 3.11, or 3.12 with --ros system (what Jazzy's rclpy is for)")
@click.option("--glibc", default="2.35", show_default=True, help="the robot's glibc (oldest manylinux accepted)")
@click.option("--can-interface", default="socketcan", show_default=True, help="for the unit's preflight")
@click.option("--can-channel", default="can0", show_default=True, help="for the unit's preflight")
@click.option("--service-cpus", default=None, help="the unit's CPUAffinity (default: '0 1' plus realtime.cpus)")
@click.option("--watchdog-s", type=click.FloatRange(0.5, 600), default=2.0, show_default=True,
              help="the unit's WatchdogSec")
@click.option("--compress", "compresslevel", type=click.IntRange(0, 9), default=1, show_default=True,
              help="gzip level (the wheels inside are already compressed)")
def bundle_command(*, robot, calibration, config, out, force, ros, python_version, glibc, can_interface, can_channel,
                   service_cpus, watchdog_s, compresslevel) -> None:
    """Build the offline install bundle: wheelhouse, robot files, systemd unit, install.sh, manifest.

    Unpacks into one folder; `FOLDER/install.sh TARGET` installs offline and leaves
    TARGET/venv/bin/dct. Needs this machine to reach the package index (pip download).
    --ros wheels (the default) carries ROS 2 Jazzy's rclpy, so the robot needs no ROS 2 of its
    own; --ros system uses the robot's; the choice is recorded in MANIFEST.json for dct preflight.
    """
    import re
    import time
    from pathlib import Path

    from runtime.app.deploy.bundle import (
        DEFAULT_PYTHON, ROS_DISTRO, ROS_DISTRO_PYTHON, BundleError, BundleInputs, build_bundle,
    )

    if python_version is None:
        python_version = ROS_DISTRO_PYTHON[ROS_DISTRO] if ros == "system" else DEFAULT_PYTHON
    if not re.fullmatch(r"3\.\d{1,2}", python_version):
        raise click.ClickException(f"--python-version {python_version!r}: give X.Y, e.g. 3.11")
    if not re.fullmatch(r"2\.\d{1,2}", glibc):
        raise click.ClickException(f"--glibc {glibc!r}: give 2.X, e.g. 2.35")
    t0 = time.perf_counter()
    inputs = BundleInputs(*(Path(p) if p else None for p in (robot, calibration, config)))
    try:
        res = build_bundle(out, inputs, force=force, python_version=python_version, glibc=glibc,
                           can_interface=can_interface, can_channel=can_channel, service_cpus=service_cpus,
                           watchdog_s=watchdog_s, compresslevel=compresslevel, ros=ros, echo=click.echo)
    except BundleError as exc:
        raise click.ClickException(str(exc)) from None
    for note in res.notes:
        click.echo(f"note: {note}")
    steps = ", ".join(f"{k.removesuffix('_s')} {v:.1f} s" for k, v in res.seconds.items())
    click.echo(f"bundle: {res.path} ({res.size_bytes / 1e6:.0f} MB, {res.files} files, {res.wheels} wheels) "
               f"in {time.perf_counter() - t0:.1f} s ({steps})")
    click.echo(f"install: tar xzf {res.path.name} && ./{res.folder}/install.sh /opt/dct")
