"""`dct preflight`: is this computer ready to drive this robot? Checked before driving.

Each check gives one line, PASS / WARN / FAIL, what was seen and, when not PASS, how to fix it.
A FAIL is something the robot cannot drive without (a file that does not load, a distance net
for another footprint, a CAN bus that is down, a base that does not answer, a silent sensor,
too little disk for the logs); a WARN is something that makes the drive worse but not unsafe
(no clock sync, a power-saving CPU governor, no SCHED_FIFO: the loop then runs SCHED_OTHER and
counts its lateness as always). The exit code is 0 only when no check FAILs.

Checks, in order (names as in the JSON):
- files: `robot`, `config`, `calibration` (for this robot's camera: robot name, image size,
  lidar->camera extrinsic close to the robot description's mounts), `distance_net` (loads and
  its footprint is the robot's, models.distance_net.DistanceNet.load);
- CAN: `can_link` (SocketCAN: /sys/class/net/<if>/operstate up and the bit rate from
  `ip -details -json link show` equal to the robot description's; udp_multicast / virtual /
  limo_serial: the bus opens), `base` (0x221 within 100 ms of the enable frame 0x421 that the
  controller sends at start, then 0x211: not in E-stop, no error that stops the controller);
- sensors: `topic:<stream>` for the lidar, IMU and camera topics of the config's `ros:` section
  (runtime.io.ros RosInputConfig; without one, DEFAULT_TOPICS), heard for `listen_s` and
  judged against their nominal rates; the last sample of each must decode;
- host: `clock_sync`, `cpus`, `cpu_governor`, `sched_fifo`, `cpu_affinity`, `disk`.

Everything that touches the machine takes its source as an argument (the /sys root, the `ip`
and clock commands, the bus), so that tests can fake a robot computer.
"""
from __future__ import annotations

import glob
import json
import math
import os
import shutil
import subprocess
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Literal

Status = Literal["PASS", "WARN", "FAIL"]

#: Nominal sensor rates (Hz) of the LIMO-class robot (DESIGN.md section 2) where the config has
#: none: camera 15-30 Hz, IMU 200 Hz; the lidar's comes from inputs.lidar.frame_period_s.
NOMINAL_RATE_HZ = {"camera": 15.0, "imu": 200.0}
#: A topic slower than this share of its nominal rate FAILs; slower than WARN_RATE_SHARE WARNs.
FAIL_RATE_SHARE = 0.5
WARN_RATE_SHARE = 0.8
#: The base must answer the enable frame with 0x221 within this (DESIGN: feedback every 20 ms).
BASE_ANSWER_TIMEOUT_S = 0.100
#: After the first 0x221, how long to wait for 0x211 (sent every 100 ms).
SYSTEM_STATE_WAIT_S = 0.35
#: The calibration's lidar->camera extrinsic may differ from the robot description's mounts by
#: this much before preflight warns (a mount moved, or the calibration is for another robot).
EXTRINSIC_WARN_M = 0.05
EXTRINSIC_WARN_DEG = 5.0
#: Free disk below this FAILs (the recorder drops records on a full disk, but a drive without
#: its log cannot be analysed); below WARN_DISK_FACTOR x this WARNs.
DEFAULT_MIN_FREE_GB = 1.0
WARN_DISK_FACTOR = 4.0

SOCKETCAN_UP_FIX = "sudo ip link set {ch} down; sudo ip link set {ch} up type can bitrate {bitrate}"


@dataclass(frozen=True)
class Check:
    """One preflight result. `fix` says how to make it PASS (shown unless it passed)."""

    name: str
    status: Status
    message: str
    fix: str | None = None

    @property
    def ok(self) -> bool:
        return self.status != "FAIL"

    def text(self) -> str:
        """The message and, unless it passed, the fix."""
        return self.message if self.status == "PASS" or not self.fix else f"{self.message}; fix: {self.fix}"

    def line(self) -> str:
        return f"{self.status:<4}  {self.name:<16} {self.text()}"

    def as_json(self) -> dict[str, Any]:
        return {"name": self.name, "ok": self.ok, "status": self.status, "message": self.text()}


