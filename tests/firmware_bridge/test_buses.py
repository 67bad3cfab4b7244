"""Bus selection and the udp_multicast bus between two endpoints."""
from __future__ import annotations

import random
import time
import uuid

import can
import pydantic
import pytest

from firmware_bridge import candump, codec
from firmware_bridge import protocol as p
from firmware_bridge.base_driver import AgileXBaseDriver
from firmware_bridge.buses import DEFAULT_UDP_GROUP, BusConfig, BusOpenError, open_bus

GROUP = "239.74.163.97"  # not python-can's default group, to avoid clashing with other tests


def _multicast_possible(port: int) -> str | None:
    try:
        bus = open_bus(BusConfig(interface="udp_multicast", channel=GROUP, udp_port=port))
    except (OSError, can.CanError) as exc:
        return f"cannot join multicast group {GROUP}: {exc}"
    bus.shutdown()
    return None


@pytest.fixture
def udp_port() -> int:
    port = random.randint(42000, 48000)
    reason = _multicast_possible(port)
    if reason:
        pytest.skip(reason)
    return port


def test_config_validation():
    assert BusConfig().interface == "virtual" and BusConfig().serial_baud == 460800
    with pytest.raises(pydantic.ValidationError):
        BusConfig(interface="pcan")
    with pytest.raises(pydantic.ValidationError):
        BusConfig(interface="virtual", bitrat=1)


def test_virtual_via_config():
    cfg = BusConfig(interface="virtual", channel=f"fb-{uuid.uuid4().hex}")
    a, b = open_bus(cfg), open_bus(cfg)
    try:
        a.send(codec.encode(p.ControlModeCommand(1)))
        assert candump.format_candump(b.recv(timeout=1.0)) == "421#0100000000000000"
    finally:
        a.shutdown()
        b.shutdown()


def test_socketcan_same_code_path():
    # No SocketCAN on these machines: the config is accepted and open_bus reaches python-can's
    # backend, whose OS error comes back as one BusOpenError naming interface, channel and reason.
    cfg = BusConfig(interface="socketcan", channel="dctmissing0")
    with pytest.raises(BusOpenError) as exc_info:
        open_bus(cfg).shutdown()
    text = str(exc_info.value)
    assert isinstance(exc_info.value, can.CanInitializationError)
    assert text.startswith("cannot open socketcan bus on channel 'dctmissing0': ") and "\n" not in text
    assert exc_info.value.reason  # the OS reason, e.g. "Address family not supported by protocol"


def test_limo_serial_open_error_names_the_os_reason(tmp_path):
    missing = str(tmp_path / "ttyMISSING")
    with pytest.raises(BusOpenError, match=r"cannot open limo_serial bus on channel '.*ttyMISSING': "
                                           r"No such file or directory \[ENOENT\]"):
        open_bus(BusConfig(interface="limo_serial", channel=missing))
    with pytest.raises(BusOpenError, match=r"Is a directory \[EISDIR\]"):
        open_bus(BusConfig(interface="limo_serial", channel=str(tmp_path)))


@pytest.mark.parametrize(
    ("interface", "channel", "fragment"),
    [("udp_multicast", "not-a-group", "not a multicast group"), ("udp_multicast", "10.0.0.1", "not a multicast group"),
     ("udp_multicast", "", "not a multicast group"), ("socketcan", "a/b", "not a network interface name"),
     ("socketcan", "x" * 16, "not a network interface name"), ("limo_serial", "", "must not be empty")],
)
def test_bad_channel_rejected_by_config(interface, channel, fragment):
    with pytest.raises(pydantic.ValidationError, match=fragment):
        BusConfig(interface=interface, channel=channel)


def test_default_channel_per_interface():
    assert BusConfig(interface="udp_multicast").channel == DEFAULT_UDP_GROUP
    assert BusConfig(interface="socketcan").channel == "can0"
    assert BusConfig(interface="limo_serial", channel=None).channel == "/dev/ttyTHS1"
    assert BusConfig().channel == "dct"


def _recv_until(bus: can.BusABC, fid: int, timeout_s: float = 2.0) -> can.Message | None:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        m = bus.recv(timeout=0.1)
        if m is not None and m.arbitration_id == fid:
            return m
    return None


def test_udp_multicast_two_buses_exchange(udp_port):
    cfg = BusConfig(interface="udp_multicast", channel=GROUP, udp_port=udp_port)
    a, b = open_bus(cfg), open_bus(cfg)
    try:
        a.send(codec.encode(p.MotionCommand(0.15, 0.0)))
        m = _recv_until(b, 0x111)
        assert m is not None and candump.format_candump(m) == "111#0096000000000000"
    finally:
        a.shutdown()
        b.shutdown()


def test_driver_over_udp_ignores_own_frames(udp_port):
    cfg = BusConfig(interface="udp_multicast", channel=GROUP, udp_port=udp_port)
    bus, peer = open_bus(cfg), open_bus(cfg)
    try:
        drv = AgileXBaseDriver(bus, time.monotonic)
        drv.send_motion(0.3, 0.0)  # multicast loops it back to our own socket
        assert _recv_until(peer, 0x111) is not None
        peer.send(codec.encode(p.MotionState(0.3, 0.0)))
        deadline = time.monotonic() + 2.0
        while drv.feedback.motion is None and time.monotonic() < deadline:
            drv.poll()
            time.sleep(0.005)
        assert drv.feedback.motion.record == p.MotionState(0.3, 0.0)
        assert drv.feedback.decode_error_counts == {}
    finally:
        bus.shutdown()
        peer.shutdown()
