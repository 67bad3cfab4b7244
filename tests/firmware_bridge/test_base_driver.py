"""AgileXBaseDriver over a virtual bus against a tiny fake base peer."""
from __future__ import annotations

import math

import can
import numpy as np
import pytest

from firmware_bridge import candump, codec
from firmware_bridge import protocol as p
from firmware_bridge.base_driver import AgileXBaseDriver


def drain(bus: can.BusABC) -> list[str]:
    out = []
    while (m := bus.recv(timeout=0)) is not None:
        out.append(candump.format_candump(m))
    return out


def test_enable_sequence_bytes(virtual_pair, clock):
    bus, peer = virtual_pair
    drv = AgileXBaseDriver(bus, clock)
    drv.enable()
    drv.send_motion(0.15, 0.0)
    drv.send_motion(0.0, 0.05)
    assert drain(peer) == ["421#0100000000000000", "111#0096000000000000", "111#0000003200000000"]
    assert drv.last_command == p.MotionCommand(0.0, 0.05)


def test_feedback_staleness_with_fake_clock(virtual_pair, clock):
    bus, peer = virtual_pair
    drv = AgileXBaseDriver(bus, clock, feedback_timeout_s=0.1)
    assert drv.feedback_lost  # before the first 0x221
    assert drv.poll() == 0
    clock.t = 1.0
    peer.send(codec.encode(p.MotionState(0.4, -0.1)))
    assert drv.poll() == 1
    fb = drv.feedback
    assert fb.motion.record == p.MotionState(0.4, -0.1) and fb.motion.stamp_s == 1.0
    assert not drv.feedback_lost
    clock.t = 1.099
    assert not drv.feedback_lost
    clock.t = 1.101
    assert drv.feedback_lost
    # Other frames do not refresh the 0x221 stamp.
    peer.send(codec.encode(p.SystemState(0, 1, 12.0, 0, 0, 0)))
    drv.poll()
    assert drv.feedback_lost
    peer.send(codec.encode(p.MotionState(0.0, 0.0)))
    drv.poll()
    assert not drv.feedback_lost and math.isclose(drv.feedback_age_s, 0.0)


def test_control_mode_and_errors(virtual_pair, clock):
    bus, peer = virtual_pair
    drv = AgileXBaseDriver(bus, clock)
    assert drv.control_mode is None and drv.error_code is None and drv.errors_active() == []
    peer.send(codec.encode(p.SystemState(0, p.CONTROL_MODE_STANDBY, 12.1, 0, 0, 0)))
    drv.poll()
    assert drv.control_mode == p.CONTROL_MODE_STANDBY and drv.control_mode_name == "standby"
    peer.send(codec.encode(p.SystemState(0, p.CONTROL_MODE_CAN, 12.1,
                                     p.ERROR_HOST_COMM_LOST | p.ERROR_MOTOR2_COMM, 0, 1)))
    drv.poll()
    assert drv.control_mode == p.CONTROL_MODE_CAN
    assert drv.error_code == 0x0210
    assert drv.errors_active() == ["motor2_comm", "host_comm_lost"]
    peer.send(codec.encode(p.SystemState(0, 1, 12.1, 0, 0, 5)))  # counter jumped 1 -> 5
    drv.poll()
    assert drv.feedback.system_count_gaps == 1


def test_bad_frames_counted_and_never_acted_on(virtual_pair, clock):
    bus, peer = virtual_pair
    drv = AgileXBaseDriver(bus, clock)
    peer.send(codec.encode(p.MotionState(0.2, 0.0)))
    peer.send(can.Message(arbitration_id=0x221, data=b"\x7f\xff", is_extended_id=False))  # short
    peer.send(can.Message(arbitration_id=0x5AA, data=bytes(8), is_extended_id=False))  # unknown
    peer.send(can.Message(arbitration_id=0x211, data=bytes([0, 9, 0, 0, 0, 0, 0, 0]), is_extended_id=False))
    assert drv.poll() == 4
    fb = drv.feedback
    assert fb.motion.record.linear_mps == 0.2  # the short frame did not overwrite it
    # A feedback field outside its range is kept and flagged, not dropped with the whole frame:
    # control mode 9 is not CAN command mode, so the controller will not drive on it.
    assert fb.system.record.flagged_fields == ("control_mode",) and drv.control_mode == 9
    assert fb.decode_error_counts == {"wrong_dlc": 1, "unknown_frame_id": 1}
    assert "0x5AA" in fb.last_decode_error and fb.frames_received == 4


def test_an_unknown_vehicle_state_reaches_the_controller_as_not_normal(virtual_pair, clock):
    from runtime.io.hardware import AgileXBaseHardware

    bus, peer = virtual_pair
    hw = AgileXBaseHardware(AgileXBaseDriver(bus, clock))
    peer.send(can.Message(arbitration_id=0x211, data=bytes([7, 1, 0, 240, 0x02, 0x00, 0, 5]), is_extended_id=False))
    inputs = hw.read(clock())
    assert inputs.vehicle_state == 7 and inputs.system_state_flags == ("vehicle_state",)
    assert not inputs.vehicle_normal and not inputs.ready
    assert inputs.error_code == 0x0200  # the rest of the frame is kept