def _one_line(exc: BaseException) -> str:
    return " ".join(str(exc).split()) or type(exc).__name__


# ----------------------------------------------------------------------------- files


@dataclass
class LoadedFiles:
    robot: Any = None
    config: Any = None
    calibration: Any = None
    checks: list[Check] = field(default_factory=list)


def check_files(robot_path: str | Path | None, calibration_path: str | Path | None,
                config_path: str | Path | None, *, load_net: bool = True) -> LoadedFiles:
    """Load and cross-check the robot description, controller config, calibration and distance net."""
    from calibration.calibration_file import load_calibration
    from calibration.errors import ConfigFileError
    from calibration.robot_description import load_robot_description
    from runtime.config import load_controller_config

    out = LoadedFiles()
    try:
        out.robot = load_robot_description(robot_path)
        out.checks.append(Check("robot", "PASS", f"robot description '{out.robot.name}' "
                                f"{robot_path or '(shipped LIMO description)'}: valid"))
    except ConfigFileError as exc:
        out.checks.append(Check("robot", "FAIL", _one_line(exc), "correct the robot description file"))
    try:
        out.config = load_controller_config(config_path)
        out.checks.append(Check("config", "PASS", f"controller config {config_path or '(shipped default)'}: valid, "
                                f"planner {out.config.preset}"))
    except ConfigFileError as exc:
        out.checks.append(Check("config", "FAIL", _one_line(exc), "correct the controller config file"))
    needs_camera = out.config is not None and out.config.uses_camera
    if calibration_path is None:
        out.checks.append(Check("calibration", "FAIL" if needs_camera else "WARN", "no calibration file given",
                                "pass --calibration (made by `dct calibrate`)" + (
                                    "; planner mode dct projects lidar points into the camera" if needs_camera else "")))
    else:
        try:
            cal = load_calibration(calibration_path)
            out.calibration = cal
            out.checks.append(_calibration_matches_robot(cal, out.robot, calibration_path, needs_camera))
        except ConfigFileError as exc:
            out.checks.append(Check("calibration", "FAIL", _one_line(exc), "recalibrate with `dct calibrate`"))
    out.checks.append(_check_distance_net(out.robot, out.config) if load_net else
                      Check("distance_net", "WARN", "not checked", "run without skipping the model check"))
    return out


def _calibration_matches_robot(cal: Any, robot: Any, path: Any, needs_camera: bool) -> Check:
    if robot is None:
        return Check("calibration", "FAIL", f"calibration {path}: valid, but cannot be compared (no robot description)",
                     "fix the robot description first")
    cam = robot.sensors.camera
    problems = []
    if cal.robot != robot.name:
        problems.append(f"it is for robot '{cal.robot}', not '{robot.name}'")
    if (cal.camera.width_px, cal.camera.height_px) != (cam.width_px, cam.height_px):
        problems.append(f"its image is {cal.camera.width_px}x{cal.camera.height_px} px, the robot's camera "
                        f"{cam.width_px}x{cam.height_px} px")
    if problems:
        return Check("calibration", "FAIL", f"calibration {path}: " + "; ".join(problems),
                     f"use the calibration made on robot '{robot.name}' (dct calibrate)")
    if cal.lidar_to_camera is None:
        return Check("calibration", "FAIL" if needs_camera else "WARN",
                     f"calibration {path}: camera intrinsics for '{robot.name}', but no lidar_to_camera extrinsic",
                     "run `dct calibrate extrinsics`")
    import numpy as np

    T_base_cam = robot.sensors.camera.mount.transform()
    T_base_lidar = robot.sensors.lidar.mount.transform()
    expected = np.linalg.inv(T_base_cam) @ T_base_lidar
    T = cal.T_cam_lidar()
    dt = float(np.linalg.norm(T[:3, 3] - expected[:3, 3]))
    cos = (np.trace(expected[:3, :3].T @ T[:3, :3]) - 1.0) / 2.0
    dr = math.degrees(math.acos(max(-1.0, min(1.0, cos))))
    msg = (f"calibration {path}: for '{robot.name}' camera {cam.width_px}x{cam.height_px}; lidar->camera "
           f"{dt * 100:.1f} cm / {dr:.1f} deg from the robot description's mounts")
    if dt > EXTRINSIC_WARN_M or dr > EXTRINSIC_WARN_DEG:
        return Check("calibration", "WARN", msg + f" (more than {EXTRINSIC_WARN_M * 100:g} cm / {EXTRINSIC_WARN_DEG:g} deg)",
                     "check the sensor mounts, or the robot description's sensors section, and recalibrate")
    method = str(cal.provenance.method)
    if "nominal" in method.lower():
        return Check("calibration", "WARN", msg + f"; nominal values, not measured ({method})",
                     "calibrate the camera on this robot (`dct calibrate`)")
    return Check("calibration", "PASS", msg)


