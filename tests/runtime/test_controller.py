"""Controller state machine: start-up, safety stop latch, goal reached (fake hardware)."""
import numpy as np

from calibration.robot_description import load_robot_description
from runtime.config import load_controller_config
from runtime.controller import ControllerState, NavigationController
from runtime.geometry import Pose2D
from runtime.hardware import BaseInputs
from runtime.loop import StageClock
from runtime.telemetry import STAGES, TickTelemetry


class FakeBase:
    """A kinematic base: integrates the written command; feedback can be withheld."""

    def __init__(self):
        self.t = 0.0
        self.x = self.y = self.yaw = 0.0
        self.left = self.right = 0.0
        self.v = self.w = 0.0
        self.feedback_on = True
        self.error_code = 0
        self.in_command_mode = True
        self.writes = []
        self.activated = False

    def configure(self):
        pass

    def activate(self):
        self.activated = True

    def deactivate(self):
        self.writes.append((0.0, 0.0))

    def advance(self, dt):
        track = 0.175
        self.left += (self.v - self.w * track / 2) * dt
        self.right += (self.v + self.w * track / 2) * dt
        self.t += dt

    def read(self, now_s):
        return BaseInputs(
            stamp_s=now_s,
            feedback_lost=not self.feedback_on,
            ever_received_motion_state=True,
            in_command_mode=self.in_command_mode,
            error_code=self.error_code,
            linear_mps=self.v,
            angular_radps=self.w,
            odometry=(self.left, self.right),
        )

    def write(self, v, w):
        self.v, self.w = v, w
        self.writes.append((v, w))


def make(goal=Pose2D(2.0, 0.0, 0.0), mode="pure-pursuit"):
    """The state machine is tested with the sensorless placeholder planner unless `mode` says."""
    robot = load_robot_description()
    config = load_controller_config().with_planner_mode(mode)
    base = FakeBase()
    ctl = NavigationController(robot, config, base, goal, clock=lambda: base.t)
    ctl.activate()
    return ctl, base


def run_ticks(ctl, base, n, before_tick=None):
    tel = TickTelemetry(capacity=4)
    stages = StageClock(np.full(len(STAGES), 1.0))
    for k in range(n):
        if before_tick:
            before_tick(k)
        row = tel.begin_tick()
        stages.start(row)
        ctl.tick(base.t, stages)
        base.advance(0.05)


def test_becomes_active_on_feedback_and_drives_to_the_goal():
    ctl, base = make()
    run_ticks(ctl, base, 1)
    assert ctl.state is ControllerState.ACTIVE
    run_ticks(ctl, base, 200)
    assert ctl.state is ControllerState.GOAL_REACHED
    assert abs(ctl.pose.x_m - 2.0) < 0.15
    assert base.writes[-1] == (0.0, 0.0)
    speeds = np.array(base.writes)[:, 0]
    assert speeds.max() <= 1.0 + 1e-9
    assert np.max(np.abs(np.diff(speeds))) <= 2.0 * 0.05 + 1e-9  # acceleration limit


def test_feedback_loss_latches_stopped_with_zero_command():
    ctl, base = make()
    run_ticks(ctl, base, 10)
    assert base.v > 0
    base.feedback_on = False
    run_ticks(ctl, base, 1)
    assert ctl.state is ControllerState.STOPPED
    assert "feedback lost" in ctl.stop_reason
    assert base.writes[-1] == (0.0, 0.0)
    base.feedback_on = True  # latched: coming back does not restart motion
    run_ticks(ctl, base, 5)
    assert ctl.state is ControllerState.STOPPED and base.writes[-1] == (0.0, 0.0)
    ctl.keepalive(base.t)
    assert base.writes[-1] == (0.0, 0.0)


def test_mpc_never_moves_without_fresh_lidar_points():
    """The default planner (MPC) holds zero while it has no obstacle points, or only stale ones."""
    ctl, base = make(mode="all-fixed")
    assert load_controller_config().planner.mode == "all-fixed"  # the shipped default
    run_ticks(ctl, base, 40)
    assert ctl.state is ControllerState.ACTIVE
    assert all(w == (0.0, 0.0) for w in base.writes)
    assert ctl.stale_scan_holds >= 38


def test_consecutive_deadline_misses_stop_the_robot():
    ctl, base = make()
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


def test_no_feedback_at_start_up_times_out():
    ctl, base = make()

    def no_feedback(k):
        base.feedback_on = False

    base.read_orig = base.read

    def read(now_s):
        inputs = base.read_orig(now_s)
        return BaseInputs(**{**inputs.__dict__, "ever_received_motion_state": False, "feedback_lost": True})

    base.read = read
    run_ticks(ctl, base, 10)
    assert ctl.state is ControllerState.INITIALIZING
    assert all(w == (0.0, 0.0) for w in base.writes)
    run_ticks(ctl, base, 15)  # past the 1 s start-up timeout
    assert ctl.state is ControllerState.STOPPED and "within" in ctl.stop_reason


def test_base_error_bit_stops_the_controller():
    ctl, base = make()
    run_ticks(ctl, base, 5)
    base.error_code = 0x0200  # base lost our command stream
    run_ticks(ctl, base, 1)
    assert ctl.state is ControllerState.STOPPED and "0x0200" in ctl.stop_reason


def test_remote_control_takeover_stops_the_controller():
    ctl, base = make()
    run_ticks(ctl, base, 5)
    base.in_command_mode = False
    run_ticks(ctl, base, 1)
    assert ctl.state is ControllerState.STOPPED