def test_actuator_and_odometry_feedback(virtual_pair, clock):
    bus, peer = virtual_pair
    drv = AgileXBaseDriver(bus, clock)
    clock.t = 2.5
    for i in range(4):
        peer.send(codec.encode(p.ActuatorHighSpeed(i, 100 * (i + 1), 0.5, 1000 * i)))
        peer.send(codec.encode(p.ActuatorLowSpeed(i, 12.0, 30, 31, 0)))
    peer.send(codec.encode(p.Odometry(1.5, 1.6)))
    assert drv.poll() == 9
    fb = drv.feedback
    assert [s.record.rpm for s in fb.actuator_hs] == [100, 200, 300, 400]
    assert [s.record.motor_index for s in fb.actuator_ls] == [0, 1, 2, 3]
    assert fb.odometry.record == p.Odometry(1.5, 1.6) and fb.odometry.stamp_s == 2.5
    assert drv.motor_currents_a(2.55, 0.1) == (0.5, 0.5, 0.5, 0.5)
    assert drv.motor_currents_a(2.7, 0.1) is None  # stale: no evidence of a push


def test_motor_currents_need_all_four_motors(virtual_pair, clock):
    bus, peer = virtual_pair
    drv = AgileXBaseDriver(bus, clock)
    clock.t = 1.0
    for i in range(3):
        peer.send(codec.encode(p.ActuatorHighSpeed(i, 100, -1.2, 0)))
    drv.poll()
    assert drv.motor_currents_a(1.0, 0.1) is None
    peer.send(codec.encode(p.ActuatorHighSpeed(3, 100, 2.4, 0)))
    drv.poll()
    assert drv.motor_currents_a(1.0, 0.1) == (-1.2, -1.2, -1.2, 2.4)


@pytest.mark.parametrize("bad", [math.nan, math.inf, np.float32("nan"), 33.0, -40.0, "1", None, True])
def test_send_motion_rejects_bad_values(virtual_pair, clock, bad):
    bus, peer = virtual_pair
    drv = AgileXBaseDriver(bus, clock)
    with pytest.raises(ValueError):
        drv.send_motion(bad, 0.0)
    with pytest.raises(ValueError):
        drv.send_motion(0.0, bad)
    assert drain(peer) == []


def test_shutdown_sends_zero_and_survives_dead_bus(virtual_pair, clock):
    bus, peer = virtual_pair
    drv = AgileXBaseDriver(bus, clock)
    drv.send_motion(0.5, 0.3)
    assert drv.shutdown() == 3
    frames = drain(peer)
    assert frames[0] == "111#01F4012C00000000"
    assert frames[1:] == ["111#0000000000000000"] * 3
    bus.shutdown()
    assert drv.shutdown() == 0  # does not raise


def test_no_periodic_tasks(virtual_pair, clock):
    bus, peer = virtual_pair
    drv = AgileXBaseDriver(bus, clock)
    drv.enable()
    drv.send_motion(0.1, 0.0)
    assert bus._periodic_tasks == []  # commands come from the caller's loop only


def test_send_motion_accepts_numpy_scalars(virtual_pair, clock):
    bus, peer = virtual_pair
    drv = AgileXBaseDriver(bus, clock)
    drv.send_motion(np.float32(0.15), np.float64(0.05))
    assert drain(peer) == ["111#0096003200000000"]


def test_each_watched_stream_has_its_own_age_and_the_vehicle_state_is_kept(virtual_pair, clock):
    bus, peer = virtual_pair
    drv = AgileXBaseDriver(bus, clock)
    for fid in (p.ID_MOTION_STATE, p.ID_SYSTEM_STATE, p.ID_ODOMETRY):
        assert drv.frame_age_s(fid) == math.inf
    assert drv.vehicle_state is None
    clock.t = 2.0
    peer.send(codec.encode(p.Odometry(1.0, 1.0)))
    peer.send(codec.encode(p.SystemState(p.VEHICLE_STATE_ESTOP, 1, 12.0, 0, 0, 0)))
    drv.poll()
    clock.t = 2.5
    peer.send(codec.encode(p.MotionState(0.0, 0.0)))
    drv.poll()
    assert drv.frame_age_s(p.ID_ODOMETRY) == pytest.approx(0.5)
    assert drv.frame_age_s(p.ID_SYSTEM_STATE, now_s=3.0) == pytest.approx(1.0)
    assert drv.frame_age_s(p.ID_MOTION_STATE) == pytest.approx(0.0)
    assert drv.vehicle_state == p.VEHICLE_STATE_ESTOP
    with pytest.raises(ValueError, match="not a watched feedback frame"):
        drv.frame_age_s(p.ID_BMS)


def test_frames_polled_at_a_tick_are_stamped_with_its_time_so_ages_are_tick_differences(virtual_pair, clock):
    """A control loop's tick reads the bus a few milliseconds after its start; stamped with the
    clock then, a frame 0.1 s older at a later tick would look fresher than the tick times say
    (and than a replay of the run, whose clock is the tick's). Given the tick's time, the age and
    the feedback-lost verdict are those of the tick times alone."""
    bus, peer = virtual_pair
    drv = AgileXBaseDriver(bus, clock, feedback_timeout_s=0.1)
    clock.t = 10.004  # the clock when the tick at 10.000 polls
    peer.send(codec.encode(p.Odometry(1.0, 1.0)))
    peer.send(codec.encode(p.MotionState(0.1, 0.0)))
    assert drv.poll(now_s=10.0) == 2
    clock.t = 10.1002  # the next-but-one tick, at 10.1001 (its jitter), reads its clock late again
    assert drv.frame_age_s(p.ID_ODOMETRY, 10.1001) == pytest.approx(0.1001, abs=1e-9)
    assert drv.frame_age_s(p.ID_ODOMETRY, 10.1001) > 0.1  # stale at that tick, as a replay finds it
    assert drv.feedback_lost_at(10.1001)
    assert not drv.feedback_lost_at(10.0999)
    # without a tick's time, the clock stamps (a tool that polls on its own)
    peer.send(codec.encode(p.MotionState(0.1, 0.0)))
    drv.poll()
    assert drv.frame_age_s(p.ID_MOTION_STATE, 10.2) == pytest.approx(10.2 - 10.1002)
    assert not drv.feedback_lost