def distance_net_path(config: Any) -> str | None:
    return None if config is None else config.planner.distance_net_path


def _check_distance_net(robot: Any, config: Any) -> Check:
    if config is not None and not config.uses_distance_net:
        return Check("distance_net", "PASS", f"not used (planner {config.preset})")
    if robot is None:
        return Check("distance_net", "FAIL", "not checked: no valid robot description", "fix the robot description")
    from models.distance_net import DistanceNet, shipped_artifact_path
    from models.errors import DistanceNetError, FootprintMismatchError

    path = distance_net_path(config)
    shown = path or f"{shipped_artifact_path()} (shipped)"
    try:
        net = DistanceNet.load(path, robot=robot)
    except FootprintMismatchError as exc:
        return Check("distance_net", "FAIL", f"wrong model footprint: {_one_line(exc)}",
                     f"point planner.distance_net_path at the net trained for '{robot.name}'")
    except (DistanceNetError, OSError, ValueError) as exc:
        return Check("distance_net", "FAIL", _one_line(exc), "reinstall the bundle or retrain: dct models train-distance")
    fp = net.metadata.get("footprint", {})
    return Check("distance_net", "PASS", f"{shown}: footprint {fp.get('length_m')} x {fp.get('width_m')} m "
                 f"matches '{robot.name}', integrity verified")


# ----------------------------------------------------------------------------- CAN


def _ip_link_json(channel: str) -> str | None:
    if shutil.which("ip") is None:
        return None
    try:
        done = subprocess.run(["ip", "-details", "-json", "link", "show", channel], capture_output=True,
                              text=True, timeout=5)
    except (OSError, subprocess.SubprocessError):
        return None
    return done.stdout if done.returncode == 0 else None


def check_socketcan_link(channel: str, bitrate_bps: int, *, sys_root: str | Path = "/",
                         ip_link_json: Callable[[str], str | None] = _ip_link_json) -> Check:
    """SocketCAN interface `channel` up at `bitrate_bps` (read from /sys and `ip -details -json`)."""
    fix_up = SOCKETCAN_UP_FIX.format(ch=channel, bitrate=bitrate_bps)
    net = Path(sys_root) / "sys" / "class" / "net" / channel
    if not net.is_dir():
        have = sorted(p.name for p in net.parent.glob("*")
                      if (p / "type").is_file() and (p / "type").read_text().strip() == "280")  # ARPHRD_CAN
        return Check("can_link", "FAIL", f"no network interface {channel}"
                     + (f" (CAN interfaces here: {', '.join(have)})" if have else " (no CAN interface here)"),
                     "plug in the CAN adapter, load its driver (`modprobe gs_usb` / `can_raw`), or pass --can-channel")
    operstate = _read(net / "operstate") or "?"
    flags = int(_read(net / "flags") or "0", 16)
    up = operstate == "up" or (operstate == "unknown" and flags & 0x1)
    if not up:
        return Check("can_link", "FAIL", f"CAN down: {channel} operstate is {operstate}", fix_up)
    bitrate, state = None, None
    raw = ip_link_json(channel)
    if raw:
        try:
            info = json.loads(raw)[0].get("linkinfo", {}).get("info_data", {})
            bitrate = info.get("bittiming", {}).get("bitrate")
            state = info.get("state")
        except (ValueError, IndexError, AttributeError, TypeError):
            pass
    if state == "BUS-OFF":
        return Check("can_link", "FAIL", f"CAN {channel} is up but BUS-OFF (wiring, termination or bit rate)",
                     "check the CAN wiring and 120 ohm termination, then " + fix_up)
    if bitrate is None:
        return Check("can_link", "WARN", f"{channel} up; bit rate unknown (`ip -details -json link show` gave none)",
                     f"check by hand: ip -details link show {channel} (must say bitrate {bitrate_bps})")
    if int(bitrate) != int(bitrate_bps):
        return Check("can_link", "FAIL", f"CAN {channel} is at {bitrate} bit/s, the base talks at {bitrate_bps}", fix_up)
    extra = f", state {state}" if state else ""
    warn = state is not None and state not in ("ERROR-ACTIVE",)
    return Check("can_link", "WARN" if warn else "PASS", f"{channel} up at {bitrate} bit/s{extra}",
                 "check the wiring (error counters: ip -details -statistics link show)" if warn else None)


