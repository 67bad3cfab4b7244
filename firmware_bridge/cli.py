"""`dct can`: encode, decode, dump and send AgileX V2 frames (candump text format).

Every input error is one line on stderr and a non-zero exit: usage errors (a missing option,
a value click cannot parse) are reworded onto one line by ``_OneLineCommand``/``_OneLineGroup``,
values are checked against the DBC (NaN, inf, range) by ``SignalValue``, and a bus that cannot
open names the interface, the channel and the OS reason.
"""
from __future__ import annotations

import json
import math
import os
import sys
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from typing import Any, BinaryIO

import can
import click

from firmware_bridge import candump, codec, frame_errors
from firmware_bridge import protocol as p

#: Longest candump line (bytes, without the line end) that ``decode`` accepts. A candump line is
#: under 100 characters; anything much longer is not a frame and is never echoed in full.
MAX_LINE_BYTES = 256
#: Characters of a rejected over-long or binary line shown in the error.
SHOWN_CHARS = 60


# --------------------------------------------------------------------------------------
# One-line errors
# --------------------------------------------------------------------------------------
class OneLineUsageError(click.ClickException):
    """A usage error printed as one ``Error: ...`` line (click's own adds usage and hint lines)."""

    exit_code = 2


def _one_line(ctx: click.Context, exc: click.UsageError) -> OneLineUsageError:
    return OneLineUsageError(f"{ctx.command_path}: {exc.format_message()} (see --help)")


class _OneLineUsage:
    """Mixin: usage errors while parsing arguments come out as one line (help stays help)."""

    def parse_args(self, ctx: click.Context, args: list[str]) -> list[str]:
        try:
            return super().parse_args(ctx, args)
        except click.exceptions.NoArgsIsHelpError:
            raise
        except click.UsageError as exc:
            raise _one_line(ctx, exc) from None


class _OneLineCommand(_OneLineUsage, click.Command):
    pass


class _OneLineGroup(_OneLineUsage, click.Group):
    command_class = _OneLineCommand
    group_class = type  # sub-groups are _OneLineGroup too

    def resolve_command(self, ctx: click.Context, args: list[str]) -> Any:
        try:
            return super().resolve_command(ctx, args)
        except click.UsageError as exc:
            raise _one_line(ctx, exc) from None


def _shown(text: str, limit: int = SHOWN_CHARS) -> str:
    return text if len(text) <= limit else f"{text[:limit]}... ({len(text)} characters)"


def _param_name(param: click.Parameter | None) -> str:
    if param is None:
        return "value"
    if isinstance(param, click.Option) and param.opts:
        return max(param.opts, key=len)
    return (param.human_readable_name or "value").upper()


_INF_WORDS = ("inf", "infinity")


class SignalValue(click.ParamType):
    """A physical value of one DBC signal, checked exactly as ``protocol.encode`` will check it.

    NaN, inf, a value that would overflow the scaling or lie outside the DBC range, and a
    fraction for an integer signal are one-line errors naming the option, the signal and the
    allowed range.
    """

    def __init__(self, frame_id: int, signal: str) -> None:
        self.frame_id = frame_id
        self.signal = signal
        self.name = signal

    @staticmethod
    def _number(text: str) -> int | float | None:
        """An int ("300", "0x1F") or a float ("0.15", "1e308", "nan", "inf"), None if neither."""
        for parse in (lambda t: int(t, 0), int, float):
            try:
                return parse(text.strip())
            except ValueError:
                continue
        return None

    def convert(self, value: Any, param: click.Parameter | None, ctx: click.Context | None) -> Any:
        name = _param_name(param)
        number = self._number(value) if isinstance(value, str) else value
        where = f"signal {self.signal} of frame 0x{self.frame_id:03X}"
        if number is None:
            raise click.ClickException(f"{name}: {_shown(repr(value))} is not a number ({where})")
        if isinstance(number, float) and math.isinf(number) and value.strip().lower().lstrip("+-") not in _INF_WORDS:
            lo, hi, unit = codec.signal_limits(self.frame_id, self.signal)
            raise click.ClickException(f"{name}: {_shown(value.strip())} is out of range, "
                                       f"allowed [{lo}, {hi}]{' ' + unit if unit else ''} ({where})")
        try:
            codec.signal_raw(self.frame_id, self.signal, number)
        except frame_errors.FrameError as exc:
            raise click.ClickException(f"{name}: {exc}") from None
        return number


