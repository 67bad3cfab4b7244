"""LockstepBus: python-can's Bus interface and the virtual bus's delivery rules, without its
per-frame deep copy and wall-clock stamps."""
from __future__ import annotations

import threading
import uuid

import can
import pytest

from firmware_bridge import codec
from firmware_bridge import protocol as p
from firmware_bridge.base_driver import AgileXBaseDriver
from hil_sim.episode.lockstep import virtual_bus_pair
from hil_sim.episode.lockstep_bus import LockstepBus, _channels


@pytest.fixture
def channel():
    name = f"test-{uuid.uuid4().hex}"
    yield name
    assert name not in _channels  # every bus of the test was shut down


def _frame(fid: int = 0x221, data: bytes = b"\x01\x02\x03\x04\x05\x06\x07\x08", stamp: float = 1.25) -> can.Message:
    return can.Message(arbitration_id=fid, is_extended_id=False, dlc=8, data=data, timestamp=stamp)


def test_frames_reach_the_other_ends_in_order_with_the_senders_stamp(channel):
    with LockstepBus(channel) as a, LockstepBus(channel) as b, LockstepBus(channel) as c:
        for k in range(3):
            a.send(_frame(0x250 + k, stamp=0.5 + k))
        for bus in (b, c):
            got = [bus.recv(timeout=0) for _ in range(3)]
            assert [m.arbitration_id for m in got] == [0x250, 0x251, 0x252]
            assert [m.timestamp for m in got] == [0.5, 1.5, 2.5]
            assert all(m.is_rx and m.channel == channel and not m.is_extended_id and m.dlc == 8 for m in got)
            assert bus.recv(timeout=0) is None
        assert a.recv(timeout=0) is None  # not its own frames


def test_own_frames_only_with_receive_own_messages(channel):
    with LockstepBus(channel, receive_own_messages=True) as a, LockstepBus(channel) as b:
        a.send(_frame())
        own = a.recv(timeout=0)
        assert own is not None and not own.is_rx
        assert b.recv(timeout=0).is_rx


def test_each_receiver_gets_its_own_copy(channel):
    sent = _frame()
    with LockstepBus(channel) as a, LockstepBus(channel) as b, LockstepBus(channel) as c:
        a.send(sent)
        mb, mc = b.recv(timeout=0), c.recv(timeout=0)
        mb.data[0] = 0xFF
        sent.data[1] = 0xEE
        assert bytes(mc.data) == b"\x01\x02\x03\x04\x05\x06\x07\x08"
        assert mb is not sent and mc is not sent


def test_channels_are_separate(channel):
    with LockstepBus(channel) as a, LockstepBus(channel + "-other") as b:
        a.send(_frame())
        assert b.recv(timeout=0) is None


def test_filters_drop_frames_that_do_not_match(channel):
    with LockstepBus(channel) as a, LockstepBus(channel, can_filters=[{"can_id": 0x311, "can_mask": 0x7FF}]) as b:
        a.send(_frame(0x221))
        a.send(_frame(0x311))
        assert b.recv(timeout=0).arbitration_id == 0x311
        assert b.recv(timeout=0) is None


def test_recv_with_a_timeout_waits_for_a_frame_from_another_thread(channel):
    with LockstepBus(channel) as a, LockstepBus(channel) as b:
        assert b.recv(timeout=0.01) is None
        timer = threading.Timer(0.05, lambda: a.send(_frame(0x311)))
        timer.start()
        got = b.recv(timeout=5.0)
        timer.join()
        assert got is not None and got.arbitration_id == 0x311


def test_a_shut_down_bus_refuses_to_work_and_leaves_the_channel(channel):
    a, b = LockstepBus(channel), LockstepBus(channel)
    b.shutdown()
    b.shutdown()  # twice is fine
    with pytest.raises(can.CanOperationError):
        b.recv(timeout=0)
    with pytest.raises(can.CanOperationError):
        b.send(_frame())
    a.send(_frame())  # nobody listening: nothing queued anywhere
    a.shutdown()


def test_a_bad_channel_is_refused():
    with pytest.raises(ValueError, match="LockstepBus: channel"):
        LockstepBus("")


def test_the_driver_and_codec_talk_over_the_lockstep_pair():
    controller, sim = virtual_bus_pair()
    try:
        driver = AgileXBaseDriver(controller, clock=lambda: 0.0)
        driver.send_motion(0.25, -0.5)
        record = codec.decode(sim.recv(timeout=0))
        assert isinstance(record, p.MotionCommand)
        assert (record.linear_mps, record.angular_radps) == (0.25, -0.5)
        sim.send(codec.encode(p.MotionState(linear_mps=0.1, angular_radps=0.0)))
        assert driver.poll() == 1
    finally:
        controller.shutdown()
        sim.shutdown()
