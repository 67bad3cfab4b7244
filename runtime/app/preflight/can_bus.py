"""Preflight's CAN checks: `can_link` (SocketCAN: the interface is up at the robot's bit rate;
udp_multicast / virtual / limo_serial: the bus opens) and `base` (the base answers the enable
frame, is not in E-stop and reports no error that stops the controller)."""
from __future__ import annotations

import json
import shutil
import subprocess
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from runtime.app.preflight.check import Check, one_line, read_text

#: The base must answer the enable frame with 0x221 within this (it sends 0x221 every 20 ms:
#: docs/protocol.md, section State feedback frames (base to host)).
BASE_ANSWER_TIMEOUT_S = 0.100
#: After the first 0x221, how long to wait for 0x211 (sent every 100 ms).
SYSTEM_STATE_WAIT_S = 0.35

SOCKETCAN_UP_FIX = "sudo ip link set {ch} down; sudo ip link set {ch} up type can bitrate {bitrate}"


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
    operstate = read_text(net / "operstate") or "?"
    flags = int(read_text(net / "flags") or "0", 16)
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
        return Check("base", "FAIL", f"cannot send the enable frame 0x421: {one_line(exc)}",
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
        return checks + [Check("can_link", "FAIL", f"CAN down: {one_line(exc)}", fix),
                         Check("base", "FAIL", "not checked: the bus does not open", "see can_link")]
    try:
        if cfg.interface != "socketcan":
            checks.append(Check("can_link", "PASS", f"{cfg.interface} bus on {cfg.channel!r} opens"))
        if check_base:
            checks.append(check_base_answers(bus))
    finally:
        bus.shutdown()
    return checks
