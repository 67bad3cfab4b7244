"""Bus selection by configuration: one code path for virtual, UDP multicast, SocketCAN and LIMO serial."""
from __future__ import annotations

import contextlib
import errno
import gc
import ipaddress
import logging
from collections.abc import Iterator
from typing import Any, Literal

import can
from pydantic import BaseModel, ConfigDict, Field, model_validator

from firmware_bridge.limo_serial import LIMO_DEFAULT_BAUD, LimoSerialBus

DEFAULT_UDP_GROUP = "239.74.163.2"  # python-can's IPv4 default group
DEFAULT_UDP_PORT = 43113
#: Channel used when a config names none: virtual channel, multicast group, CAN interface, serial port.
DEFAULT_CHANNELS: dict[str, str] = {
    "virtual": "dct", "udp_multicast": DEFAULT_UDP_GROUP, "socketcan": "can0", "limo_serial": "/dev/ttyTHS1"}
_IFNAMSIZ = 16  # Linux network interface names are at most 15 characters


class BusOpenError(can.CanInitializationError):
    """A bus that cannot be opened. The message names the interface, the channel and the OS reason."""

    def __init__(self, interface: str, channel: str, reason: str) -> None:
        self.interface = interface
        self.channel = channel
        self.reason = reason
        super().__init__(f"cannot open {interface} bus on channel {channel!r}: {reason}")


class BusConfig(BaseModel):
    """Which bus to open. ``channel``: virtual channel name, multicast group, SocketCAN interface
    (``can0``) or serial port path, depending on ``interface`` (default: ``DEFAULT_CHANNELS``)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    interface: Literal["virtual", "udp_multicast", "socketcan", "limo_serial"] = "virtual"
    channel: str = "dct"
    bitrate: int = Field(500_000, gt=0, description="CAN bit rate (set on the robot with ip link for SocketCAN)")
    serial_baud: int = Field(LIMO_DEFAULT_BAUD, gt=0, description="LIMO UART baud rate")
    udp_port: int = Field(DEFAULT_UDP_PORT, gt=0, lt=65536)
    receive_own_messages: bool = False

    @model_validator(mode="before")
    @classmethod
    def _default_channel(cls, data: Any) -> Any:
        if isinstance(data, dict) and data.get("channel") is None:
            data = {**data, "channel": DEFAULT_CHANNELS.get(data.get("interface", "virtual"), "dct")}
        return data

    @model_validator(mode="after")
    def _check_channel(self) -> BusConfig:
        channel = self.channel
        if self.interface == "udp_multicast":
            try:
                group = ipaddress.ip_address(channel)
            except ValueError:
                group = None
            if group is None or not group.is_multicast:
                raise ValueError(f"udp_multicast channel {channel!r} is not a multicast group address "
                                 f"(IPv4 224.0.0.0/4 or IPv6 ff00::/8, e.g. {DEFAULT_UDP_GROUP})")
        elif self.interface == "socketcan":
            if not channel or len(channel) >= _IFNAMSIZ or any(c.isspace() or c == "/" for c in channel):
                raise ValueError(f"socketcan channel {channel!r} is not a network interface name (e.g. can0)")
        elif not channel:
            raise ValueError(f"{self.interface} channel must not be empty")
        return self


class _DropNotShutDown(logging.Filter):
    """python-can warns "X was not properly shut down" when a bus whose __init__ failed is freed;
    after a failed open that is noise next to our one-line error."""

    def filter(self, record: logging.LogRecord) -> bool:
        return "was not properly shut down" not in record.getMessage()


@contextlib.contextmanager
def _quiet_failed_open() -> Iterator[None]:
    logger = logging.getLogger("can.bus")
    quiet = _DropNotShutDown()
    logger.addFilter(quiet)
    try:
        yield
    finally:
        logger.removeFilter(quiet)


def os_reason(exc: BaseException) -> str:
    """The innermost OS-level reason in an exception chain ("No such file or directory [ENOENT]")."""
    chain: list[BaseException] = []
    cur: BaseException | None = exc
    while cur is not None and all(cur is not seen for seen in chain):
        chain.append(cur)
        cur = cur.__cause__ or cur.__context__
    for err in reversed(chain):
        number, text = _errno_and_text(err)
        if text:
            code = errno.errorcode.get(number) if isinstance(number, int) and number > 0 else None
            return f"{text} [{code}]" if code else text
    return f"{exc}" or type(exc).__name__


def _errno_and_text(err: BaseException) -> tuple[int | None, str | None]:
    """(errno, strerror) of an OSError, or of an error shaped like one (``termios.error`` is
    ``(25, 'Inappropriate ioctl for device')`` but no OSError); (None, None) otherwise."""
    if isinstance(err, OSError) and err.strerror:
        return err.errno, err.strerror
    if len(err.args) == 2 and isinstance(err.args[0], int) and isinstance(err.args[1], str):
        return err.args[0], err.args[1]
    return None, None


_HINTS = {
    ("socketcan", errno.EAFNOSUPPORT): "SocketCAN needs Linux with the can kernel modules",
    ("socketcan", errno.ENODEV): "no such CAN interface; list them with `ip link`",
    ("limo_serial", errno.ENOENT): "no such serial port",
    ("limo_serial", errno.EACCES): "no permission; add the user to the dialout group",
    ("limo_serial", errno.ENOTTY): "not a serial port",
}


def _hint(interface: str, exc: BaseException) -> str:
    cur: BaseException | None = exc
    for _ in range(8):
        if cur is None:
            break
        number, _ = _errno_and_text(cur)
        if (interface, number) in _HINTS:
            return f"; {_HINTS[(interface, number)]}"
        cur = cur.__cause__ or cur.__context__
    return ""


def _construct(config: BusConfig) -> can.BusABC:
    if config.interface == "virtual":
        return can.Bus(interface="virtual", channel=config.channel,
                       receive_own_messages=config.receive_own_messages)
    if config.interface == "udp_multicast":
        if config.receive_own_messages:
            raise ValueError("BusConfig: udp_multicast does not support receive_own_messages=True")
        return can.Bus(interface="udp_multicast", channel=config.channel, port=config.udp_port)
    if config.interface == "socketcan":
        # The bit rate of a SocketCAN interface is set outside the process (ip link set can0 type can bitrate ...).
        return can.Bus(interface="socketcan", channel=config.channel,
                       receive_own_messages=config.receive_own_messages)
    if config.interface == "limo_serial":
        return LimoSerialBus(config.channel, baudrate=config.serial_baud)
    raise ValueError(f"BusConfig: unknown interface {config.interface!r}")  # unreachable (Literal)


def open_bus(config: BusConfig) -> can.BusABC:
    """Open the python-can bus described by ``config``.

    Raises ``BusOpenError`` (a ``can.CanInitializationError``) naming the interface, the channel
    and the OS reason when the bus cannot be opened.
    """
    with _quiet_failed_open():
        try:
            return _construct(config)
        except (OSError, ValueError, ImportError, can.CanError) as exc:
            reason = os_reason(exc) + _hint(config.interface, exc)
        # The half-built bus is freed with the exception above; collect cycles while quiet.
        gc.collect()
    raise BusOpenError(config.interface, config.channel, reason)
