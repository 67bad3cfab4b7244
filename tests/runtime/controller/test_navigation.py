"""Controller state machine: start-up, watchdogs on every input, holds and resumes, E-stop
restart, latched stops, goal reached (fake base, synthetic sensors)."""
import math

import numpy as np
import pytest

from calibration.robot_description import load_robot_description
from firmware_bridge import protocol as p
from runtime.config import load_controller_config
from runtime.controller.navigation import ControllerState, NavigationController
from runtime.common.geometry import Pose2D
from runtime.io.hardware import BaseInputs
from runtime.loop.fixed_rate import StageClock
from runtime.common.sensor_data import ImuSample, LidarScan
from runtime.io.sensor_inbox import SensorInbox
from runtime.loop.telemetry import STAGES, TickTelemetry

DT = 0.05


class FakeBase:
    """A kinematic base: integrates the written command; each feedback stream can be silenced."""

    def __init__(self):
        self.t = 0.0
        self.left = self.right = 0.0
        self.v = self.w = 0.0
        self.silent: set[str] = set()  # "0x221", "0x311", "0x211"
        self.last = {"0x221": None, "0x311": None, "0x211": None}
        self.error_code = 0
        self.in_command_mode = True
        self.vehicle_state = p.VEHICLE_STATE_NORMAL
        self.flags: tuple[str, ...] = ()
        self.writes = []
        self.activations = 0

    def configure(self):
        pass

    def activate(self):
        self.activations += 1

    def deactivate(self):
        self.writes.append((0.0, 0.0))

    def advance(self, dt):
        track = 0.175
        self.left += (self.v - self.w * track / 2) * dt
        self.right += (self.v + self.w * track / 2) * dt
        self.t += dt

    def _receive(self):
        for stream in self.last:
            if stream not in self.silent:
                self.last[stream] = self.t

    def _age(self, stream, now_s):
        last = self.last[stream]
        return math.inf if last is None else now_s - last

    def read(self, now_s):
        self._receive()
        motion_age = self._age("0x221", now_s)
        return BaseInputs(
            stamp_s=now_s,
            feedback_lost=motion_age > 0.1,
            ever_received_motion_state=self.last["0x221"] is not None,
            in_command_mode=self.in_command_mode,
            error_code=self.error_code,
            linear_mps=self.v,
            angular_radps=self.w,
            odometry=(self.left, self.right) if self.last["0x311"] is not None else None,
            motion_state_age_s=motion_age,
            system_state_age_s=self._age("0x211", now_s),
            odometry_age_s=self._age("0x311", now_s),
            vehicle_state=self.vehicle_state,
            system_state_flags=self.flags,
        )

    def write(self, v, w):
        self.v, self.w = v, w
        self.writes.append((v, w))


class FakeSensors:
    """A lidar in a 4 x 4 m room (10 Hz frames with range noise) and a still IMU at 200 Hz (with
    its noise: a sample with the very same values as the 19 before is a stuck IMU)."""

    def __init__(self, inbox: SensorInbox, seed=0):
        self.inbox = inbox
        self.rng = np.random.default_rng(seed)
        self.next_frame_s = 0.0
        self.next_imu_s = 0.0
        self.lidar = "good"  # good | blind | far | frozen | silent
        self.imu_on = True
        self.imu_delay_s = 0.0  # samples reach the inbox this long after their stamp
        self.gyro_z_radps = 0.0
        self._imu_held: list[ImuSample] = []
        self._last_scan = None

    def room_scan(self, stamp_s):
        n = 6000
        az = self.rng.uniform(-math.pi, math.pi, n)
        # distance to a square room's wall 2 m away on each side
        r = 2.0 / np.maximum(np.abs(np.cos(az)), np.abs(np.sin(az)))
        r = r + self.rng.normal(0.0, 0.02, n)
        pts = np.stack([r * np.cos(az), r * np.sin(az), np.full(n, 0.05)], axis=1).astype(np.float32)
        offs = np.sort(self.rng.uniform(0.0, 0.099, n)).astype(np.float32)
        return LidarScan(stamp_s, pts, offs, 0.1)

    def step(self, t):
        while self.next_imu_s <= t + 1e-9:
            if self.imu_on:
                noise = self.rng.normal(0.0, 1e-3, 6)
                gyro = noise[:3] + np.array([0.0, 0.0, self.gyro_z_radps])
                self._imu_held.append(ImuSample(self.next_imu_s, gyro, np.array([0.0, 0.0, 9.81]) + noise[3:]))
            self.next_imu_s += 0.005
        while self._imu_held and self._imu_held[0].stamp_s + self.imu_delay_s <= t + 1e-9:
            self.inbox.put_imu(self._imu_held.pop(0))
        while self.next_frame_s + 0.1 <= t + 1e-9:
            stamp = self.next_frame_s
            self.next_frame_s += 0.1
            if self.lidar == "silent":
                continue
            if self.lidar == "frozen" and self._last_scan is not None:
                self.inbox.put_scan(self._last_scan)
                continue
            scan = self.room_scan(stamp)
            if self.lidar == "blind":
                scan = LidarScan(stamp, np.zeros((0, 3), np.float32), np.zeros(0, np.float32), 0.1, nothing_seen=True)
            elif self.lidar == "far":
                pts = scan.points_m * 5.0  # 10 m and more: beyond the planner's 6 m
                scan = LidarScan(stamp, pts, scan.point_time_offsets_s, 0.1)
            self._last_scan = scan
            self.inbox.put_scan(scan)


