"""`backoff`: the stall recovery. Reverse along the recorded path, then let the planner replan.

The seed of the paper's correcting mode (section IV-C-3: "the robot reverses along its recorded
states for F steps with v in [-v_rev, 0] and the planner replans"). The MPC tracks the recorded
poses backwards with its speed bounds narrowed to [-v_rev, 0]; the safety supervisor checks the
reversing command like any other, so the robot never backs into what it cannot see being clear.
When the trail is shorter than the distance asked (a stall right after the start), the robot
backs off straight behind itself.
"""
from __future__ import annotations

import math

import numpy as np

from runtime.modes.base import ModeDecision, Situation
from runtime.planning.mpc import MpcPlanner


class PoseTrail:
    """The robot's recorded path: poses at least `spacing_m` apart, newest last (bounded)."""

    def __init__(self, spacing_m: float = 0.02, capacity: int = 500) -> None:
        self.spacing_m = spacing_m
        self._xy = np.zeros((capacity, 2))
        self._n = 0

    def record(self, pose: np.ndarray) -> None:
        n = self._n
        if n and math.hypot(pose[0] - self._xy[n - 1, 0], pose[1] - self._xy[n - 1, 1]) < self.spacing_m:
            return
        if n == self._xy.shape[0]:
            self._xy[:-1] = self._xy[1:]  # drop the oldest (rare: once per spacing travelled)
            n -= 1
        self._xy[n] = pose[:2]
        self._n = n + 1

    def clear(self) -> None:
        self._n = 0

    def back_from(self, xy: np.ndarray, distance_m: float) -> np.ndarray:
        """Recorded points going back from `xy` until `distance_m` of path (newest first); the
        trail keeps only what lies before the last one returned (the next backoff goes further)."""
        pts = [np.asarray(xy[:2], dtype=np.float64)]
        travelled = 0.0
        k = self._n - 1
        while k >= 0 and travelled < distance_m:
            step = math.hypot(self._xy[k, 0] - pts[-1][0], self._xy[k, 1] - pts[-1][1])
            if step > 1e-6:
                pts.append(self._xy[k].copy())
                travelled += step
            k -= 1
        self._n = max(k + 1, 0)
        return np.array(pts)

    def __len__(self) -> int:
        return self._n


class BackoffMode:
    name = "backoff"

    def __init__(self, mpc: MpcPlanner, distance_m: float, speed_mps: float, timeout_s: float,
                 arrive_tolerance_m: float = 0.05) -> None:
        self.mpc = mpc
        self.distance_m = distance_m
        self.speed_mps = speed_mps
        self.timeout_s = timeout_s
        self.arrive_tolerance_m = arrive_tolerance_m
        H, dt = mpc.config.horizon_steps, mpc.config.step_s
        self._H, self._dt = H, dt
        self._path: np.ndarray | None = None
        self._cum: np.ndarray | None = None
        self._started_s = 0.0
        self._s = np.zeros(H + 1)
        self._speed = np.zeros(H + 1)
        self._ref = np.zeros((H + 1, 3))

    def reset(self) -> None:
        self._path = None
        self.mpc.reset()

    def start(self, s: Situation, trail: PoseTrail) -> str:
        """Plan the way back; returns a description for the event log."""
        self.mpc.reset()
        path = trail.back_from(s.pose, self.distance_m)
        how = "along the recorded path"
        if path.shape[0] < 2 or _length(path) < 0.5 * self.distance_m:
            c, sn = math.cos(s.pose[2]), math.sin(s.pose[2])
            steps = np.linspace(0.0, self.distance_m, 8)[:, None]
            path = s.pose[:2] - steps * np.array([c, sn])
            how = "straight back (short recorded path)"
        return self.start_path(s, path, how)

    def start_path(self, s: Situation, path: np.ndarray, how: str = "") -> str:
        """Reverse along `path` ((M, 2) odom xy, from the robot's position on; correcting mode's
        line-up gives a straight one); returns a description for the event log."""
        self.mpc.reset()
        self._path = np.asarray(path, dtype=np.float64)
        seg = np.hypot(*np.diff(self._path, axis=0).T)
        self._cum = np.concatenate([[0.0], np.cumsum(seg)])
        self._started_s = s.now_s
        return f"reversing {self._cum[-1]:.2f} m {how} at up to {self.speed_mps:g} m/s"

    def _reference(self, xy: np.ndarray) -> np.ndarray:
        """(H+1, 3) waypoints along the way back, speed -v_rev, slowing to stop at its end."""
        path, cum = self._path, self._cum
        d = np.hypot(path[:, 0] - xy[0], path[:, 1] - xy[1])
        total = float(cum[-1])
        s = self._s
        speed = self._speed
        s[0] = float(cum[int(np.argmin(d))])
        for h in range(self._H + 1):  # H+1 scalar steps (arc length and speed), not points
            speed[h] = min(self.speed_mps, math.sqrt(2.0 * self.mpc.limits.accel_mps2 * max(total - s[h], 0.0)))
            if h < self._H:
                s[h + 1] = min(total, s[h] + speed[h] * self._dt)
        ref = self._ref
        ref[:, 0] = np.interp(s, cum, path[:, 0])
        ref[:, 1] = np.interp(s, cum, path[:, 1])
        ref[:, 2] = -speed
        return ref

    def plan(self, s: Situation) -> ModeDecision:
        if self._path is None:
            return ModeDecision(done=True, note="no backoff planned")
        end = self._path[-1]
        left_m = math.hypot(end[0] - s.pose[0], end[1] - s.pose[1])
        if left_m <= self.arrive_tolerance_m:
            return ModeDecision(done=True, note="backed off")
        if s.now_s - self._started_s > self.timeout_s:
            return ModeDecision(done=True, note=f"backoff timed out {left_m:.2f} m short")
        plan = self.mpc.plan(s.pose, s.command, self._reference(s.pose), s.points_fix,
                             speed_bounds_mps=(-self.speed_mps, 0.0))
        return ModeDecision(float(plan.commands[0, 0]), float(plan.commands[0, 1]), degraded=plan.fallback,
                            note="backing off")


def _length(path: np.ndarray) -> float:
    return float(np.hypot(*np.diff(path, axis=0).T).sum()) if path.shape[0] > 1 else 0.0
