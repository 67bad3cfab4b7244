"""The emulated base firmware: protocol behaviour, motor model, and driving the MuJoCo robot.

Physics tests run in lockstep: the test plays the host (0x421 once, then 0x111 every 20 ms on
a python-can virtual bus), and each physics step calls emulator.step -> world.set_wheel_torques
-> world.step.
"""
from __future__ import annotations

import uuid
from collections import defaultdict
from dataclasses import dataclass, field
from typing import Callable

import can
import numpy as np
import pytest
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st

from calibration.robot_description import RobotDescription, load_robot_description
from firmware_bridge import codec, frame_errors
from firmware_bridge import protocol as p
from firmware_bridge.firmware_emulator import EmulatedBaseFirmware, FirmwareEmulatorError
from hil_sim.world.scenario import Scenario, load_scenario
from hil_sim.world.mujoco_world import World

ROBOT = load_robot_description()
COMMAND_PERIOD_S = 0.02


def open_floor(**extra) -> Scenario:
    """An empty 20 x 20 m floor with the robot at the origin facing +x."""
    raw = {
        "name": "open_floor",
        "floor": {"size_m": [20.0, 20.0], "friction": 0.8},
        "robot": {"start": {"x_m": -5.0, "y_m": 0.0}},
        "goal": {"pose": {"x_m": 5.0, "y_m": 0.0}, "tolerance_m": 0.2},
        "time_limit_s": 30.0,
    }
    raw.update(extra)
    return Scenario.model_validate(raw)


def bus_pair() -> tuple[can.BusABC, can.BusABC]:
    channel = f"hil-fw-{uuid.uuid4().hex}"
    return (can.Bus(interface="virtual", channel=channel, preserve_timestamps=True),
            can.Bus(interface="virtual", channel=channel, preserve_timestamps=True))


@dataclass
class Trace:
    """What a lockstep drive recorded (log every physics step)."""

    t: list[float] = field(default_factory=list)
    pose: list[tuple[float, float, float]] = field(default_factory=list)
    body_vel: list[tuple[float, float, float]] = field(default_factory=list)
    wheel_speeds: list[np.ndarray] = field(default_factory=list)
    currents: list[np.ndarray] = field(default_factory=list)
    frames: list[tuple[float, object]] = field(default_factory=list)
    command_times: list[float] = field(default_factory=list)
    #: Wheel angles handed to the firmware, keyed by the step time the frames carry.
    angles_in: dict[float, np.ndarray] = field(default_factory=dict)

    def arrays(self):
        return (np.array(self.t), np.array(self.pose), np.array(self.body_vel),
                np.array(self.wheel_speeds), np.array(self.currents))

    def records(self, cls) -> list[tuple[float, object]]:
        return [(t, r) for t, r in self.frames if isinstance(r, cls)]


def drive(
    world: World,
    command: Callable[[float], tuple[float, float] | None],
    duration_s: float,
    *,
    enable: bool = True,
    robot: RobotDescription = ROBOT,
    firmware: EmulatedBaseFirmware | None = None,
    buses: tuple[can.BusABC, can.BusABC] | None = None,
    on_step: Callable[[World], None] | None = None,
) -> tuple[Trace, EmulatedBaseFirmware]:
    """Lockstep drive: command(t) -> (v, omega) sent as 0x111 every 20 ms, None = send nothing."""
    fw_bus, host = buses or bus_pair()
    fw = firmware or EmulatedBaseFirmware(fw_bus, robot)
    trace = Trace()
    if enable:
        host.send(codec.encode(p.ControlModeCommand(mode=p.CONTROL_MODE_CAN)))
    t_end = world.time_s + duration_s
    next_cmd = world.time_s
    try:
        while world.time_s < t_end - 0.5 * world.timestep_s:
            t = world.time_s
            if t >= next_cmd - 1e-9:
                cmd = command(t)
                if cmd is not None:
                    host.send(codec.encode(p.MotionCommand(linear_mps=cmd[0], angular_radps=cmd[1])))
                    trace.command_times.append(t)
                next_cmd += COMMAND_PERIOD_S
            angles = world.wheel_angles_rad()
            trace.angles_in[t] = angles
            torques = fw.step(t, world.wheel_speeds_radps(), angles)
            world.set_wheel_torques(torques)
            world.step()
            if on_step is not None:
                on_step(world)
            while (msg := host.recv(timeout=0.0)) is not None:
                trace.frames.append((t, codec.decode(msg)))
            trace.t.append(world.time_s)
            trace.pose.append(world.robot_pose())
            trace.body_vel.append(world.robot_body_velocity())
            trace.wheel_speeds.append(world.wheel_speeds_radps())
            trace.currents.append(fw.last_currents_a.copy())
    finally:
        if buses is None:
            fw_bus.shutdown()
            host.shutdown()
    return trace, fw