def make(goal=Pose2D(2.0, 0.0, 0.0), mode="pure-pursuit", sensors=False):
    """The state machine is tested with the sensorless placeholder planner unless `mode` says."""
    robot = load_robot_description()
    config = load_controller_config().with_planner_mode(mode)
    base = FakeBase()
    inbox = SensorInbox() if sensors else None
    ctl = NavigationController(robot, config, base, goal, clock=lambda: base.t, sensors=inbox, lockstep=True)
    ctl.activate()
    fake = FakeSensors(inbox) if sensors else None
    return ctl, base, fake


def run_ticks(ctl, base, n, sensors=None, before_tick=None):
    tel = TickTelemetry(capacity=4)
    stages = StageClock(np.full(len(STAGES), 1.0))
    for k in range(n):
        if before_tick:
            before_tick(k)
        if sensors is not None:
            sensors.step(base.t)
        row = tel.begin_tick()
        stages.start(row)
        ctl.tick(base.t, stages)
        ctl.slack_work()  # as the loop runs it, after the command is written
        base.advance(DT)


def events(ctl):
    return [(e.event, e.reason) for e in ctl.events]


def test_becomes_active_on_feedback_and_drives_to_the_goal():
    ctl, base, _ = make()
    run_ticks(ctl, base, 1)
    assert ctl.state is ControllerState.ACTIVE
    run_ticks(ctl, base, 200)
    assert ctl.state is ControllerState.GOAL_REACHED
    assert abs(ctl.pose.x_m - 2.0) < 0.15
    assert base.writes[-1] == (0.0, 0.0)
    speeds = np.array(base.writes)[:, 0]
    assert speeds.max() <= 1.0 + 1e-9
    assert np.max(np.abs(np.diff(speeds))) <= 2.0 * DT + 1e-9  # acceleration limit
    assert events(ctl)[-1][0] == "goal_reached"


@pytest.mark.parametrize("stream", ["0x221", "0x311", "0x211"])
def test_a_silent_feedback_stream_stops_the_robot_naming_it_and_it_resumes(stream):
    """Every feedback stream has a watchdog (not only 0x221): 0x311 stopping used to freeze the
    pose while the robot kept driving; 0x211 stopping kept stale error bits and mode."""
    ctl, base, _ = make(goal=Pose2D(20.0, 0.0, 0.0))
    run_ticks(ctl, base, 10)
    assert ctl.state is ControllerState.ACTIVE and base.v > 0.3
    base.silent.add(stream)
    run_ticks(ctl, base, 10)  # 0.5 s: longer than every timeout (0x211: 0.35 s)
    assert ctl.state is ControllerState.HOLDING
    assert base.writes[-1] == (0.0, 0.0)
    stop = ctl.events.last("stop")
    assert stop is not None and f"{stream} stale" in stop.reason
    base.silent.clear()
    run_ticks(ctl, base, 1)
    assert ctl.state is ControllerState.ACTIVE
    assert ctl.events.last().event == "resume"
    run_ticks(ctl, base, 1)
    assert 0.0 < base.writes[-1][0] <= 2.0 * DT * 2 + 1e-9  # ramps up from zero, never a jump


