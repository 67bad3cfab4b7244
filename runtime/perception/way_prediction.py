"""Where the moving tracks go, and which of their ways the robot must keep clear of
(runtime.perception.moving_obstacles, steps 4-5).

4. Prediction: a moving cluster's points (at most `max_points`, evenly picked) carried along its
   velocity every `step_s` up to `horizon_s` (constant velocity: a person who turns is found again
   within `window_s`); at least `min_way_m` of way (time capped by `max_horizon_s`); for a person
   coming down a line that passes over the robot, until the person is past the robot (at most
   `max_horizon_s`), so that the way leaves the robot its two sides to go to, not its end to go
   round (docs/decisions/people-way-length.md).
5. Conflict: a person whose predicted points come within `conflict_radius_m` of where the robot,
   going straight on, would be about then (that step +- one) would meet the robot; a conflict is
   one both holding the robot's speed (at least `min_extrapolation_speed_mps`) and speeding up to
   its cruise speed at its acceleration limit (a crossing it clears in a hurry is one it drives
   through), and one where braking would not keep the robot clear of the person but going on
   would, by its footprint every `go_dt_s`, is none either (`WayPredictor._goes_first`: the robot
   goes on, and keeps going); it holds `conflict_hold_s` after the last scan that found it. Only
   then does the person's whole way ahead go to the planner and the supervisor. A robot already
   in the person's way (its centre within `in_the_way_m` of the person's predicted centre line)
   loses the predicted points of a channel out of it (runtime.perception.exit_channel); one
   beside the way keeps them all and holds before it (docs/decisions/people-conflict-test.md).
"""
from __future__ import annotations

import math

import numpy as np

from runtime.perception.cluster_tracking import Track
from runtime.perception.exit_channel import exit_channel


class RobotMotion:
    """The robot going straight on from p0 along the unit vector u, from speed v0: how far it
    goes in time tau holding its speed (at least the minimum), hurrying on to cruise at its
    acceleration limit, or braking at it. config: PredictorSettings."""

    def __init__(self, config, robot_pose, robot_speed_mps: float) -> None:
        c = config
        self.config = c
        self.u = np.array([math.cos(robot_pose[2]), math.sin(robot_pose[2])])
        self.p0 = np.array([robot_pose[0], robot_pose[1]], dtype=np.float64)
        self.v0 = max(0.0, float(robot_speed_mps))
        self.steady_speed = max(self.v0, c.min_extrapolation_speed_mps)
        self.t_acc = max(0.0, c.cruise_speed_mps - self.v0) / c.accel_mps2
        self.t_stop = self.v0 / c.accel_mps2

    def steady(self, tau: float) -> float:
        return self.steady_speed * tau

    def hurried(self, tau: float) -> float:
        c, v0, t_acc = self.config, self.v0, self.t_acc
        if tau <= t_acc:
            return v0 * tau + 0.5 * c.accel_mps2 * tau * tau
        return v0 * t_acc + 0.5 * c.accel_mps2 * t_acc * t_acc + c.cruise_speed_mps * (tau - t_acc)

    def braking(self, tau: float) -> float:
        c, v0 = self.config, self.v0
        tau = min(tau, self.t_stop)
        return v0 * tau - 0.5 * c.accel_mps2 * tau * tau

    def meets(self, corridor: list[np.ndarray], travel) -> bool:
        """Does a predicted step k of the corridor come within conflict_radius_m of the robot
        between steps k - 1 and k + 1, the robot going travel(tau) by time tau?"""
        c, p0, u = self.config, self.p0, self.u
        for k, q in enumerate(corridor, start=1):
            a = p0 + u * travel(max(0.0, (k - 1) * c.step_s))  # the robot one step before ...
            b = p0 + u * travel((k + 1) * c.step_s)  # ... to one step after
            ab = b - a
            f = np.clip(((q - a) @ ab) / max(float(ab @ ab), 1e-12), 0.0, 1.0)
            if (np.hypot(*(q - (a + f[:, None] * ab)).T) <= c.conflict_radius_m).any():
                return True
        return False


