"""Every preflight check in order (`run_preflight`), the options that choose them, the summary."""
from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from typing import Any

from runtime.app.preflight.can_bus import check_can
from runtime.app.preflight.check import Check
from runtime.app.preflight.computer import DEFAULT_MIN_FREE_GB, check_clock_sync, check_cpus, check_disk, check_realtime
from runtime.app.preflight.files import check_files
from runtime.app.preflight.ros_setup import (
    ManifestError, check_discovery, check_middleware, check_ros_install, check_security, check_socket_buffers,
    default_manifest,
    discovery_reach, read_ros_install, resolve,
)
from runtime.app.preflight.topics import check_topics, expected_rates_hz, topics_from_config

SKIPPABLE = ("can", "base", "sensors", "clock", "model")


@dataclass
class PreflightOptions:
    robot: str | None = None
    calibration: str | None = None
    config: str | None = None
    can_interface: str | None = None  # None: the config's can_bus when --config is given, else socketcan
    can_channel: str | None = None
    can_udp_port: int | None = None
    ros_domain: int | None = None
    listen_s: float = 2.0
    log_dir: str = "."
    min_free_gb: float = DEFAULT_MIN_FREE_GB
    sys_root: str = "/"
    skip: tuple[str, ...] = ()
    #: the bundle's MANIFEST.json (how ROS 2 was installed); None: beside this venv, when there is one
    manifest: str | None = None


def can_settings(opts: PreflightOptions, config: Any) -> tuple[dict[str, Any], str]:
    """The bus to check and where it came from. With --config and no --can-* option: the config's
    can_bus (the bus `dct run --config` opens); the command line's options override it as they do
    in `dct run`; without --config, the command line's (socketcan by default)."""
    cli_given = any(v is not None for v in (opts.can_interface, opts.can_channel, opts.can_udp_port))
    from_config = opts.config is not None and config is not None
    if from_config:
        bus = config.can_bus.model_dump()
        bus = {k: bus[k] for k in ("interface", "channel", "udp_port", "serial_baud")}
    else:
        bus = {"interface": "socketcan", "channel": None, "udp_port": None, "serial_baud": None}
    if opts.can_interface is not None:
        bus.update(interface=opts.can_interface, channel=None, udp_port=None, serial_baud=None)
    if opts.can_channel is not None:
        bus["channel"] = opts.can_channel
    if opts.can_udp_port is not None:
        bus["udp_port"] = opts.can_udp_port
    if from_config and not cli_given:
        source = f"bus from {opts.config} can_bus"
    elif from_config:
        source = f"bus from {opts.config} can_bus with the command line's --can-* options"
    else:
        source = "bus from the command line" + ("" if cli_given else " (default socketcan)") + (
            "; the --config did not load" if opts.config is not None else "")
    return bus, source


def run_preflight(opts: PreflightOptions, echo: Callable[[str], None] | None = None) -> list[Check]:
    """Every check, in order; each line is echoed as soon as it is known."""
    checks: list[Check] = []

    def add(items: Check | list[Check]) -> None:
        for c in [items] if isinstance(items, Check) else items:
            checks.append(c)
            if echo is not None:
                echo(c.line())

    def skipped(name: str, what: str) -> Check:
        return Check(name, "WARN", f"not checked (--skip {what})", f"run without --skip {what} before driving")

    files = check_files(opts.robot, opts.calibration, opts.config, load_net="model" not in opts.skip)
    add(files.checks)
    bitrate = files.robot.can.bitrate_bps if files.robot is not None else 500_000
    if "can" in opts.skip:
        add([skipped("can_link", "can"), skipped("base", "can")])
    else:
        bus, source = can_settings(opts, files.config)
        can_checks = check_can(bus["interface"], bus["channel"], bitrate_bps=bitrate, udp_port=bus["udp_port"],
                               serial_baud=bus["serial_baud"], sys_root=opts.sys_root,
                               check_base="base" not in opts.skip)
        add([replace(c, message=f"{c.message} ({source})") if c.name == "can_link" else c for c in can_checks])
        if "base" in opts.skip:
            add(skipped("base", "base"))
    ros = ros_config(files.config, opts.ros_domain)
    add(ros_setup_checks(ros, opts.manifest, opts.sys_root))
    if "sensors" in opts.skip:
        add(skipped("topics", "sensors"))
    else:
        required = ["lidar", "imu"] + (["camera"] if files.config is not None and files.config.uses_camera
                                       else [])
        topics = topics_from_config(files.config, opts.ros_domain)
        add(check_topics(topics, expected_rates_hz(files.config), listen_s=opts.listen_s, required=required,
                         options=ros.transport_options("dct_preflight"),
                         after_listen=_live_calibration(files, topics)))
    add(skipped("clock_sync", "clock") if "clock" in opts.skip else check_clock_sync())
    realtime = getattr(files.config, "realtime", None)
    add(check_cpus(realtime, sys_root=opts.sys_root))
    add(check_realtime(realtime))
    add(check_disk(opts.log_dir, opts.min_free_gb))
    return checks


def _live_calibration(files: Any, topics: Any):
    """The calibration checks on the last samples heard (runtime.app.preflight.calibration_live);
    None when there is no calibration to check (no robot description, a file that does not fit)."""
    if files.sensors is None:
        return None
    from runtime.app.preflight.calibration_live import check_calibration_live

    return lambda last: check_calibration_live(last, topics, files.sensors, files.config)


def ros_config(config: Any, domain_id: int | None = None):
    """The config's `ros:` section (the defaults when the config did not load), on `domain_id`."""
    from runtime.io.ros.settings import RosConfig

    ros = getattr(config, "ros", None)
    ros = ros if isinstance(ros, RosConfig) else RosConfig()
    if domain_id is not None:
        ros = ros.model_copy(update={"inputs": ros.inputs.model_copy(update={"domain_id": int(domain_id)})})
    return ros


def ros_setup_checks(ros: Any, manifest: str | None, sys_root: str = "/") -> list[Check]:
    """`ros:install` (when there is a bundle's manifest), `ros:middleware`, `ros:discovery`, `ros:security`,
    `ros:buffers`."""
    from runtime.io.ros.transport import rclpy_available

    checks = []
    path = manifest if manifest is not None else (default_manifest() if default_manifest().is_file() else None)
    if path is not None:
        try:
            checks.append(check_ros_install(read_ros_install(path), ros))
        except ManifestError as exc:
            checks.append(Check("ros:install", "FAIL", str(exc), "pass the installed bundle's --manifest "
                                "(TARGET/MANIFEST.json)"))
    middleware = resolve(ros, rclpy_available)[0]
    checks.append(check_middleware(ros))
    checks.append(check_discovery(ros, middleware))
    checks.append(check_security(ros, middleware, discovery_reach(ros, middleware)[0]))
    checks.append(check_socket_buffers(middleware, sys_root))
    return checks


def summary_line(checks: Sequence[Check]) -> str:
    n = {s: sum(c.status == s for c in checks) for s in ("PASS", "WARN", "FAIL")}
    verdict = "ready to drive" if n["FAIL"] == 0 else "NOT ready to drive"
    return f"preflight: {verdict} ({n['PASS']} pass, {n['WARN']} warn, {n['FAIL']} fail)"


def checks_json(checks: Sequence[Check]) -> dict[str, Any]:
    return {"ok": all(c.ok for c in checks), "checks": [c.as_json() for c in checks]}
