"""What `dct run` does after each tick, outside the tick's timings (the loop's after_tick hook):
the sensor-to-command latency, the recorder, the ROS publisher, new goals, the systemd watchdog,
the console's state lines (holds, stops, a calibration mismatch and the partition's fall-back, a
step of the system clock).

It reads the controller's published snapshot (runtime.controller.snapshot), never its internals,
and everything it does is O(1) and non-blocking: the publisher and the recorder have their own
threads and bounded queues.

Sensor-to-command latency: for each tick that used a new lidar frame, the loop-clock time at
which its command was written minus the end of that frame (its last point's time).
"""
from __future__ import annotations

import re

import numpy as np

from runtime.controller.goals import GoalError


_NUMBER = re.compile(r"\d+(\.\d+)?")


class LatencyTracker:
    """Sensor-to-command latency per new lidar frame (module docstring); preallocated."""

    def __init__(self, capacity: int = 1 << 16) -> None:
        self._buf = np.zeros(capacity)
        self._n = 0
        self._last_scan = None

    def note(self, scan, written_s: float | None) -> None:
        if scan is None or scan is self._last_scan or written_s is None:
            return
        self._last_scan = scan
        offs = scan.point_time_offsets_s
        frame_end = float(scan.stamp_s) + (float(offs.max()) if len(offs) else float(scan.frame_duration_s))
        self._buf[self._n % len(self._buf)] = written_s - frame_end
        self._n += 1

    def values(self) -> np.ndarray:
        return self._buf[: min(self._n, len(self._buf))].copy()


class RunObserver:
    """The after_tick hook of `dct run` (module docstring)."""

    def __init__(self, assembly, ros, publisher, receiver, notifier, echo, record_hook=None) -> None:
        """assembly: runtime.controller.builder.Assembly; ros: the config's `ros` section;
        publisher, receiver: runtime.io.ros; notifier: systemd's (runtime.app.deploy.sd_notify);
        echo: where to say a goal was ignored; record_hook: the recorder's after_tick, or None."""
        self.assembly = assembly
        self.ros, self.publisher, self.receiver = ros, publisher, receiver
        self.notifier, self.echo, self.record_hook = notifier, echo, record_hook
        self.latency = LatencyTracker()
        self.goals_ignored = 0
        self._said: tuple[str, str] | None = None
        self._said_mismatch = False
        self._said_at_s = -1e9
        #: runtime.app.resume.ResumeWriter (`--resume-file`), or None
        self.resume_writer = None
        self._said_resume = False
        self._clock_steps_said = 0

    def __call__(self, row: np.void) -> None:
        from runtime.io.ros.publisher import TickView

        snap = self.assembly.controller.snapshot
        telemetry = self.assembly.telemetry
        self.latency.note(snap.scan, self.assembly.loop.stage_clock.write_done_loop_s)
        if self.record_hook is not None:
            self.record_hook(row)
        out = self.ros.outputs
        clouds = int(row["tick"]) % out.clouds_every_ticks == 0
        self.publisher.offer(TickView(
            stamp_s=float(row["scheduled_s"]), pose=snap.pose, v_mps=snap.command[0],
            omega_radps=snap.command[1], state=snap.state.name,
            stage_ms={s: float(row["stage_s"][i]) * 1e3 for i, s in enumerate(telemetry.stages)},
            tick_ms=float(row["tick_s"]) * 1e3,
            extra={"deadline_misses": telemetry.deadline_misses, "hold_reason": snap.hold_reason or "",
                   "stop_reason": snap.stop_reason or "", "safety": snap.safety or "",
                   "active_mode": snap.active_mode, "finished": snap.finished,
                   "goal_x": snap.goal.x_m, "goal_y": snap.goal.y_m, "pose_x": snap.pose.x_m,
                   "pose_y": snap.pose.y_m, "pose_yaw": snap.pose.yaw_rad,
                   "partition_fallback": snap.partition_fallback[0] if snap.partition_fallback else "",
                   "calibration_mismatch": snap.calibration_mismatch or ""},
            points_fix=snap.points_fix if clouds else None,
            plan_states=snap.plan.states if clouds and snap.plan is not None else None,
            # P_mov as the partition labelled it: the scan deskewed to the tick
            points_mov=snap.p_mov_lidar() if clouds and snap.partition_frame is not None else None,
            clouds=clouds,
        ))
        if self.resume_writer is not None:
            if not self._said_resume and snap.resume_outcome is not None:
                self._said_resume = True
                self.echo(f"dct run: odometry {snap.resume_outcome}")
            p, g = snap.pose, snap.goal
            self.resume_writer.offer((p.x_m, p.y_m, p.yaw_rad), snap.wheels_m, (g.x_m, g.y_m, g.yaw_rad),
                                     snap.state.name == "GOAL_REACHED")
        self._take_goal()
        self._say_clock_step()
        self._say_state(snap)
        self._say_fallback(snap)
        self.notifier.watchdog()

    #: At most one console line about holds per this many seconds (a flapping input would flood it).
    SAY_EVERY_S = 1.0

    def _say_clock_step(self) -> None:
        """Say on the console when the sensor inbox saw the system clock stepped (an int read a tick)."""
        inbox = self.receiver.inbox
        if inbox.clock_steps != self._clock_steps_said:
            self._clock_steps_said = inbox.clock_steps
            self.echo(f"dct run: {inbox.last_clock_step}")

    def _say_state(self, snap) -> None:
        """Say on the console when the controller starts or stops holding or stops, and why."""
        why = (snap.stop_reason if snap.state.name == "STOPPED" else
               snap.hold_reason if snap.state.name == "HOLDING" else "") or ""
        now = (snap.state.name, _NUMBER.sub("#", why))  # the same hold with older ages is no news
        if now == self._said or (snap.t_s - self._said_at_s < self.SAY_EVERY_S and now[0] == "HOLDING"):
            return
        if self._said is not None or why:
            self.echo(f"dct run: {snap.state.name}" + (f": {why}" if why else ""))
        self._said, self._said_at_s = now, snap.t_s

    def _say_fallback(self, snap) -> None:
        """Say once on the console that the calibration was found wrong, and what the partition does."""
        mismatch = snap.calibration_mismatch
        if mismatch is None or self._said_mismatch:
            return
        self._said_mismatch = True
        if snap.partition_fallback is not None:
            self.echo(f"dct run: {snap.state.name}: partition all-fixed (every lidar point an obstacle) from "
                      f"t={snap.partition_fallback[1]:.2f} s: calibration mismatch: {mismatch}")
        else:
            self.echo(f"dct run: {snap.state.name}: calibration mismatch: {mismatch}")

    def _take_goal(self) -> None:
        """A new goal from the goal topic: validated now, taken by the next tick. Goals the
        receiver refused (malformed, outside the goal workspace) are said and counted here."""
        for refused in self.receiver.take_goal_rejections():
            self.goals_ignored += 1
            self.echo(f"dct run: goal refused: {refused}")
        g = self.receiver.take_goal()
        if g is None:
            return
        odom = self.ros.outputs.odom_frame
        if g.frame_id not in ("", odom):
            self.goals_ignored += 1
            self.echo(f"dct run: goal in frame {g.frame_id!r} ignored: goals are taken in the odometry frame ({odom!r})")
            return
        try:
            self.assembly.controller.request_goal(g.pose, self.ros.inputs.goal.topic)
        except GoalError as exc:
            self.goals_ignored += 1
            self.echo(f"dct run: {exc}: ignored")