class WayPredictor:
    """Steps 4-5 (module docstring); config: PredictorSettings."""

    def __init__(self, config) -> None:
        self.config = config
        self.conflicts = 0  # scans in which a moving track would meet the robot (never reset)

    def predict(self, now_s: float, moving: list[Track], robot_pose, robot_speed_mps: float) -> np.ndarray:
        """Each moving cluster's points carried along its velocity at every step, kept where the
        robot, going straight on at its speed (at least min_extrapolation_speed_mps), would be
        within conflict_radius_m of them about then (+- one step): a crossing the robot clears
        before the person arrives, or one the person has passed, does not hold it up; one they
        would reach together does, unless braking would leave the robot in the person's way and
        going on clears it (_goes_first)."""
        c = self.config
        steps = int(c.horizon_s / c.step_s + 1e-9)
        if not moving or steps <= 0:
            return np.zeros((0, 2))
        motion = RobotMotion(c, robot_pose, robot_speed_mps)
        out = []
        for t in moving:
            way = self._way(now_s, t, steps, motion)
            if way is not None:
                out.append(way)
        self.conflicts += int(bool(out))
        return np.concatenate(out) if out else np.zeros((0, 2))

    def _way(self, now_s: float, t: Track, steps: int, motion: RobotMotion) -> np.ndarray | None:
        """The track's way ahead the robot keeps clear of (None: none, no conflict)."""
        c = self.config
        pts = t.points
        if len(pts) > c.max_points:
            pts = pts[np.linspace(0, len(pts) - 1, c.max_points).astype(np.intp)]
        speed = float(np.hypot(*t.velocity))
        n = max(steps, self._steps_past_robot(t, motion.p0),
                int(min(c.max_horizon_s, c.min_way_m / max(speed, 1e-6)) / c.step_s + 1e-9))
        corridor = [pts + t.velocity * (k * c.step_s) for k in range(1, n + 1)]
        if now_s - t.moving_since_s < c.min_moving_s:
            return None  # a glimpse: a static object's view changing shows such (step 3)
        if all(motion.meets(corridor, travel) for travel in (motion.steady, motion.hurried)):
            t.corridor_conflict_s = t.last[0]
            if self._goes_first(t, pts, motion, n * c.step_s):
                t.passing_first = t.passing_first or t.last[0] > t.conflict_until_s
            else:
                t.passing_first = False
                t.conflict_until_s = t.last[0] + c.conflict_hold_s
        if t.last[0] > t.corridor_conflict_s + c.conflict_hold_s:
            t.passing_first = False  # past: a later meeting is decided afresh
        if t.last[0] > t.conflict_until_s:
            t.exit_side = None
            return None
        way = np.concatenate(corridor)  # the person's way ahead: the robot goes behind, or waits
        # Never frozen in the person's way: a robot the person's centre line passes over gets
        # out of it (the real person stays P_fix) rather than holding still in it.
        p0 = motion.p0
        a = np.array(t.last[1:])
        ab = t.velocity * (n * c.step_s)
        f = min(1.0, max(0.0, float((p0 - a) @ ab) / max(float(ab @ ab), 1e-12)))
        if math.hypot(*(p0 - (a + f * ab))) < c.in_the_way_m:
            way = way[exit_channel(c, way, a, t.velocity, p0, motion.u, t)]
        return way

    def _goes_first(self, t: Track, pts: np.ndarray, motion: RobotMotion, horizon_s: float) -> bool:
        """A conflict by the corridor test (step 5): does the robot rather go on in front of the
        person? Each way (braking at the acceleration limit, or hurrying on to cruise) has a least
        gap between the footprint and the person's predicted points, and that gap less
        go_uncertainty_mps x the time ahead (its margin). The robot yields when braking keeps a
        margin of go_clearance_m; it goes when braking does not, going on has the larger gap, and
        its margin is not negative (it keeps clear of a person go_uncertainty_mps faster than
        estimated). Head-on both gaps are nil: it yields. Having gone, it goes on while going on
        keeps go_commit_clearance_m (a later, faster estimate of the same person does not turn
        the go into a stop in the person's lane). See docs/decisions/people-go-first.md."""
        c = self.config
        go, go_now = self._gap(pts, t.velocity, motion, motion.hurried, horizon_s)
        if t.passing_first and go_now >= c.go_commit_clearance_m:
            return True
        stop, stop_now = self._gap(pts, t.velocity, motion, motion.braking, horizon_s)
        return stop < c.go_clearance_m and go_now > stop_now and go >= 0.0

    def _gap(self, pts: np.ndarray, velocity: np.ndarray, motion: RobotMotion, travel,
             horizon_s: float) -> tuple[float, float]:
        """The robot along its heading (travel(tau): how far by then), its footprint against the
        person's points carried along their velocity, every go_dt_s up to horizon_s: (the least
        gap less go_uncertainty_mps x tau (tau at most horizon_s), the least gap), m."""
        c = self.config
        p0, u = motion.p0, motion.u
        tau = np.arange(0.0, horizon_s + 1e-9, c.go_dt_s)
        centres = p0 + np.outer([travel(float(x)) for x in tau], u)  # (T, 2)
        rel = pts[None, :, :] + tau[:, None, None] * velocity - centres[:, None, :]  # (T, M, 2)
        along = np.abs(rel @ u) - c.robot_half_length_m
        across = np.abs(rel @ np.array([-u[1], u[0]])) - c.robot_half_width_m
        gap = np.hypot(np.maximum(along, 0.0), np.maximum(across, 0.0)).min(axis=1)  # (T,)
        return float((gap - c.go_uncertainty_mps * np.minimum(tau, c.horizon_s)).min()), float(gap.min())

    def _steps_past_robot(self, t: Track, robot_xy: np.ndarray) -> int:
        """Steps until a person coming down a line that passes over the robot is past it (0: not
        such a person), at most max_horizon_s."""
        c = self.config
        speed = float(np.hypot(*t.velocity))
        if speed <= 1e-6:
            return 0
        d = t.velocity / speed
        rel = robot_xy - np.array(t.last[1:])
        along = float(rel @ d)
        if along <= 0.0 or abs(float(rel[0] * d[1] - rel[1] * d[0])) >= c.in_the_way_m:
            return 0
        return int(min(c.max_horizon_s, along / speed + c.step_s) / c.step_s + 1e-9) + 1