def _read(path: Path) -> str | None:
    try:
        return path.read_text().strip()
    except OSError:
        return None


def check_base_answers(bus: Any, *, timeout_s: float = BASE_ANSWER_TIMEOUT_S,
                       system_wait_s: float = SYSTEM_STATE_WAIT_S) -> Check:
    """Send the enable frame (0x421 = CAN command mode, as the controller does at start; it does
    not move the wheels) and wait for the base's 0x221; then read 0x211 for E-stop and errors."""
    from firmware_bridge import protocol as p
    from firmware_bridge.base_driver import AgileXBaseDriver
    from runtime.io.hardware import STOPPING_ERRORS

    driver = AgileXBaseDriver(bus, time.monotonic)
    driver.discard_pending()
    t0 = time.monotonic()
    try:
        driver.enable()
    except Exception as exc:  # noqa: BLE001 - python-can raises CanError / OSError per interface
        return Check("base", "FAIL", f"cannot send the enable frame 0x421: {_one_line(exc)}",
                     "check the CAN link (see can_link)")
    answer_s = None
    deadline = t0 + max(timeout_s, system_wait_s)
    while time.monotonic() < deadline:
        driver.poll()
        motion = driver.feedback.motion
        if answer_s is None and motion is not None:
            answer_s = motion.stamp_s - t0
        if answer_s is not None and driver.vehicle_state is not None:
            break
        if answer_s is None and time.monotonic() > t0 + timeout_s:
            break
        time.sleep(0.002)
    if answer_s is None or answer_s > timeout_s:
        seen = driver.feedback.frames_received
        return Check("base", "FAIL", f"the base did not answer: no 0x221 within {timeout_s * 1000:.0f} ms of 0x421"
                     f" ({seen} other frames heard)",
                     "power the base on, check the CAN cable to the motor controller and the bit rate")
    msg = f"0x221 {answer_s * 1000:.1f} ms after 0x421"
    if driver.vehicle_state is None:
        return Check("base", "WARN", msg + f"; no 0x211 within {system_wait_s * 1000:.0f} ms (state unknown)",
                     "check the base firmware (0x211 every 100 ms)")
    if driver.vehicle_state == p.VEHICLE_STATE_ESTOP:
        return Check("base", "FAIL", msg + "; the base reports E-stop", "release the emergency stop")
    code = driver.error_code or 0
    if code & STOPPING_ERRORS:
        return Check("base", "FAIL", msg + f"; base error 0x{code:04X}: {', '.join(driver.errors_active)}",
                     "fix the base fault (battery, motor driver, motor link) and power-cycle it")
    return Check("base", "PASS", msg + f"; 0x211 state normal, control mode {driver.control_mode_name}")