# ------------------------------------------------------------------------------------------
# Physics requirements
# ------------------------------------------------------------------------------------------
def test_straight_0p5_mps_reaches_speed_within_5_percent():
    world = World(open_floor(), ROBOT)
    trace, fw = drive(world, lambda t: (0.5, 0.0), 3.0)
    t, pose, vel, wheels, _ = trace.arrays()
    late = t > 2.0
    gt_speed = vel[late, 0].mean()
    reported = np.array([r.linear_mps for tt, r in trace.records(p.MotionState) if tt > 2.0])
    assert len(reported) >= 45
    assert abs(gt_speed - 0.5) <= 0.025, gt_speed
    assert np.all(np.abs(reported - 0.5) <= 0.025), reported
    assert abs(pose[-1, 1]) < 0.01 and abs(pose[-1, 2]) < 0.01  # straight, no yaw drift
    assert fw.error_code == 0 and fw.frames_rejected == 0


def test_command_timeout_stops_the_wheels_and_latches_error():
    world = World(open_floor(), ROBOT)
    trace, fw = drive(world, lambda t: (0.5, 0.0) if t < 1.5 else None, 2.3)
    last = trace.command_times[-1]
    t, _, vel, wheels, _ = trace.arrays()
    states = trace.records(p.SystemState)
    # Error bit 0x0200 appears in the first 0x211 after the timeout, not before.
    before = [r.error_code for tt, r in states if tt < last + 0.5 - 1e-6]
    after = [r.error_code for tt, r in states if tt >= last + 0.5 + 1e-6]
    assert all(code & p.ERROR_HOST_COMM_LOST == 0 for code in before)
    assert after and all(code & p.ERROR_HOST_COMM_LOST for code in after)
    assert np.all(fw.wheel_targets_radps == 0.0)
    # Still moving at full speed just before the timeout (the firmware did not stop early).
    i_before = np.searchsorted(t, last + 0.49)
    assert vel[i_before, 0] > 0.45
    # The first 0x221 at or after 520 ms reports (about) zero, and the wheels have stopped.
    motion_after = [(tt, r) for tt, r in trace.records(p.MotionState) if tt >= last + 0.52 - 1e-6]
    assert abs(motion_after[0][1].linear_mps) <= 0.01, motion_after[:3]
    i520 = np.searchsorted(t, last + 0.52)
    assert np.all(np.abs(wheels[i520]) < 0.5), wheels[i520]
    # The body stops shortly after (ground truth; braking distance is physics, not firmware).
    stopped = t[(t > last + 0.5) & (np.abs(vel[:, 0]) < 0.005)]
    assert stopped.size and stopped[0] - last < 0.65, stopped[:1] - last


