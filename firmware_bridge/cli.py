"""`dct can`: encode, decode, dump and send AgileX V2 frames (candump text format)."""
from __future__ import annotations

import json
import sys
import time

import click

from firmware_bridge import protocol as p


def _decoded_json(record: object, msg_id: int) -> str:
    out = {"id": f"0x{msg_id:03X}", "message": p.message_name(msg_id)}
    out.update(p.record_to_dict(record))
    return json.dumps(out, separators=(", ", ": "))


def _bus_options(f):
    f = click.option("--interface", type=click.Choice(["virtual", "udp_multicast", "socketcan", "limo_serial"]),
                     default="udp_multicast", show_default=True)(f)
    f = click.option("--channel", default=None,
                     help="virtual channel, multicast group, can0 or serial port (default per interface)")(f)
    f = click.option("--udp-port", type=int, default=None, help="udp_multicast port")(f)
    f = click.option("--serial-baud", type=int, default=None, help="limo_serial baud rate")(f)
    return f


def _open(interface: str, channel: str | None, udp_port: int | None, serial_baud: int | None):
    from firmware_bridge.buses import DEFAULT_UDP_GROUP, BusConfig, open_bus

    defaults = {"virtual": "dct", "udp_multicast": DEFAULT_UDP_GROUP, "socketcan": "can0",
                "limo_serial": "/dev/ttyTHS1"}
    kw: dict = {"interface": interface, "channel": channel or defaults[interface]}
    if udp_port is not None:
        kw["udp_port"] = udp_port
    if serial_baud is not None:
        kw["serial_baud"] = serial_baud
    return open_bus(BusConfig(**kw))


@click.group(name="can")
def can_group() -> None:
    """AgileX CAN protocol V2 tools (frames in candump 'ID#DATA' format)."""


@can_group.group(name="encode")
def encode_group() -> None:
    """Encode a command frame and print it in candump format."""


def _print_encoded(record: object) -> None:
    try:
        msg = p.encode(record)
    except p.FrameError as exc:
        raise click.ClickException(f"{exc.name}: {exc}") from None
    click.echo(p.format_candump(msg))


@encode_group.command(name="motion")
@click.option("--linear", "linear_mps", type=float, required=True, help="linear velocity, m/s")
@click.option("--angular", "angular_radps", type=float, default=0.0, show_default=True, help="angular velocity, rad/s")
@click.option("--lateral", "lateral_mps", type=float, default=0.0, show_default=True, help="lateral velocity, m/s (mecanum)")
@click.option("--steering", "steering_rad", type=float, default=0.0, show_default=True, help="steering angle, rad (Ackermann)")
def encode_motion(linear_mps: float, angular_radps: float, lateral_mps: float, steering_rad: float) -> None:
    """0x111 motion command (SDK float32-truncation scaling)."""
    _print_encoded(p.MotionCommand(linear_mps, angular_radps, lateral_mps, steering_rad))


@encode_group.command(name="enable")
def encode_enable() -> None:
    """0x421 = 0x01: enable CAN command mode."""
    _print_encoded(p.ControlModeCommand(p.CONTROL_MODE_CAN))


@encode_group.command(name="mode")
@click.argument("mode", type=int)
def encode_mode(mode: int) -> None:
    """0x421 control mode (0 standby, 1 CAN, 2 UART)."""
    _print_encoded(p.ControlModeCommand(mode))


@encode_group.command(name="clear-errors")
@click.option("--code", type=int, default=0, show_default=True, help="0 all, 1..4 motor 1..4")
def encode_clear(code: int) -> None:
    """0x441 error clear."""
    _print_encoded(p.ErrorClearCommand(code))


@can_group.command(name="decode")
@click.argument("frames", nargs=-1)
def decode_cmd(frames: tuple[str, ...]) -> None:
    """Decode candump frames ('221#03E8FE0C00000000'; '-' or none reads lines from stdin).

    Prints one JSON line per frame with the DBC signal names. Exit status 1 if any frame was rejected.
    """
    lines = list(frames) if frames and frames != ("-",) else [ln for ln in sys.stdin.read().splitlines() if ln.strip()]
    failed = 0
    for text in lines:
        try:
            msg = p.parse_candump(text)
            record = p.decode(msg)
        except p.FrameError as exc:
            failed += 1
            click.echo(json.dumps({"input": text, "error": exc.name, "detail": str(exc)}), err=True)
            continue
        click.echo(_decoded_json(record, msg.arbitration_id))
    if failed:
        sys.exit(1)


@can_group.command(name="dump")
@_bus_options
@click.option("--count", type=int, default=0, help="stop after this many frames (0 = forever)")
@click.option("--duration", "duration_s", type=float, default=0.0, help="stop after this many seconds (0 = forever)")
def dump_cmd(interface: str, channel: str | None, udp_port: int | None, serial_baud: int | None,
             count: int, duration_s: float) -> None:
    """Print received frames as candump lines followed by the decoded JSON (or the error)."""
    bus = _open(interface, channel, udp_port, serial_baud)
    n = 0
    t_end = time.monotonic() + duration_s if duration_s > 0 else None
    try:
        while (count <= 0 or n < count) and (t_end is None or time.monotonic() < t_end):
            msg = bus.recv(timeout=0.1)
            if msg is None:
                continue
            n += 1
            try:
                tail = _decoded_json(p.decode(msg), msg.arbitration_id)
            except p.FrameError as exc:
                tail = json.dumps({"error": exc.name, "detail": str(exc)})
            click.echo(f"({msg.timestamp:.6f}) {interface} {p.format_candump(msg)} {tail}")
    except KeyboardInterrupt:
        pass
    finally:
        bus.shutdown()


@can_group.command(name="send")
@_bus_options
@click.argument("frames", nargs=-1, required=True)
def send_cmd(interface: str, channel: str | None, udp_port: int | None, serial_baud: int | None,
             frames: tuple[str, ...]) -> None:
    """Send candump frames once each (no periodic sending)."""
    try:
        msgs = [p.parse_candump(f) for f in frames]
    except p.FrameError as exc:
        raise click.ClickException(f"{exc.name}: {exc}") from None
    bus = _open(interface, channel, udp_port, serial_baud)
    try:
        for msg in msgs:
            bus.send(msg)
    finally:
        bus.shutdown()