def check_can(interface: str, channel: str | None, *, bitrate_bps: int, udp_port: int | None = None,
              sys_root: str | Path = "/", ip_link_json: Callable[[str], str | None] = _ip_link_json,
              check_base: bool = True, serial_baud: int | None = None) -> list[Check]:
    """`can_link` and `base` for any bus interface."""
    import pydantic

    from firmware_bridge.buses import BusConfig, BusOpenError, open_bus

    kw: dict[str, Any] = {"interface": interface, "channel": channel, "bitrate": bitrate_bps}
    if udp_port is not None:
        kw["udp_port"] = udp_port
    if serial_baud is not None:
        kw["serial_baud"] = serial_baud
    try:
        cfg = BusConfig(**kw)
    except pydantic.ValidationError as exc:
        msg = "; ".join(str(e["msg"]).removeprefix("Value error, ") for e in exc.errors())
        return [Check("can_link", "FAIL", f"bad CAN settings: {msg}", "correct --can-interface / --can-channel")]
    checks = []
    if cfg.interface == "socketcan":
        link = check_socketcan_link(cfg.channel, bitrate_bps, sys_root=sys_root, ip_link_json=ip_link_json)
        if link.status == "FAIL":
            return [link, Check("base", "FAIL", "not checked: the CAN link is not usable", "see can_link")]
        checks.append(link)
    try:
        bus = open_bus(cfg)
    except BusOpenError as exc:
        fix = (SOCKETCAN_UP_FIX.format(ch=cfg.channel, bitrate=bitrate_bps) if cfg.interface == "socketcan"
               else "check --can-interface / --can-channel")
        return checks + [Check("can_link", "FAIL", f"CAN down: {_one_line(exc)}", fix),
                         Check("base", "FAIL", "not checked: the bus does not open", "see can_link")]
    try:
        if cfg.interface != "socketcan":
            checks.append(Check("can_link", "PASS", f"{cfg.interface} bus on {cfg.channel!r} opens"))
        if check_base:
            checks.append(check_base_answers(bus))
    finally:
        bus.shutdown()
    return checks


# ----------------------------------------------------------------------------- sensor topics


def default_topics(domain_id: int = 0):
    """The topics a LIMO with a Livox Mid-360 and a ROS 2 camera driver publishes, for configs
    without a `ros:` section (livox_ros_driver2 CustomMsg, the driver's IMU, an image_raw camera)."""
    from runtime.io.ros.receiver import CameraTopic, ImuTopic, LidarTopic, RosInputConfig

    return RosInputConfig(domain_id=domain_id,
                          lidar=LidarTopic(topic="/livox/lidar", type="livox_ros_driver2/msg/CustomMsg"),
                          imu=ImuTopic(topic="/livox/imu"),
                          camera=CameraTopic(topic="/camera/color/image_raw", type="sensor_msgs/msg/Image"))


def topics_from_config(config: Any, domain_id: int | None = None):
    """The config's `ros:` section when it has one, else DEFAULT topics; `domain_id` overrides."""
    ros = getattr(config, "ros", None) if config is not None else None
    ros = getattr(ros, "inputs", ros)  # ControllerConfig.ros is a RosConfig: its inputs are the topics
    if ros is None:
        ros = default_topics()
    if domain_id is not None:
        ros = ros.model_copy(update={"domain_id": int(domain_id)})
    return ros


def expected_rates_hz(config: Any) -> dict[str, float]:
    lidar = 10.0 if config is None else 1.0 / config.inputs.lidar.frame_period_s
    return {"lidar": lidar, **NOMINAL_RATE_HZ}