def test_one_kg_box_is_pushed_and_30_kg_box_is_not():
    free_world = World(open_floor(), ROBOT)
    free, _ = drive(free_world, lambda t: (0.4, 0.0), 2.5)
    _, _, _, _, free_currents = free.arrays()
    free_current = np.abs(free_currents[-1000:]).mean()

    light = World(load_scenario("push_1kg"), ROBOT)
    start_light = light.obstacle_position("box")
    drive(light, lambda t: (0.4, 0.0), 2.5)
    moved_light = np.linalg.norm(light.obstacle_position("box")[:2] - start_light[:2])

    heavy = World(load_scenario("push_30kg"), ROBOT)
    start_heavy = heavy.obstacle_position("box")
    trace, _ = drive(heavy, lambda t: (0.4, 0.0), 2.5)
    moved_heavy = np.linalg.norm(heavy.obstacle_position("box")[:2] - start_heavy[:2])
    t, pose, vel, wheels, currents = trace.arrays()
    late = t > 1.5

    assert moved_light > 0.4, moved_light
    assert moved_heavy < 0.03, moved_heavy
    assert np.ptp(pose[late, 0]) < 0.03  # the robot is stuck against it (it may jostle)
    assert np.abs(wheels[late]).mean() * ROBOT.drive.wheel_radius_m > 0.05  # wheels slip
    stuck_current = np.abs(currents[late]).mean()
    assert stuck_current > 3.0 * free_current, (stuck_current, free_current)
    # 0x251..0x254 show it (the wheels slip, so rpm stays near the commanded ~85 rpm).
    hs = [r for tt, r in trace.records(p.ActuatorHighSpeed) if tt > 1.5]
    hs_free = [r for tt, r in free.records(p.ActuatorHighSpeed) if tt > 1.5]
    assert np.mean([abs(r.current_a) for r in hs]) > 3.0 * max(0.1, np.mean([abs(r.current_a) for r in hs_free]))


@pytest.mark.parametrize("omega", [1.0, -1.0])
def test_turning_direction_follows_the_sign_of_omega(omega):
    world = World(open_floor(), ROBOT)
    trace, _ = drive(world, lambda t: (0.0, omega), 2.0)
    _, pose, vel, _, _ = trace.arrays()
    yaw = np.unwrap(pose[:, 2])
    assert np.sign(yaw[-1]) == np.sign(omega) and abs(yaw[-1]) > 0.2, yaw[-1]
    assert np.hypot(pose[-1, 0] + 5.0, pose[-1, 1]) < 0.05  # turned in place
    reported = [r.angular_radps for tt, r in trace.records(p.MotionState) if tt > 1.0]
    assert np.all(np.sign(reported) == np.sign(omega))


def test_arc_turns_left_while_driving_forward():
    world = World(open_floor(), ROBOT)
    trace, _ = drive(world, lambda t: (0.5, 0.5), 2.0)
    _, pose, vel, _, _ = trace.arrays()
    assert pose[-1, 0] > -5.0 + 0.6 and pose[-1, 1] > 0.0 and pose[-1, 2] > 0.1


# ------------------------------------------------------------------------------------------
# Protocol behaviour
# ------------------------------------------------------------------------------------------
def test_standby_ignores_motion_until_can_mode():
    world = World(open_floor(), ROBOT)
    fw_bus, host = bus_pair()
    try:
        trace, fw = drive(world, lambda t: (0.5, 0.0), 0.5, enable=False, buses=(fw_bus, host))
        assert fw.control_mode == p.CONTROL_MODE_STANDBY
        assert fw.commands_ignored >= 20
        assert abs(world.robot_pose()[0] + 5.0) < 1e-3
        assert all(r.control_mode == p.CONTROL_MODE_STANDBY for _, r in trace.records(p.SystemState))
        trace, fw = drive(world, lambda t: (0.5, 0.0), 1.0, firmware=fw, buses=(fw_bus, host))
        assert fw.control_mode == p.CONTROL_MODE_CAN
        assert world.robot_pose()[0] + 5.0 > 0.2
        assert trace.records(p.SystemState)[-1][1].control_mode == p.CONTROL_MODE_CAN
    finally:
        fw_bus.shutdown()
        host.shutdown()