class Seconds(click.ParamType):
    """A finite, non-negative duration in seconds (NaN and inf are errors, not 'forever')."""

    name = "seconds"

    def convert(self, value: Any, param: click.Parameter | None, ctx: click.Context | None) -> float:
        name = _param_name(param)
        try:
            seconds = float(value)
        except (TypeError, ValueError):
            raise click.ClickException(f"{name}: {_shown(repr(value))} is not a number of seconds") from None
        if math.isnan(seconds) or math.isinf(seconds):
            raise click.ClickException(f"{name}: {seconds} is not a finite number of seconds (use 0 for no limit)")
        if seconds < 0:
            raise click.ClickException(f"{name}: {seconds} is negative (use 0 for no limit)")
        return seconds


# --------------------------------------------------------------------------------------
# Bus opening
# --------------------------------------------------------------------------------------
def _decoded_json(record: object, msg_id: int) -> str:
    out = {"id": f"0x{msg_id:03X}", "message": codec.message_name(msg_id)}
    out.update(codec.record_to_dict(record))
    return json.dumps(out, separators=(", ", ": "))


def _bus_options(f):
    f = click.option("--interface", type=click.Choice(["virtual", "udp_multicast", "socketcan", "limo_serial"]),
                     default="udp_multicast", show_default=True)(f)
    f = click.option("--channel", default=None,
                     help="virtual channel, multicast group, can0 or serial port (default per interface)")(f)
    f = click.option("--udp-port", type=click.IntRange(1, 65535), default=None, help="udp_multicast port")(f)
    f = click.option("--serial-baud", type=click.IntRange(min=1), default=None, help="limo_serial baud rate")(f)
    return f


def _config_error(exc: Any) -> str:
    parts = []
    for err in exc.errors():
        loc = ".".join(str(x) for x in err["loc"])
        msg = str(err["msg"]).removeprefix("Value error, ")
        parts.append(f"{loc}: {msg}" if loc else msg)
    return "; ".join(parts)


def _open(interface: str, channel: str | None, udp_port: int | None, serial_baud: int | None):
    import pydantic

    from firmware_bridge.buses import BusConfig, BusOpenError, open_bus

    if channel is not None and len(channel) > MAX_LINE_BYTES:
        raise click.ClickException(f"--channel: {_shown(repr(channel))} is too long for a bus channel")
    kw: dict = {"interface": interface, "channel": channel}
    if udp_port is not None:
        kw["udp_port"] = udp_port
    if serial_baud is not None:
        kw["serial_baud"] = serial_baud
    try:
        config = BusConfig(**kw)
    except pydantic.ValidationError as exc:
        raise click.ClickException(f"cannot open bus: {_config_error(exc)}") from None
    try:
        return open_bus(config)
    except BusOpenError as exc:
        raise click.ClickException(str(exc)) from None


def _bus_failure(action: str, interface: str, channel: str | None, exc: BaseException) -> click.ClickException:
    from firmware_bridge.buses import DEFAULT_CHANNELS, os_reason

    channel = DEFAULT_CHANNELS[interface] if channel is None else channel
    return click.ClickException(f"{interface} bus on channel {channel!r}: {action} failed: {os_reason(exc)}")


# --------------------------------------------------------------------------------------
# Commands
# --------------------------------------------------------------------------------------
@click.group(name="can", cls=_OneLineGroup)
def can_group() -> None:
    """AgileX CAN protocol V2 tools (frames in candump 'ID#DATA' format)."""


@can_group.group(name="encode")
def encode_group() -> None:
    """Encode a command frame and print it in candump format."""


def _print_encoded(record: object) -> None:
    try:
        msg = codec.encode(record)
    except frame_errors.FrameError as exc:
        raise click.ClickException(f"{exc.name}: {exc}") from None
    click.echo(candump.format_candump(msg))


_MOTION = p.ID_MOTION_COMMAND


@encode_group.command(name="motion")
@click.option("--linear", "linear_mps", type=SignalValue(_MOTION, "linear_velocity"), required=True,
              help="linear velocity, m/s")
@click.option("--angular", "angular_radps", type=SignalValue(_MOTION, "angular_velocity"), default=0.0,
              show_default=True, help="angular velocity, rad/s")
@click.option("--lateral", "lateral_mps", type=SignalValue(_MOTION, "lateral_velocity"), default=0.0,
              show_default=True, help="lateral velocity, m/s (mecanum)")
@click.option("--steering", "steering_rad", type=SignalValue(_MOTION, "steering_angle"), default=0.0,
              show_default=True, help="steering angle, rad (Ackermann)")