def test_a_silent_stream_is_detected_within_its_timeout():
    ctl, base, _ = make(goal=Pose2D(20.0, 0.0, 0.0))
    run_ticks(ctl, base, 10)
    base.silent.add("0x311")
    run_ticks(ctl, base, 2)  # 0.1 s: at the timeout, not beyond
    assert ctl.state is ControllerState.ACTIVE
    run_ticks(ctl, base, 1)
    assert ctl.state is ControllerState.HOLDING


def test_estop_holds_and_clearing_it_restarts_the_start_up_sequence():
    ctl, base, _ = make(goal=Pose2D(20.0, 0.0, 0.0))
    run_ticks(ctl, base, 20)
    v_before = base.v
    assert v_before > 0.5 and base.activations == 1
    base.vehicle_state = p.VEHICLE_STATE_ESTOP
    run_ticks(ctl, base, 1)
    assert ctl.state is ControllerState.HOLDING and base.writes[-1] == (0.0, 0.0)
    assert ctl.events.last("stop").reason == "E-stop"
    run_ticks(ctl, base, 20)
    assert base.activations == 1  # no enable while the E-stop is on
    base.vehicle_state = p.VEHICLE_STATE_NORMAL
    run_ticks(ctl, base, 1)
    assert base.activations == 2  # a fresh enable (0x421)
    assert ctl.state is ControllerState.INITIALIZING and base.writes[-1] == (0.0, 0.0)
    run_ticks(ctl, base, 1)
    assert ctl.state is ControllerState.ACTIVE
    assert 0.0 < base.writes[-1][0] <= 2.0 * DT + 1e-9 < v_before  # from zero, not at the old speed
    names = [e for e, _ in events(ctl)]
    assert names[-3:] == ["stop", "restart", "resume"]


@pytest.mark.parametrize("state, flags, words", [
    (p.VEHICLE_STATE_EXCEPTION, (), "exception"),
    (7, ("vehicle_state",), "unknown vehicle state 7"),
])
def test_any_vehicle_state_that_is_not_normal_stops_the_robot(state, flags, words):
    ctl, base, _ = make(goal=Pose2D(20.0, 0.0, 0.0))
    run_ticks(ctl, base, 10)
    base.vehicle_state, base.flags = state, flags
    run_ticks(ctl, base, 1)
    assert ctl.state is ControllerState.HOLDING and base.writes[-1] == (0.0, 0.0)
    assert words in ctl.events.last("stop").reason


def test_base_that_lost_our_command_stream_is_re_enabled_not_latched():
    ctl, base, _ = make(goal=Pose2D(20.0, 0.0, 0.0))
    run_ticks(ctl, base, 5)
    base.error_code = p.ERROR_HOST_COMM_LOST
    run_ticks(ctl, base, 1)
    assert base.activations == 2 and ctl.state is ControllerState.INITIALIZING
    assert "0x0200" in ctl.events.last("stop").reason
    run_ticks(ctl, base, 3)
    assert ctl.state is ControllerState.INITIALIZING  # the bit is still reported: wait
    assert base.activations == 2 and ctl.restarts == 1  # no enable per tick while it is
    base.error_code = 0  # the fresh enable cleared it
    run_ticks(ctl, base, 1)
    assert ctl.state is ControllerState.ACTIVE
    assert [e for e, _ in events(ctl)].count("restart") == 1


def test_a_base_that_keeps_saying_it_lost_us_is_re_enabled_at_a_bounded_rate():
    ctl, base, _ = make(goal=Pose2D(20.0, 0.0, 0.0))
    run_ticks(ctl, base, 5)
    base.error_code = p.ERROR_HOST_COMM_LOST
    run_ticks(ctl, base, 40)  # 2 s
    assert ctl.state is ControllerState.INITIALIZING and all(w == (0.0, 0.0) for w in base.writes[-40:])
    assert 3 <= ctl.restarts <= 5  # every 0.5 s, not every tick