def test_timeout_latch_needs_a_new_enable():
    world = World(open_floor(), ROBOT)
    fw_bus, host = bus_pair()
    try:
        _, fw = drive(world, lambda t: (0.3, 0.0) if t < 0.5 else None, 1.2, buses=(fw_bus, host))
        assert fw.comm_lost
        x0 = world.robot_pose()[0]
        # Commands resume without 0x421: ignored, robot stays.
        _, fw = drive(world, lambda t: (0.3, 0.0), 0.5, enable=False, firmware=fw, buses=(fw_bus, host))
        assert fw.comm_lost and fw.commands_ignored > 0
        assert abs(world.robot_pose()[0] - x0) < 0.01
        # 0x441 does not clear it either.
        host.send(codec.encode(p.ErrorClearCommand(code=p.ERROR_CLEAR_ALL)))
        _, fw = drive(world, lambda t: (0.3, 0.0), 0.2, enable=False, firmware=fw, buses=(fw_bus, host))
        assert fw.comm_lost and fw.error_clears == 1
        # A new enable clears the bit and the robot moves again.
        trace, fw = drive(world, lambda t: (0.3, 0.0), 0.8, firmware=fw, buses=(fw_bus, host))
        assert not fw.comm_lost
        assert world.robot_pose()[0] - x0 > 0.1
        assert trace.records(p.SystemState)[-1][1].error_code & p.ERROR_HOST_COMM_LOST == 0
    finally:
        fw_bus.shutdown()
        host.shutdown()


def test_feedback_periods_counters_and_odometry():
    world = World(open_floor(), ROBOT)
    trace, fw = drive(world, lambda t: (0.4, 0.0), 2.0)
    counts: dict[int, int] = defaultdict(int)
    for _, r in trace.frames:
        fid = codec._record_frame_id(r)
        counts[fid] += 1
    assert counts[p.ID_MOTION_STATE] in (100, 101)
    assert counts[p.ID_ODOMETRY] in (100, 101)
    for k in range(4):
        assert counts[p.ID_ACTUATOR_HS_BASE + k] in (100, 101)
        assert counts[p.ID_ACTUATOR_LS_BASE + k] in (20, 21)
    assert counts[p.ID_SYSTEM_STATE] in (20, 21)
    assert counts[p.ID_BMS] in (2, 3)
    rolling = [r.count for _, r in trace.records(p.SystemState)]
    assert rolling == [i % 256 for i in range(len(rolling))]
    # 0x311 wheel distances agree with the ground-truth distance driven (no slip when cruising).
    odo = trace.records(p.Odometry)[-1][1]
    driven = world.robot_pose()[0] + 5.0
    assert abs(odo.left_wheel_m - driven) < 0.02 and abs(odo.right_wheel_m - driven) < 0.02
    # Pulse counts follow the wheel angle: pulses_per_rev per revolution.
    for tt, r in trace.records(p.ActuatorHighSpeed)[-8:]:
        angle = trace.angles_in[tt][r.motor_index]
        expected = angle / (2 * np.pi) * ROBOT.motors.encoder_pulses_per_rev
        assert abs(r.pulse_count - expected) <= 1.0
        assert r.rpm > 0  # forward is positive on both sides


@settings(max_examples=80, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    frame_id=st.one_of(st.sampled_from([0x111, 0x421, 0x441]), st.integers(0, 0x7FF)),
    data=st.binary(min_size=0, max_size=8),
    extended=st.booleans(),
)
def test_bad_frames_are_counted_and_never_acted_on(frame_id, data, extended):
    msg = can.Message(arbitration_id=frame_id, is_extended_id=extended, data=data, dlc=len(data))
    try:
        codec.decode(msg)
        bad = False
    except frame_errors.FrameError:
        bad = True
    assume(bad)
    fw_bus, host = bus_pair()
    try:
        fw = EmulatedBaseFirmware(fw_bus, ROBOT)
        host.send(codec.encode(p.ControlModeCommand(mode=p.CONTROL_MODE_CAN)))
        fw.step(0.0, np.zeros(4), np.zeros(4))
        host.send(msg)
        torques = fw.step(0.01, np.zeros(4), np.zeros(4))
        assert fw.frames_rejected == 1
        assert fw.control_mode == p.CONTROL_MODE_CAN and fw.error_code == 0
        assert fw.commanded == (0.0, 0.0) and fw.last_command_time_s is None
        assert np.all(fw.wheel_targets_radps == 0.0) and np.all(torques == 0.0)
    finally:
        fw_bus.shutdown()
        host.shutdown()