def check_topics(ros_config: Any, rates_hz: dict[str, float], *, listen_s: float = 2.0,
                 required: Sequence[str] = ("lidar", "imu")) -> list[Check]:
    """Listen to each configured sensor topic for `listen_s`; one check per topic.

    A topic in `required` that is silent or too slow FAILs; others (the camera when the planner
    does not use it) only WARN.
    """
    from cyclonedds.domain import DomainParticipant

    from runtime.io.ros.dds import raw_reader, ros_qos
    from runtime.io.ros.messages import ROS_TYPES
    from runtime.io.ros.receiver import decode_cdr

    streams = [(s, t) for s in ("lidar", "imu", "camera") if (t := getattr(ros_config, s)) is not None]
    if not streams:
        return [Check("topics", "FAIL", "the config names no sensor topics", "add lidar and imu topics to ros:")]
    dp = DomainParticipant(ros_config.domain_id)
    readers = [(s, t, raw_reader(dp, t.topic, ROS_TYPES[t.type], ros_qos(t.qos.reliability, max(t.qos.depth, 50))))
               for s, t in streams]
    arrivals: dict[str, list[float]] = {s: [] for s, _ in streams}
    last: dict[str, bytes] = {}
    end = time.monotonic() + listen_s
    while True:
        now = time.monotonic()
        for s, _t, r in readers:
            got = r.take_raw(256)
            if got:
                arrivals[s].extend([now] * len(got))
                last[s] = got[-1]
        if now >= end:
            break
        time.sleep(0.005)
    checks = []
    for s, t in streams:
        name, expected = f"topic:{s}", rates_hz.get(s, 1.0)
        bad = "FAIL" if s in required else "WARN"
        ts = arrivals[s]
        where = f"{t.topic} ({t.type}, domain {ros_config.domain_id})"
        if not ts:
            checks.append(Check(name, bad, f"sensor topic silent: nothing on {where} in {listen_s:g} s",
                                f"start the {s} driver; check the topic name and ROS_DOMAIN_ID"))
            continue
        # Rate over the span that samples arrived in (discovery takes a moment after start).
        span = ts[-1] - ts[0]
        rate = (len(ts) - 1) / span if len(ts) > 1 and span > 0.2 * listen_s else len(ts) / listen_s
        try:
            decode_cdr(t.type, last[s])
            decoded = ""
        except Exception as exc:  # noqa: BLE001 - a RosMessageError, or anything the parser hits
            checks.append(Check(name, bad, f"{where}: {rate:.1f} Hz but undecodable: {_one_line(exc)[:160]}",
                                f"check that the driver publishes {t.type}"))
            continue
        msg = f"{where}: {rate:.1f} Hz (expected {expected:g} Hz){decoded}"
        if rate < FAIL_RATE_SHARE * expected:
            checks.append(Check(name, bad, msg + f", below {FAIL_RATE_SHARE:.0%}",
                                f"check the {s} driver's rate setting and the network load"))
        elif rate < WARN_RATE_SHARE * expected:
            checks.append(Check(name, "WARN", msg + f", below {WARN_RATE_SHARE:.0%}",
                                f"check the {s} driver's rate setting and the network load"))
        else:
            checks.append(Check(name, "PASS", msg))
    return checks


# ----------------------------------------------------------------------------- host


def _run_text(argv: Sequence[str]) -> str | None:
    if shutil.which(argv[0]) is None:
        return None
    try:
        done = subprocess.run(list(argv), capture_output=True, text=True, timeout=5)
    except (OSError, subprocess.SubprocessError):
        return None
    return done.stdout if done.returncode == 0 else None


def check_clock_sync(run_text: Callable[[Sequence[str]], str | None] = _run_text) -> Check:
    """NTP sync from timedatectl or chrony; WARN when it is off or cannot be told."""
    fix = "enable time sync: sudo timedatectl set-ntp true (or install chrony)"
    out = run_text(["timedatectl", "show", "-p", "NTPSynchronized", "--value"])
    if out is not None and out.strip() in ("yes", "no"):
        if out.strip() == "yes":
            return Check("clock_sync", "PASS", "timedatectl: NTP synchronized")
        chrony = run_text(["chronyc", "tracking"])
        if chrony is None:
            return Check("clock_sync", "WARN", "timedatectl: clock not synchronized (recorded times may drift "
                         "from other computers' logs)", fix)
    chrony = run_text(["chronyc", "tracking"])
    if chrony is not None:
        leap = next((ln.split(":", 1)[1].strip() for ln in chrony.splitlines() if ln.startswith("Leap status")), None)
        if leap == "Normal":
            return Check("clock_sync", "PASS", "chrony: synchronized (leap status Normal)")
        return Check("clock_sync", "WARN", f"chrony: not synchronized (leap status {leap})", fix)
    return Check("clock_sync", "WARN", "clock sync unknown: neither timedatectl nor chronyc answered", fix)