def test_base_fault_bit_latches_stopped():
    ctl, base, _ = make()
    run_ticks(ctl, base, 5)
    base.error_code = p.ERROR_MOTOR_DRIVER
    run_ticks(ctl, base, 1)
    assert ctl.state is ControllerState.STOPPED and "0x0100" in ctl.stop_reason
    base.error_code = 0
    run_ticks(ctl, base, 5)  # latched
    assert ctl.state is ControllerState.STOPPED and base.writes[-1] == (0.0, 0.0)
    ctl.keepalive(base.t)
    assert base.writes[-1] == (0.0, 0.0)
    assert ctl.events.last().event == "safety_stop"


def test_remote_control_takeover_stops_the_controller():
    ctl, base, _ = make()
    run_ticks(ctl, base, 5)
    base.in_command_mode = False
    run_ticks(ctl, base, 1)
    assert ctl.state is ControllerState.STOPPED and "command mode" in ctl.stop_reason


def test_consecutive_deadline_misses_stop_the_robot():
    ctl, base, _ = make()
    run_ticks(ctl, base, 10)
    ctl.note_deadline(True)
    ctl.note_deadline(False)  # not consecutive: resets the count
    ctl.note_deadline(True)
    ctl.note_deadline(True)
    assert ctl.state is ControllerState.ACTIVE
    ctl.note_deadline(True)  # third in a row (config: 3)
    assert ctl.state is ControllerState.STOPPED
    run_ticks(ctl, base, 1)
    assert base.writes[-1] == (0.0, 0.0)


def test_a_deadline_stop_is_published_at_the_time_of_the_tick_that_overran():
    """The verdict comes after the tick (a tick that overran: a whole period later on the
    robot); the snapshot it republishes is still that tick's, at that tick's time, which a
    recording takes as the time the tick read its inputs at (dct replay replays it there)."""
    ctl, base, _ = make()
    run_ticks(ctl, base, 10)
    tick_s = ctl.snapshot.t_s
    ctl.note_deadline(True)
    ctl.note_deadline(True)
    base.t += 0.06  # the third overrunning tick ends 60 ms after it began
    ctl.note_deadline(True)
    assert ctl.state is ControllerState.STOPPED and ctl.snapshot.state is ControllerState.STOPPED
    assert ctl.snapshot.t_s == tick_s
    assert ctl.events.last().event == "safety_stop" and ctl.events.last().t_s == pytest.approx(base.t)


def test_no_feedback_at_start_up_times_out():
    ctl, base, _ = make()
    base.silent = {"0x221", "0x311", "0x211"}
    run_ticks(ctl, base, 10)
    assert ctl.state is ControllerState.INITIALIZING
    assert all(w == (0.0, 0.0) for w in base.writes)
    run_ticks(ctl, base, 15)  # past the 1 s start-up timeout
    assert ctl.state is ControllerState.STOPPED and "within" in ctl.stop_reason


# -- the lidar and the IMU (MPC mode) ---------------------------------------------------------

@pytest.fixture(scope="module")
def mpc_controller_factory():
    return lambda: make(goal=Pose2D(1.5, 0.0, 0.0), mode="all-fixed", sensors=True)


def test_mpc_never_moves_without_lidar_frames(mpc_controller_factory):
    ctl, base, sensors = mpc_controller_factory()
    sensors.lidar = "silent"
    run_ticks(ctl, base, 40, sensors)
    assert ctl.state is ControllerState.INITIALIZING
    assert all(w == (0.0, 0.0) for w in base.writes)
    assert any("lidar stale" in f.reason for f in ctl.faults)