# ------------------------------------------------------------------------------------------
# Motor model without physics
# ------------------------------------------------------------------------------------------
def _enabled_firmware(v: float, omega: float) -> tuple[EmulatedBaseFirmware, can.BusABC, can.BusABC]:
    fw_bus, host = bus_pair()
    fw = EmulatedBaseFirmware(fw_bus, ROBOT)
    host.send(codec.encode(p.ControlModeCommand(mode=p.CONTROL_MODE_CAN)))
    host.send(codec.encode(p.MotionCommand(linear_mps=v, angular_radps=omega)))
    fw.step(0.0, np.zeros(4), np.zeros(4))
    return fw, fw_bus, host


def test_targets_follow_ramp_and_differential_kinematics():
    fw, a, b = _enabled_firmware(0.5, 1.0)
    try:
        r, track = ROBOT.drive.wheel_radius_m, ROBOT.drive.track_m
        t = 0.0
        for _ in range(400):  # 0.4 s: beyond the ramps (0.25 s for v, 0.17 s for omega)
            t += 0.001
            fw.step(t, fw.wheel_targets_radps.copy(), np.zeros(4))
        left, right = (0.5 - 1.0 * track / 2) / r, (0.5 + 1.0 * track / 2) / r
        np.testing.assert_allclose(fw.wheel_targets_radps, [right, left, left, right], rtol=1e-9)
    finally:
        a.shutdown()
        b.shutdown()
    fw, a, b = _enabled_firmware(0.5, 0.0)
    try:
        fw.step(0.1, np.zeros(4), np.zeros(4))
        expected_v = ROBOT.limits.max_linear_accel_mps2 * 0.1
        np.testing.assert_allclose(fw.wheel_targets_radps, expected_v / ROBOT.drive.wheel_radius_m, rtol=1e-9)
    finally:
        a.shutdown()
        b.shutdown()


def test_current_is_clamped_by_limit_and_back_emf():
    mot = ROBOT.motors
    fw, a, b = _enabled_firmware(1.0, ROBOT.limits.max_angular_speed_radps)
    try:
        for k in range(1, 700):
            if k % 300 == 0:  # keep-alive
                b.send(codec.encode(p.MotionCommand(linear_mps=1.0, angular_radps=ROBOT.limits.max_angular_speed_radps)))
            fw.step(k * 0.001, np.zeros(4), np.zeros(4))  # blocked wheels
        assert np.all(np.abs(fw.last_currents_a) <= mot.current_limit_a + 1e-12)
        assert np.allclose(np.abs(fw.last_currents_a), mot.current_limit_a)
        # A blocked wheel shows high current and zero rpm on 0x251..0x254.
        frames = []
        while (msg := b.recv(timeout=0.0)) is not None:
            frames.append(codec.decode(msg))
        hs = [r for r in frames if isinstance(r, p.ActuatorHighSpeed)][-4:]
        assert [r.rpm for r in hs] == [0, 0, 0, 0]
        assert all(abs(r.current_a) == pytest.approx(mot.current_limit_a) for r in hs)
        low = [r for r in frames if isinstance(r, p.ActuatorLowSpeed)][-4:]
        assert all(r.driver_state & 0x04 for r in low)  # over-current: > 0.5 s at the limit

        np.testing.assert_allclose(fw.last_torques_nm, mot.torque_constant_nm_per_a * fw.last_currents_a)
        # Near the no-load speed the supply cannot push the current up: (V - k w) / R.
        w_fast = np.full(4, 0.95 * mot.supply_voltage_v / mot.torque_constant_nm_per_a)
        fw.wheel_targets_radps[:] = 0.0
        fw._integral[:] = [10.0] * 4  # a wound-up integrator asks for far more than is available
        torques = fw.step(0.7, w_fast, np.zeros(4))
        cap = (mot.supply_voltage_v - mot.torque_constant_nm_per_a * w_fast) / mot.resistance_ohm
        assert np.all(fw.last_currents_a <= cap + 1e-9)
        assert np.all(torques <= mot.torque_constant_nm_per_a * cap + 1e-9)
    finally:
        a.shutdown()
        b.shutdown()


