"""Bus selection by configuration: one code path for virtual, UDP multicast, SocketCAN and LIMO serial."""
from __future__ import annotations

from typing import Literal

import can
from pydantic import BaseModel, ConfigDict, Field

from firmware_bridge.limo_serial import LIMO_DEFAULT_BAUD, LimoSerialBus

DEFAULT_UDP_GROUP = "239.74.163.2"  # python-can's IPv4 default group
DEFAULT_UDP_PORT = 43113


class BusConfig(BaseModel):
    """Which bus to open. ``channel``: virtual channel name, multicast group, SocketCAN interface
    (``can0``) or serial port path, depending on ``interface``."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    interface: Literal["virtual", "udp_multicast", "socketcan", "limo_serial"] = "virtual"
    channel: str = "dct"
    bitrate: int = Field(500_000, gt=0, description="CAN bit rate (set on the robot with ip link for SocketCAN)")
    serial_baud: int = Field(LIMO_DEFAULT_BAUD, gt=0, description="LIMO UART baud rate")
    udp_port: int = Field(DEFAULT_UDP_PORT, gt=0, lt=65536)
    receive_own_messages: bool = False


def open_bus(config: BusConfig) -> can.BusABC:
    """Open the python-can bus described by ``config``."""
    if config.interface == "virtual":
        return can.Bus(interface="virtual", channel=config.channel,
                       receive_own_messages=config.receive_own_messages)
    if config.interface == "udp_multicast":
        if config.receive_own_messages:
            raise ValueError("BusConfig: udp_multicast does not support receive_own_messages=True")
        return can.Bus(interface="udp_multicast", channel=config.channel or DEFAULT_UDP_GROUP,
                       port=config.udp_port)
    if config.interface == "socketcan":
        # The bit rate of a SocketCAN interface is set outside the process (ip link set can0 type can bitrate ...).
        return can.Bus(interface="socketcan", channel=config.channel,
                       receive_own_messages=config.receive_own_messages)
    if config.interface == "limo_serial":
        return LimoSerialBus(config.channel, baudrate=config.serial_baud)
    raise ValueError(f"BusConfig: unknown interface {config.interface!r}")  # unreachable (Literal)