@pytest.mark.parametrize("fault, words", [
    ("blind", "lidar blind: no returns"),
    ("far", "lidar blind: 0 of 20000 rays returned within 6 m"),
    ("frozen", "lidar frozen"),
    ("silent", "lidar stale"),
])
def test_a_lidar_that_cannot_see_stops_the_robot_and_good_frames_resume_it(mpc_controller_factory, fault, words):
    """An empty scan, one whose returns all lie beyond the planner's range, a repeated frame and
    no frame at all are "no data", never "free space"."""
    ctl, base, sensors = mpc_controller_factory()
    run_ticks(ctl, base, 16, sensors)
    assert ctl.state is ControllerState.ACTIVE and base.v > 0.2
    sensors.lidar = fault
    run_ticks(ctl, base, 8, sensors)
    assert ctl.state is ControllerState.HOLDING
    assert base.writes[-1] == (0.0, 0.0)
    assert words in ctl.events.last("stop").reason
    sensors.lidar = "good"
    run_ticks(ctl, base, 4, sensors)
    assert ctl.state is ControllerState.ACTIVE
    assert ctl.events.last("resume") is not None


def test_a_silent_imu_stops_the_robot(mpc_controller_factory):
    ctl, base, sensors = mpc_controller_factory()
    run_ticks(ctl, base, 16, sensors)
    assert ctl.state is ControllerState.ACTIVE
    sensors.imu_on = False
    run_ticks(ctl, base, 3, sensors)
    assert ctl.state is ControllerState.HOLDING and "IMU stale" in ctl.events.last("stop").reason
    sensors.imu_on = True
    run_ticks(ctl, base, 2, sensors)
    assert ctl.state is ControllerState.ACTIVE


def test_a_late_imu_holds_the_robot_and_its_late_samples_still_turn_the_heading(mpc_controller_factory):
    """Samples arriving 80 ms after they were taken (a loaded link) are stale: the robot holds.
    They are still true, stamped when taken: the odometry integrates them, so the rotation of that
    time is in the heading (left out, it was lost for good)."""
    ctl, base, sensors = mpc_controller_factory()
    run_ticks(ctl, base, 16, sensors)
    assert ctl.state is ControllerState.ACTIVE
    wheels = ctl.odometry.wheels
    t0, yaw0, covered0 = base.t, wheels.raw_gyro_yaw_rad, wheels.gyro_covered_s
    sensors.gyro_z_radps, sensors.imu_delay_s = 0.3, 0.08
    run_ticks(ctl, base, 10, sensors)
    assert ctl.state is ControllerState.HOLDING and "IMU stale" in ctl.events.last("stop").reason
    sensors.imu_delay_s = 0.0
    run_ticks(ctl, base, 4, sensors)
    assert ctl.state is ControllerState.ACTIVE
    # every sample since then integrated, the late ones too: no gap in the gyro's time
    assert wheels.gyro_covered_s - covered0 == pytest.approx(base.t - t0, abs=1e-6)
    assert wheels.raw_gyro_yaw_rad - yaw0 == pytest.approx(0.3 * (base.t - t0), abs=0.003)


def test_a_saturated_imu_sample_stops_the_robot(mpc_controller_factory):
    ctl, base, sensors = mpc_controller_factory()
    run_ticks(ctl, base, 16, sensors)
    assert ctl.state is ControllerState.ACTIVE
    from runtime.common.sensor_data import MAX_GYRO_RADPS

    sensors.inbox.put_imu(ImuSample(base.t + 0.001, np.array([0.0, 0.0, MAX_GYRO_RADPS]), np.zeros(3),
                                    saturated=True))
    run_ticks(ctl, base, 1)
    assert ctl.state is ControllerState.HOLDING and "IMU saturated" in ctl.events.last("stop").reason


# -- goals changing while driving (request_goal) ----------------------------------------------------
def test_a_new_goal_while_driving_redirects_the_robot_within_the_limits():
    ctl, base, _ = make(goal=Pose2D(3.0, 0.0, 0.0))
    run_ticks(ctl, base, 20)  # 1 s: driving along +x
    assert ctl.state is ControllerState.ACTIVE and ctl.pose.x_m > 0.3 and abs(ctl.pose.y_m) < 1e-6
    ctl.request_goal(Pose2D(2.5, 2.0, 0.0), "test")
    assert ctl.goal == Pose2D(3.0, 0.0, 0.0)  # taken by the next tick's read stage, not before
    xs = []
    run_ticks(ctl, base, 400, before_tick=lambda k: xs.append(ctl.pose.x_m))
    assert ctl.state is ControllerState.GOAL_REACHED
    assert math.hypot(ctl.pose.x_m - 2.5, ctl.pose.y_m - 2.0) < 0.15
    assert max(xs) < 2.7  # it turned towards the new goal, it did not go on towards (3, 0)
    speeds = np.array(base.writes)[:, 0]
    assert np.max(np.abs(np.diff(speeds))) <= 2.0 * DT + 1e-9  # the change ramps, it never jumps
    ev = events(ctl)
    assert [e for e, _ in ev].count("new_goal") == 1
    assert any(e == "new_goal" and "while driving" in r and "from test" in r for e, r in ev)
    assert ctl.goals_received == 2 and ctl.goals_reached == 1