def encode_motion(*, linear_mps: float, angular_radps: float, lateral_mps: float, steering_rad: float) -> None:
    """0x111 motion command (SDK float32-truncation scaling)."""
    _print_encoded(p.MotionCommand(float(linear_mps), float(angular_radps), float(lateral_mps), float(steering_rad)))


@encode_group.command(name="enable")
def encode_enable() -> None:
    """0x421 = 0x01: enable CAN command mode."""
    _print_encoded(p.ControlModeCommand(p.CONTROL_MODE_CAN))


@encode_group.command(name="mode")
@click.argument("mode", type=SignalValue(p.ID_CONTROL_MODE, "mode"))
def encode_mode(*, mode: int) -> None:
    """0x421 control mode (0 standby, 1 CAN, 2 UART)."""
    _print_encoded(p.ControlModeCommand(int(mode)))


@encode_group.command(name="clear-errors")
@click.option("--code", type=SignalValue(p.ID_ERROR_CLEAR, "clear_code"), default=0, show_default=True,
              help="0 all, 1..4 motor 1..4")
def encode_clear(*, code: int) -> None:
    """0x441 error clear."""
    _print_encoded(p.ErrorClearCommand(int(code)))


# ---------------------------------------------------------------------------- decode
@dataclass
class _Line:
    """One input line: its bytes without the line end (only the first ones if too long) and length."""

    number: int
    head: bytes
    length: int

    @property
    def too_long(self) -> bool:
        return self.length > MAX_LINE_BYTES


def _read_lines(stream: BinaryIO) -> Iterator[_Line]:
    """Lines of a binary stream as they arrive, holding at most ``MAX_LINE_BYTES + 2`` bytes of one.

    Hand-written rather than ``for line in stream``: that reads a whole line into memory however
    long it is, while ``readline(limit)`` returns as soon as a line (or the limit) is there.
    """
    limit = MAX_LINE_BYTES + 2  # room for "\r\n"
    number = 0
    while True:
        raw = stream.readline(limit)
        if not raw:
            return
        number += 1
        if len(raw) == limit and not raw.endswith(b"\n"):
            head, length, last_two = raw, len(raw), raw[-2:]
            while not last_two.endswith(b"\n"):  # drain the rest of the line without keeping it
                raw = stream.readline(1 << 16)
                if not raw:
                    break
                length += len(raw)
                last_two = (last_two + raw)[-2:]
            ending = 2 if last_two == b"\r\n" else 1 if last_two.endswith(b"\n") else 0
            yield _Line(number, head, length - ending)
            continue
        content = raw.rstrip(b"\n").removesuffix(b"\r")
        yield _Line(number, content, len(content))


@dataclass
class _DecodeTally:
    lines: int = 0
    blank: int = 0
    decoded: int = 0
    rejected: int = 0
    errors: dict[str, int] = field(default_factory=dict)
    flagged: dict[str, int] = field(default_factory=dict)

    def reject(self, line: int | None, shown: str, name: str, detail: str) -> None:
        self.rejected += 1
        self.errors[name] = self.errors.get(name, 0) + 1
        out = {"input": shown, "error": name, "detail": detail}
        if line is not None:
            out = {"line": line, **out}
        click.echo(json.dumps(out), err=True)

    def summary(self) -> str:
        return json.dumps({"summary": {
            "lines": self.lines, "decoded": self.decoded, "rejected": self.rejected, "blank": self.blank,
            "errors": dict(sorted(self.errors.items())), "flagged": dict(sorted(self.flagged.items()))}})


def _decode_line(line: _Line, tally: _DecodeTally, numbered: bool) -> None:
    """Decode one line and print its JSON (stdout) or its error (stderr)."""
    tally.lines += 1
    where = line.number if numbered else None
    label = f"line {line.number}: " if numbered else ""
    if line.too_long:
        shown = line.head[:SHOWN_CHARS].decode("utf-8", "backslashreplace") + "..."
        tally.reject(where, shown, "line_too_long",
                     f"{label}{line.length} bytes, longer than the {MAX_LINE_BYTES} a candump line may have")
        return
    try:
        text = line.head.decode("utf-8")
    except UnicodeDecodeError as exc:
        shown = line.head[:SHOWN_CHARS].decode("utf-8", "backslashreplace")
        shown += "..." if len(line.head) > SHOWN_CHARS else ""
        tally.reject(where, shown, "not_utf8",
                     f"{label}byte 0x{line.head[exc.start]:02X} at column {exc.start + 1} is not UTF-8 text")
        return
    if not text.strip() and numbered:  # blank stdin lines are skipped; a blank argument is an error
        tally.blank += 1
        return
    try:
        msg = candump.parse_candump(text)
        record = codec.decode(msg)
    except frame_errors.FrameError as exc:
        tally.reject(where, text, exc.name, f"{label}{exc}" if numbered else str(exc))
        return
    tally.decoded += 1
    for flag in codec.describe_flags(record):
        tally.flagged[flag.key] = tally.flagged.get(flag.key, 0) + 1
    click.echo(_decoded_json(record, msg.arbitration_id))  # click.echo flushes: live through a pipe