def test_commands_are_clamped_to_the_description_limits():
    fw, a, b = _enabled_firmware(5.0, -20.0)
    try:
        assert fw.commanded == (ROBOT.limits.max_linear_speed_mps, -ROBOT.limits.max_angular_speed_radps)
    finally:
        a.shutdown()
        b.shutdown()


def test_bad_step_arguments_raise():
    fw_bus, host = bus_pair()
    try:
        fw = EmulatedBaseFirmware(fw_bus, ROBOT)
        with pytest.raises(FirmwareEmulatorError, match="4 wheel speeds"):
            fw.step(0.0, np.zeros(3), np.zeros(4))
        with pytest.raises(FirmwareEmulatorError, match="non-finite"):
            fw.step(0.0, np.array([0, 0, np.nan, 0]), np.zeros(4))
        fw.step(1.0, np.zeros(4), np.zeros(4))
        with pytest.raises(FirmwareEmulatorError, match="backwards"):
            fw.step(0.5, np.zeros(4), np.zeros(4))
    finally:
        fw_bus.shutdown()
        host.shutdown()


def test_estop_stops_the_wheels_reports_it_and_ignores_motion_until_released():
    world = World(open_floor(), ROBOT)
    fw_bus, host = bus_pair()
    try:
        _, fw = drive(world, lambda t: (0.5, 0.0), 1.0, buses=(fw_bus, host))
        x0 = world.robot_pose()[0]
        fw.emergency_stop = True
        trace, fw = drive(world, lambda t: (0.5, 0.0), 1.0, enable=False, firmware=fw, buses=(fw_bus, host))
        states = [r.vehicle_state for _, r in trace.records(p.SystemState)]
        assert states and all(s == p.VEHICLE_STATE_ESTOP for s in states)
        assert world.robot_pose()[0] - x0 < 0.2  # braked, then stood (0.5 m/s: ~6 cm of braking)
        assert np.allclose(fw.wheel_targets_radps, 0.0) and fw.commands_ignored > 0
        assert not fw.comm_lost  # the host kept sending: its stream is not lost
        x1 = world.robot_pose()[0]
        fw.emergency_stop = False
        trace, fw = drive(world, lambda t: (0.5, 0.0), 1.0, enable=False, firmware=fw, buses=(fw_bus, host))
        assert trace.records(p.SystemState)[-1][1].vehicle_state == p.VEHICLE_STATE_NORMAL
        assert world.robot_pose()[0] - x1 > 0.2
    finally:
        fw_bus.shutdown()
        host.shutdown()


def test_suppressed_feedback_frames_are_not_sent():
    world = World(open_floor(), ROBOT)
    fw_bus, host = bus_pair()
    fw = EmulatedBaseFirmware(fw_bus, ROBOT)
    fw.suppressed_frame_ids = {p.ID_ODOMETRY}
    try:
        trace, fw = drive(world, lambda t: (0.3, 0.0), 0.5, firmware=fw, buses=(fw_bus, host))
        assert trace.records(p.Odometry) == [] and fw.frames_suppressed >= 24
        assert len(trace.records(p.MotionState)) >= 24
        fw.suppressed_frame_ids.clear()
        trace, fw = drive(world, lambda t: (0.3, 0.0), 0.1, firmware=fw, buses=(fw_bus, host))
        assert len(trace.records(p.Odometry)) >= 4
    finally:
        fw_bus.shutdown()
        host.shutdown()