def test_at_the_goal_the_controller_waits_for_the_next_one_idle_then_drives_again():
    ctl, base, _ = make(goal=Pose2D(1.0, 0.0, 0.0))
    run_ticks(ctl, base, 200)
    assert ctl.state is ControllerState.GOAL_REACHED and ctl.finished
    n_writes, n_events = len(base.writes), len(ctl.events)
    run_ticks(ctl, base, 100)  # 5 s idle: zero command, nothing happens, not a fault
    assert ctl.state is ControllerState.GOAL_REACHED and ctl.hold_reason is None
    assert set(base.writes[n_writes:]) == {(0.0, 0.0)} and len(ctl.events) == n_events
    ctl.request_goal(Pose2D(2.5, -0.6, 0.0), "/goal_pose")
    run_ticks(ctl, base, 1)
    assert ctl.state is ControllerState.ACTIVE and ctl.goal_reached_at_s is None
    run_ticks(ctl, base, 300)
    assert ctl.state is ControllerState.GOAL_REACHED
    assert math.hypot(ctl.pose.x_m - 2.5, ctl.pose.y_m + 0.6) < 0.15
    assert ctl.goals_reached == 2 and [e for e, _ in events(ctl)].count("goal_reached") == 2
    assert ctl.describe()["goals_received"] == 2


def test_an_estop_while_idle_at_the_goal_holds_restarts_and_returns_to_idle_then_a_new_goal_drives():
    """Idle at the goal is not outside the watchdogs: an E-stop there holds (a stop event, not
    finished), its release restarts the base (a fresh enable), and the controller is idle at the
    goal again, not driving; a goal after that drives with nothing left pending."""
    ctl, base, _ = make(goal=Pose2D(1.0, 0.0, 0.0))
    run_ticks(ctl, base, 200)
    assert ctl.state is ControllerState.GOAL_REACHED and ctl.finished and base.activations == 1
    base.vehicle_state = p.VEHICLE_STATE_ESTOP
    run_ticks(ctl, base, 2)
    assert ctl.state is ControllerState.HOLDING and not ctl.finished
    assert ctl.events.last("stop").reason == "E-stop" and base.writes[-1] == (0.0, 0.0)
    base.vehicle_state = p.VEHICLE_STATE_NORMAL
    run_ticks(ctl, base, 3)
    assert base.activations == 2 and ctl.state is ControllerState.GOAL_REACHED and ctl.finished
    assert [e for e, _ in events(ctl)][-3:] == ["stop", "restart", "resume"]
    assert ctl.goals_reached == 1 and not ctl._restart_pending
    ctl.request_goal(Pose2D(2.0, 0.0, 0.0), "/goal_pose")
    run_ticks(ctl, base, 300)
    assert ctl.state is ControllerState.GOAL_REACHED and ctl.goals_reached == 2 and base.activations == 2
    assert abs(ctl.pose.x_m - 2.0) < 0.15


@pytest.mark.parametrize("goal,field", [(Pose2D(math.nan, 0.0, 0.0), "x_m"), (Pose2D(0.0, math.inf, 0.0), "y_m"),
                                        (Pose2D(0.0, 0.0, math.nan), "yaw_rad"), (Pose2D(2e4, 0.0, 0.0), "x_m")])