def check_cpus(realtime: Any, *, getaffinity: Callable[[int], set[int]] | None = None,
               sys_root: str | Path = "/") -> list[Check]:
    """`cpus` (at least 2 usable, realtime.cpus among them) and `cpu_governor`."""
    getaffinity = getaffinity or os.sched_getaffinity
    usable = sorted(getaffinity(0))
    wanted = list(realtime.cpus) if realtime is not None and realtime.cpus else []
    checks = []
    missing = sorted(set(wanted) - set(usable))
    if len(usable) < 2:
        checks.append(Check("cpus", "FAIL", f"{len(usable)} usable CPU ({usable}); the loop is sized for 2 cores",
                            "run on a computer (or cgroup/cpuset) with at least 2 CPUs"))
    elif missing:
        checks.append(Check("cpus", "FAIL", f"realtime.cpus {wanted} names CPUs {missing} this process cannot use "
                            f"(usable: {usable})", "list only usable CPUs in realtime.cpus (config)"))
    else:
        checks.append(Check("cpus", "PASS", f"{len(usable)} usable CPUs {usable}"
                            + (f"; the loop will be pinned to {wanted}" if wanted else "")))
    root = Path(sys_root) / "sys" / "devices" / "system" / "cpu"
    governors = {}
    for path in sorted(glob.glob(str(root / "cpu[0-9]*" / "cpufreq" / "scaling_governor"))):
        cpu = Path(path).parent.parent.name
        governors[cpu] = _read(Path(path)) or "?"
    fix = "sudo cpupower frequency-set -g performance (or the BIOS power profile)"
    if not governors:
        checks.append(Check("cpu_governor", "WARN", "no cpufreq governor (a VM, or frequency scaling off): "
                            "cannot tell whether the CPU clocks down", "check the BIOS power profile"))
    else:
        slow = {c: g for c, g in governors.items() if g != "performance"}
        if slow:
            shown = ", ".join(f"{c}={g}" for c, g in list(slow.items())[:4]) + (" ..." if len(slow) > 4 else "")
            checks.append(Check("cpu_governor", "WARN", f"governor not 'performance' on {len(slow)} of "
                                f"{len(governors)} CPUs ({shown}): ticks may run slower after idle", fix))
        else:
            checks.append(Check("cpu_governor", "PASS", f"'performance' on all {len(governors)} CPUs"))
    return checks


def check_realtime(realtime: Any, *, request: Callable[..., Any] | None = None) -> list[Check]:
    """`sched_fifo` and `cpu_affinity`: ask for them on a throwaway thread, as the loop will."""
    from runtime.loop.realtime_setup import RealtimeConfig, request_realtime, rtprio_limit

    realtime = realtime or RealtimeConfig()
    request = request or request_realtime
    result = []
    cpus = realtime.cpus or tuple(sorted(os.sched_getaffinity(0)))

    def run() -> None:
        result.append(request(realtime.fifo_priority, cpus, fifo=True))

    t = threading.Thread(target=run, name="preflight-realtime")
    t.start()
    t.join()
    grant = result[0]
    checks = []
    if grant.fifo_granted:
        note = "" if realtime.fifo else " (but realtime.fifo is off in the config: the loop stays SCHED_OTHER)"
        checks.append(Check("sched_fifo", "PASS", f"SCHED_FIFO priority {realtime.fifo_priority} allowed{note}"))
    else:
        limit = rtprio_limit()
        checks.append(Check("sched_fifo", "WARN", f"SCHED_FIFO priority {realtime.fifo_priority} refused "
                            f"({(grant.fifo_reason or '').split('; fix:')[0]}): the loop will run SCHED_OTHER "
                            "(normal priority; lateness and deadline misses are counted as always)",
                            f"LimitRTPRIO={realtime.fifo_priority} in the unit (RLIMIT_RTPRIO now "
                            f"{'unlimited' if limit is None else limit}) or run as root"))
    if grant.affinity_granted:
        what = f"the loop will be pinned to CPUs {list(realtime.cpus)}" if realtime.cpus else \
            "allowed; not requested (realtime.cpus is null: the loop is not pinned)"
        checks.append(Check("cpu_affinity", "PASS", what))
    else:
        checks.append(Check("cpu_affinity", "WARN", f"pinning to CPUs {list(cpus)} refused "
                            f"({(grant.affinity_reason or '').split('; fix:')[0]}): the loop will not be pinned",
                            "list usable CPUs in realtime.cpus; check the cpuset of the service"))
    return checks