@can_group.command(name="decode")
@click.argument("frames", nargs=-1)
def decode_cmd(*, frames: tuple[str, ...]) -> None:
    """Decode candump frames ('221#03E8FE0C00000000'; '-' or none reads lines from stdin).

    Stdin is decoded line by line as it arrives (`candump can0 | dct can decode` is live);
    candump's default and -L formats are accepted. Prints one JSON line per frame with the DBC
    signal names ("flagged": out-of-range feedback fields), one JSON error line per rejected line
    on stderr, and from stdin a closing {"summary": ...} line on stderr. Lines longer than
    256 bytes and non-UTF-8 lines are rejected. Exit status 1 if any line was rejected.
    """
    tally = _DecodeTally()
    if frames and frames != ("-",):
        for number, text in enumerate(frames, start=1):
            raw = os.fsencode(text)  # undecodable argv bytes come back as they were given
            _decode_line(_Line(number, raw[:MAX_LINE_BYTES + 1], len(raw)), tally, numbered=False)
    else:
        stdin = getattr(sys.stdin, "buffer", None)
        if stdin is None:
            raise click.ClickException("decode: no frames given and stdin is closed")
        try:
            for line in _read_lines(stdin):
                _decode_line(line, tally, numbered=True)
        except KeyboardInterrupt:
            click.echo(tally.summary(), err=True)
            sys.exit(130)
        click.echo(tally.summary(), err=True)
    if tally.rejected:
        sys.exit(1)


# ---------------------------------------------------------------------------- bus commands
@can_group.command(name="dump")
@_bus_options
@click.option("--count", type=click.IntRange(min=0), default=0, help="stop after this many frames (0 = forever)")
@click.option("--duration", "duration_s", type=Seconds(), default=0.0,
              help="stop after this many seconds (0 = forever)")
def dump_cmd(*, interface: str, channel: str | None, udp_port: int | None, serial_baud: int | None,
             count: int, duration_s: float) -> None:
    """Print received frames as candump lines followed by the decoded JSON (or the error)."""
    bus = _open(interface, channel, udp_port, serial_baud)
    n = 0
    t_end = time.monotonic() + duration_s if duration_s > 0 else None
    try:
        while (count <= 0 or n < count) and (t_end is None or time.monotonic() < t_end):
            try:
                msg = bus.recv(timeout=0.1)
            except (OSError, can.CanError) as exc:
                raise _bus_failure("receive", interface, channel, exc) from None
            if msg is None:
                continue
            n += 1
            try:
                tail = _decoded_json(codec.decode(msg), msg.arbitration_id)
            except frame_errors.FrameError as exc:
                tail = json.dumps({"error": exc.name, "detail": str(exc)})
            click.echo(f"({msg.timestamp:.6f}) {interface} {candump.format_candump(msg)} {tail}")
    except KeyboardInterrupt:
        pass
    finally:
        bus.shutdown()


@can_group.command(name="send")
@_bus_options
@click.argument("frames", nargs=-1, required=True)
def send_cmd(*, interface: str, channel: str | None, udp_port: int | None, serial_baud: int | None,
             frames: tuple[str, ...]) -> None:
    """Send candump frames once each (no periodic sending)."""
    msgs = []
    for number, text in enumerate(frames, start=1):
        if len(text) > MAX_LINE_BYTES:
            raise click.ClickException(f"frame {number}: {_shown(repr(text))} is longer than a candump frame")
        try:
            msgs.append(candump.parse_candump(text))
        except frame_errors.FrameError as exc:
            raise click.ClickException(f"{exc.name}: {exc}") from None
    bus = _open(interface, channel, udp_port, serial_baud)
    try:
        for number, msg in enumerate(msgs, start=1):
            try:
                bus.send(msg, timeout=1.0)
            except (OSError, can.CanError) as exc:
                raise _bus_failure(f"send of frame {number} ({candump.format_candump(msg)})", interface, channel,
                                   exc) from None
    finally:
        bus.shutdown()