def test_a_bad_goal_is_refused_naming_its_source_and_field_and_the_robot_keeps_its_goal(goal, field):
    from runtime.controller.navigation import GoalError

    ctl, base, _ = make(goal=Pose2D(2.0, 0.0, 0.0))
    run_ticks(ctl, base, 5)
    with pytest.raises(GoalError, match=rf"/goal_pose.*{field}"):
        ctl.request_goal(goal, "/goal_pose")
    run_ticks(ctl, base, 5)
    assert ctl.goal == Pose2D(2.0, 0.0, 0.0) and ctl.goals_received == 1
    assert "new_goal" not in [e for e, _ in events(ctl)]


def test_the_same_goal_again_changes_nothing_and_a_stopped_robot_stays_stopped():
    ctl, base, _ = make(goal=Pose2D(2.0, 0.0, 0.0))
    run_ticks(ctl, base, 10)
    ctl.request_goal(Pose2D(2.0 + 1e-4, 0.0, 0.0), "/goal_pose")  # a repeated publication
    run_ticks(ctl, base, 1)
    assert ctl.goals_repeated == 1 and ctl.goals_received == 1 and "new_goal" not in [e for e, _ in events(ctl)]
    base.error_code = p.ERROR_MOTOR_DRIVER  # a base fault bit: latched stop
    run_ticks(ctl, base, 3)
    assert ctl.state is ControllerState.STOPPED
    ctl.request_goal(Pose2D(-1.0, 0.0, 0.0), "/goal_pose")
    run_ticks(ctl, base, 20)
    assert ctl.state is ControllerState.STOPPED and ctl.goal == Pose2D(-1.0, 0.0, 0.0)
    assert set(base.writes[-20:]) == {(0.0, 0.0)}


def test_in_standby_every_stage_runs_but_the_robot_waits_for_its_goal():
    """goal_given False (a robot switched on before it is sent): ACTIVE after the start-up
    sequence, commanding zero, until give_goal; then it drives to the goal, the goal logged."""
    robot = load_robot_description()
    base = FakeBase()
    ctl = NavigationController(robot, load_controller_config().with_planner_mode("pure-pursuit"), base,
                               Pose2D(2.0, 0.0, 0.0), clock=lambda: base.t, lockstep=True, goal_given=False)
    ctl.activate()
    run_ticks(ctl, base, 40)
    assert ctl.state is ControllerState.ACTIVE and not ctl.goal_given
    assert all(w == (0.0, 0.0) for w in base.writes) and abs(ctl.pose.x_m) < 1e-6
    given_at = base.t
    ctl.give_goal(given_at)
    assert ctl.goal_given_at_s == given_at and events(ctl)[-1][0] == "goal"
    run_ticks(ctl, base, 200)
    assert ctl.state is ControllerState.GOAL_REACHED and ctl.goal_reached_at_s > given_at
    assert ctl.describe()["goal_given_at_s"] == given_at


def test_an_early_started_icp_worker_is_ready_at_activation_and_closed_when_the_build_fails(monkeypatch):
    """start_odometry (the assembly's): the ICP worker starts while the rest is built and is
    ready (warmed up) once the controller is active; a build that fails after it started closes
    it (no orphan process)."""
    import runtime.controller.parts as parts
    from runtime.odometry.stage import OdometryStage

    robot = load_robot_description()
    config = load_controller_config().with_planner_mode("pure-pursuit")
    base = FakeBase()
    ctl = NavigationController(robot, config, base, Pose2D(2.0, 0.0, 0.0), clock=lambda: base.t,
                               sensors=SensorInbox(), start_odometry=True)
    try:
        worker = ctl.odometry.worker
        assert worker is not None  # started by the build, before activation
        ctl.activate()
        assert ctl.odometry.worker is worker and worker.ready and worker.failed is None
    finally:
        ctl.deactivate()
    assert ctl.odometry.worker is None

    closed = []
    close = OdometryStage.close
    monkeypatch.setattr(OdometryStage, "close", lambda self: (closed.append(self.worker), close(self)))

    def broken(*args, **kwargs):
        raise RuntimeError("no distance net")

    monkeypatch.setattr(parts, "build_planner", broken)
    with pytest.raises(RuntimeError, match="no distance net"):
        NavigationController(robot, config, FakeBase(), Pose2D(2.0, 0.0, 0.0), clock=lambda: 0.0,
                             sensors=SensorInbox(), start_odometry=True)
    assert len(closed) == 1 and closed[0] is not None