def check_disk(log_dir: str | Path, min_free_gb: float = DEFAULT_MIN_FREE_GB,
               disk_usage: Callable[[str], Any] = shutil.disk_usage) -> Check:
    d = Path(log_dir)
    probe = d
    while not probe.exists() and probe != probe.parent:
        probe = probe.parent
    try:
        free = disk_usage(str(probe)).free
    except OSError as exc:
        return Check("disk", "FAIL", f"cannot read free space of {d}: {_one_line(exc)}", "pass an existing --log-dir")
    gb = free / 1e9
    msg = f"{gb:.1f} GB free for logs in {d}"
    if gb < min_free_gb:
        return Check("disk", "FAIL", msg + f" (need {min_free_gb:g} GB)", f"free space in {d} or pass --log-dir")
    if gb < WARN_DISK_FACTOR * min_free_gb:
        return Check("disk", "WARN", msg + f" (less than {WARN_DISK_FACTOR * min_free_gb:g} GB: a long MCAP "
                     "recording may fill it; the recorder then drops records)", f"free space in {d}")
    return Check("disk", "PASS", msg)


# ----------------------------------------------------------------------------- all together

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
    if "sensors" in opts.skip:
        add(skipped("topics", "sensors"))
    else:
        required = ["lidar", "imu"] + (["camera"] if files.config is not None and files.config.uses_camera
                                       else [])
        add(check_topics(topics_from_config(files.config, opts.ros_domain), expected_rates_hz(files.config),
                         listen_s=opts.listen_s, required=required))
    add(skipped("clock_sync", "clock") if "clock" in opts.skip else check_clock_sync())
    realtime = getattr(files.config, "realtime", None)
    add(check_cpus(realtime, sys_root=opts.sys_root))
    add(check_realtime(realtime))
    add(check_disk(opts.log_dir, opts.min_free_gb))
    return checks


def summary_line(checks: Sequence[Check]) -> str:
    n = {s: sum(c.status == s for c in checks) for s in ("PASS", "WARN", "FAIL")}
    verdict = "ready to drive" if n["FAIL"] == 0 else "NOT ready to drive"
    return f"preflight: {verdict} ({n['PASS']} pass, {n['WARN']} warn, {n['FAIL']} fail)"


def checks_json(checks: Sequence[Check]) -> dict[str, Any]:
    return {"ok": all(c.ok for c in checks), "checks": [c.as_json() for c in checks]}


# ----------------------------------------------------------------------------- command line

def _command():
    import click

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
    @click.option("--json", "json_path", type=click.Path(dir_okay=False), default=None,
                  help='write {"checks": [{"name", "ok", "message"}, ...]} here')
    @click.option("--sys-root", default="/", hidden=True, help="root of /sys (tests)")
    @click.pass_context
    def preflight_command(ctx, robot, calibration, config, can_interface, can_channel, can_udp_port, ros_domain,
                          listen_s, log_dir, min_free_gb, skip, json_path, sys_root) -> None:
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
                                skip=tuple(skip))
        checks = run_preflight(opts, echo=click.echo)
        click.echo(summary_line(checks))
        if json_path is not None:
            atomic_write_json(json_path, checks_json(checks))
        ctx.exit(0 if all(c.ok for c in checks) else 1)

    return preflight_command


preflight_command = _command()

__all__ = ["Check", "PreflightOptions", "run_preflight", "check_files", "check_can", "check_socketcan_link",
           "check_base_answers", "check_topics", "check_clock_sync", "check_cpus", "check_realtime", "check_disk",
           "checks_json", "summary_line", "preflight_command"]