def test_a_reboot_is_silent_with_the_motors_off_and_comes_back_in_standby_with_odometers_at_zero():
    world = World(open_floor(), ROBOT)
    fw_bus, host = bus_pair()
    try:
        trace, fw = drive(world, lambda t: (0.5, 0.0), 1.5, buses=(fw_bus, host))
        assert trace.records(p.Odometry)[-1][1].left_wheel_m > 0.4
        fw.booting = True
        trace, fw = drive(world, lambda t: (0.5, 0.0), 0.5, enable=False, firmware=fw, buses=(fw_bus, host))
        assert trace.frames == [] and np.allclose(fw.last_torques_nm, 0.0)  # silent, motors off
        fw.booting = False
        x0 = world.robot_pose()[0]
        trace, fw = drive(world, lambda t: (0.5, 0.0), 0.5, enable=False, firmware=fw, buses=(fw_bus, host))
        states = [r for _, r in trace.records(p.SystemState)]
        assert states and all(s.control_mode == p.CONTROL_MODE_STANDBY and s.error_code == 0 for s in states)
        assert states[0].count == 0 and fw.reboots == 1
        assert abs(trace.records(p.Odometry)[0][1].left_wheel_m) < 0.05  # the odometers restarted
        assert world.robot_pose()[0] - x0 < 0.15 and fw.commands_ignored > 0  # standby: 0x111 ignored
        trace, fw = drive(world, lambda t: (0.5, 0.0), 1.0, firmware=fw, buses=(fw_bus, host))  # a fresh enable
        assert world.robot_pose()[0] - x0 > 0.3
    finally:
        fw_bus.shutdown()
        host.shutdown()


def test_an_injected_driver_fault_is_reported_and_stops_the_wheels_while_it_lasts():
    world = World(open_floor(), ROBOT)
    fw_bus, host = bus_pair()
    try:
        _, fw = drive(world, lambda t: (0.5, 0.0), 1.0, buses=(fw_bus, host))
        fw.injected_error = p.ERROR_MOTOR_DRIVER
        x0 = world.robot_pose()[0]
        trace, fw = drive(world, lambda t: (0.5, 0.0), 1.0, enable=False, firmware=fw, buses=(fw_bus, host))
        assert all(r.error_code & p.ERROR_MOTOR_DRIVER for _, r in trace.records(p.SystemState))
        assert world.robot_pose()[0] - x0 < 0.2 and np.allclose(fw.wheel_targets_radps, 0.0)
        fw.injected_error = 0
        trace, fw = drive(world, lambda t: (0.5, 0.0), 0.3, enable=False, firmware=fw, buses=(fw_bus, host))
        assert trace.records(p.SystemState)[-1][1].error_code == 0
    finally:
        fw_bus.shutdown()
        host.shutdown()


def test_the_remote_control_takes_the_base_and_leaves_it_in_standby():
    world = World(open_floor(), ROBOT)
    fw_bus, host = bus_pair()
    try:
        _, fw = drive(world, lambda t: (0.5, 0.0), 1.0, buses=(fw_bus, host))
        fw.rc_takeover = True
        x0 = world.robot_pose()[0]
        # the host tries to take it back: 0x421 is ignored while the remote control has it
        trace, fw = drive(world, lambda t: (0.5, 0.0), 1.0, enable=True, firmware=fw, buses=(fw_bus, host))
        assert all(r.control_mode == p.CONTROL_MODE_RC for _, r in trace.records(p.SystemState))
        assert world.robot_pose()[0] - x0 < 0.2
        fw.rc_takeover = False
        trace, fw = drive(world, lambda t: (0.5, 0.0), 0.3, enable=False, firmware=fw, buses=(fw_bus, host))
        assert trace.records(p.SystemState)[-1][1].control_mode == p.CONTROL_MODE_STANDBY
    finally:
        fw_bus.shutdown()
        host.shutdown()
