"""`correcting`: DCT's correcting mode (paper IV-C-3; docs/algorithms/contact.md) as a recovery strategy.

When a push fails the robot is stuck: it commands forward motion (v >= v_min, the planner's
command) but moves less than d_stuck in tau_stuck (or the selector's progress stall fires).
Then, in this order (the selector, runtime.modes.selector, switches here):
1. eq. 14: the movable object in front of the robot (its P_mov points within the footprint +
   `contact_margin_m`, on the side the robot was driving to) is relabelled fixed for the rest of
   the episode (the partition stage: runtime.perception.partition, VppStage.demote); none when there
   is none (a wedge between fixed obstacles: the MPC's local minimum);
2. the robot reverses along its recorded states (runtime.modes.backoff.PoseTrail) for F of them
   (the trail's spacing apart) with v in [-v_rev, 0] (BackoffMode: the MPC tracks the trail
   backwards, the supervisor checks every command);
   After a wedge (nothing relabelled: a tight gap approached steeply, the MPC's local minimum,
   where the heading-blind reference path would lead straight back in) the reverse goes instead
   straight to a line-up point on the passage's axis (the reference path's direction 0.25-0.65 m
   past the stall), and the robot turns along the axis there;
3. the normal mode replans on the new P_fix (the selector resets it when this mode is done).
A second correction at the same place traces back further: F times the attempt number.

"Moved" is measured twice: the odometry's displacement over the window, and, when odometry says
the robot moved, the lidar: the P_fix points in the robot frame now against those tau_stuck ago,
under "stood still" and under "moved as the odometry says". Wheels that slip against a heavy box
carry the odometry (wheels, and an ICP fooled by the box moving with the robot in its view) away
while the scan stays as it was: the scan then fits "stood still" much better. In a featureless
corridor both fit alike and the odometry is believed (never a false stuck from the lidar). The
displacement the scan did not show is the slip: the odom frame moved under the world by it, and
the selector moves the goal (in the odom frame) with it, so that the robot does not stop short.

Everything on the controller's clock (deterministic in lockstep). Each correction is recorded
(start, duration, object relabelled or None, reason) for the event log and the episode metrics.
"""
from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, replace

import numpy as np
from pydantic import BaseModel, ConfigDict, Field
from scipy.spatial import cKDTree

from runtime.modes.backoff import BackoffMode, PoseTrail
from runtime.modes.base import ModeDecision, Situation


class CorrectingConfig(BaseModel):
    """Correcting mode's settings (controller config `correcting:`); the paper's symbols in the
    names where it has them (v_min, d_stuck, tau_stuck, F, v_rev)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    enabled: bool = True
    #: Commanded v (forward) at least this (m/s) counts as "commanding motion".
    v_min_mps: float = Field(default=0.10, gt=0.0, le=2.0)
    #: Moved less than this (m) over tau_stuck_s while commanding motion: stuck.
    d_stuck_m: float = Field(default=0.05, gt=0.0, le=2.0)
    tau_stuck_s: float = Field(default=0.8, gt=0.0, le=30.0)
    #: F: recorded states to trace back (the pose trail keeps one every trail_spacing_m).
    traceback_states: int = Field(default=20, ge=1, le=400)
    trail_spacing_m: float = Field(default=0.025, gt=0.0, le=1.0)
    #: v_rev (m/s): the reverse speed bound.
    v_rev_mps: float = Field(default=0.3, gt=0.0, le=2.0)
    #: The object pushed: its P_mov points within the footprint + this margin (m), ahead.
    contact_margin_m: float = Field(default=0.12, ge=0.0, le=1.0)
    #: A reverse that has not arrived after this long ends anyway (s).
    timeout_s: float = Field(default=5.0, gt=0.0, le=60.0)
    #: Line-up after a stall with nothing movable in front (a wedge at a tight gap approached
    #: steeply, the MPC's local minimum): the direction of the reference path ahead of the stall
    #: is the passage's axis; the robot drives to the point `line_up_distance_m` before the stall
    #: on that axis, turns along it, and only then replans. 0: off.
    line_up_distance_m: float = Field(default=0.6, ge=0.0, le=3.0)
    line_up_timeout_s: float = Field(default=4.0, gt=0.0, le=60.0)
    align_tolerance_rad: float = Field(default=0.08, gt=0.0, le=1.0)
    #: At most this many corrections per goal; then the stall stays reported.
    max_corrections: int = Field(default=5, ge=0, le=100)
    #: Lidar check: "stood still" must fit the scan this many times better than the odometry's
    #: motion (mean capped nearest-point distance), and the odometry's fit be at least this bad (m).
    scan_fit_ratio: float = Field(default=0.5, gt=0.0, le=1.0)
    scan_min_misfit_m: float = Field(default=0.03, gt=0.0, le=1.0)


#: Robot-frame P_fix points kept per scan for the lidar check (thinned by stride), their range.
_SCAN_POINTS = 600
_SCAN_RANGE_M = 5.0
_FIT_CAP_M = 0.3
#: Scans kept to find where a slip began (s): a push that slows to a stall takes a while.
SLIP_HISTORY_S = 4.0


def _robot_frame(points_odom: np.ndarray, pose: np.ndarray) -> np.ndarray:
    c, s = math.cos(pose[2]), math.sin(pose[2])
    d = points_odom - pose[:2]
    q = np.column_stack([c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1]])
    q = q[np.hypot(q[:, 0], q[:, 1]) <= _SCAN_RANGE_M]
    if len(q) > _SCAN_POINTS:
        q = q[np.linspace(0, len(q) - 1, _SCAN_POINTS).astype(np.intp)]
    return q


def slip_since(history: list, new_q: np.ndarray, new_pose: np.ndarray) -> np.ndarray:
    """The odometry's displacement (odom frame, xy) that the scan does not show. history: (t,
    pose, robot-frame points) of earlier scans, oldest first. Model: the robot truly drove along
    its recorded poses up to one of them and slipped in place since; the oldest scan is compared
    with the newest as seen from each recorded position (the yaw now: the gyro does not slip);
    the best fit says where the slip began (the recorded positions first, then every 1 cm on the
    path between the best one's neighbours)."""
    _, pose0, q0 = history[0]
    tree = cKDTree(new_q)
    c0, s0 = math.cos(pose0[2]), math.sin(pose0[2])
    w = q0 @ np.array([[c0, s0], [-s0, c0]]) + pose0[:2]  # the oldest scan in odom
    c1, s1 = math.cos(new_pose[2]), math.sin(new_pose[2])

    def misfit(xy: np.ndarray) -> float:
        d = w - xy
        q = np.column_stack([c1 * d[:, 0] + s1 * d[:, 1], -s1 * d[:, 0] + c1 * d[:, 1]])
        return float(np.minimum(tree.query(q, distance_upper_bound=_FIT_CAP_M)[0], _FIT_CAP_M).mean())

    path = np.array([h[1][:2] for h in history] + [new_pose[:2]], dtype=float)
    coarse = [misfit(xy) for xy in path]
    k = int(np.argmin(coarse))
    lo, hi = path[max(k - 1, 0)], path[min(k + 1, len(path) - 1)]
    mid = path[k]
    fine = [mid]
    for a, b in ((lo, mid), (mid, hi)):
        n = int(math.hypot(*(b - a)) / 0.01)
        fine += [a + (b - a) * f for f in np.linspace(0.0, 1.0, n + 1)[1:-1]] if n > 1 else []
    best_xy = min(fine, key=misfit)
    return np.asarray(new_pose[:2] - best_xy, dtype=float)


def slip_fraction(old_q: np.ndarray, old_pose: np.ndarray, new_q: np.ndarray, new_pose: np.ndarray,
                  steps: int = 10) -> float:
    """The share (0..1) of the odometry's motion from old_pose to new_pose that the scan does not
    show: the robot is taken to have moved alpha of it, alpha on a grid, the best-fitting alpha
    (mean capped nearest-point distance) wins; 1 - alpha is the slip."""
    tree = cKDTree(new_q)
    c0, s0 = math.cos(old_pose[2]), math.sin(old_pose[2])
    w = old_q @ np.array([[c0, s0], [-s0, c0]]) + old_pose[:2]
    best, best_a = math.inf, 1.0
    for a in np.linspace(0.0, 1.0, steps + 1):
        xy = old_pose[:2] + a * (new_pose[:2] - old_pose[:2])
        yaw = new_pose[2]
        c1, s1 = math.cos(yaw), math.sin(yaw)
        d = w - xy
        q = np.column_stack([c1 * d[:, 0] + s1 * d[:, 1], -s1 * d[:, 0] + c1 * d[:, 1]])
        m = float(np.minimum(tree.query(q, distance_upper_bound=_FIT_CAP_M)[0], _FIT_CAP_M).mean())
        if m < best - 1e-9:
            best, best_a = m, float(a)
    return 1.0 - best_a


def scan_fits(old_q: np.ndarray, old_pose: np.ndarray, new_q: np.ndarray, new_pose: np.ndarray) -> tuple[float, float]:
    """(misfit if the robot stood still, misfit if it moved as the odometry says): mean nearest-
    point distance (capped) of the old robot-frame points to the new ones under each hypothesis."""
    tree = cKDTree(new_q)
    still, _ = tree.query(old_q, distance_upper_bound=_FIT_CAP_M)
    c0, s0 = math.cos(old_pose[2]), math.sin(old_pose[2])
    w = old_q @ np.array([[c0, s0], [-s0, c0]]) + old_pose[:2]  # old points in odom
    c1, s1 = math.cos(new_pose[2]), math.sin(new_pose[2])
    d = w - new_pose[:2]
    moved_q = np.column_stack([c1 * d[:, 0] + s1 * d[:, 1], -s1 * d[:, 0] + c1 * d[:, 1]])
    moved, _ = tree.query(moved_q, distance_upper_bound=_FIT_CAP_M)
    return float(np.minimum(still, _FIT_CAP_M).mean()), float(np.minimum(moved, _FIT_CAP_M).mean())


class StuckDetector:
    """The paper's trigger: v_cmd >= v_min (forward) for tau_stuck while moving less than d_stuck
    (odometry, checked by the lidar: module docstring). All on the controller's clock."""

    def __init__(self, config: CorrectingConfig) -> None:
        self.config = config
        self._since_s: float | None = None
        self._scans: deque = deque()  # (t, pose, robot-frame P_fix) since the window began
        self._history: deque = deque()  # the same for the last SLIP_HISTORY_S, commanded or not
        self._last_points: np.ndarray | None = None
        self.lidar_checks = 0
        #: The odometry's displacement the scan did not show (odom frame, m) at the last stuck
        #: found by the lidar: the wheels slipped, and the odom frame moved by this under the
        #: world (the selector moves the goal with it).
        self.last_slip_xy = np.zeros(2)

    def restart(self) -> None:
        """A new window (the scan history for the slip stays)."""
        self._since_s = None
        self._scans.clear()

    def forget(self) -> None:
        """After a correction or a mode switch: everything, the slip history included."""
        self.restart()
        self._history.clear()

    def update(self, s: Situation, planned_v_mps: float | None = None) -> str | None:
        """The reason, on the tick the robot is found stuck (then the detector restarts); None.
        The commanded speed is the planner's (planned_v_mps: the paper's v_t, what the mode asked
        for, before the safety supervisor stopped it at a wedge), else the command applied."""
        c = self.config
        v = float(s.command[0]) if planned_v_mps is None else float(planned_v_mps)
        scan = None
        seen = s.points_fix if s.points_observed is None else s.points_observed  # not predictions
        if seen is not self._last_points and len(seen):
            self._last_points = seen
            scan = (s.now_s, s.pose.copy(), _robot_frame(seen, s.pose))
            self._history.append(scan)
            while self._history[0][0] < s.now_s - SLIP_HISTORY_S:
                self._history.popleft()
        if v < c.v_min_mps:  # the paper's v_t >= v_min: forward (a reverse is what the recovery does)
            self.restart()
            return None
        if self._since_s is None:
            self._since_s = s.now_s
        if scan is not None:
            self._scans.append(scan)
        while len(self._scans) > 1 and self._scans[1][0] <= s.now_s - c.tau_stuck_s:
            self._scans.popleft()
        if s.now_s - self._since_s < c.tau_stuck_s or not self._scans:
            return None
        t0, pose0, q0 = self._scans[0]
        moved = math.hypot(s.pose[0] - pose0[0], s.pose[1] - pose0[1])
        span = s.now_s - t0
        if moved < c.d_stuck_m:
            self.forget()
            return f"commanding {v:.2f} m/s, moved {moved * 100:.1f} cm in {span:.1f} s"
        t1, pose1, q1 = self._scans[-1]
        if scan is None or t1 <= t0 or not len(q0) or not len(q1):
            return None  # the lidar check once per scan (10 Hz), not every tick
        self.lidar_checks += 1
        still, as_odometry = scan_fits(q0, pose0, q1, pose1)
        if as_odometry >= c.scan_min_misfit_m and still <= c.scan_fit_ratio * as_odometry:
            self.last_slip_xy = slip_since(list(self._history), q1, pose1)
            self.forget()
            return (f"commanding {v:.2f} m/s, odometry moved {moved:.2f} m in {span:.1f} s but the lidar scan "
                    f"did not change (misfit {still * 100:.1f} cm standing, {as_odometry * 100:.1f} cm as "
                    f"odometry says): wheels slipping")
        return None


@dataclass
class Correction:
    """One correcting-mode episode, for the event log and the metrics."""

    start_s: float
    reason: str
    object_id: int | None
    traceback_m: float
    end_s: float | None = None
    outcome: str = ""

    def to_dict(self, t0_s: float = 0.0) -> dict:
        return {"start_s": round(self.start_s - t0_s, 6),
                "duration_s": None if self.end_s is None else round(self.end_s - self.start_s, 6),
                "object_id": self.object_id, "reason": self.reason, "traceback_m": round(self.traceback_m, 4),
                "outcome": self.outcome}


class CorrectingMode:
    """Relabel (eq. 14), reverse along the recorded states (after a wedge: straight to a line-up
    point on the passage's axis, then turn along it), then let the normal mode replan."""

    name = "correcting"

    def __init__(self, config: CorrectingConfig, backoff: BackoffMode, robot, partition=None) -> None:
        """backoff: the reverses (along the trail, or straight to a line-up point; its distance is
        set per correction); partition: the controller's partition stage
        (runtime.perception.partition), set by the mode's builder."""
        self.config = config
        self.backoff = backoff
        self.partition = partition
        self.half_length_m = robot.footprint.length_m / 2
        self.half_width_m = robot.footprint.width_m / 2
        self.max_omega_radps = float(robot.body_max_angular_speed_radps)
        self.corrections: list[Correction] = []
        self._repeat = 0
        self._phase = "reverse"  # reverse -> line_up -> align (the last two after a wedge only)
        self._line_up: tuple[np.ndarray, float] | None = None  # (waypoint xy, axis yaw)
        self._phase_s = 0.0

    def reset(self) -> None:
        self.backoff.reset()
        self._phase = "reverse"
        self._line_up = None

    def counters(self) -> dict:
        return {}

    def slack_work(self) -> bool:
        """Nothing deferred: the reverses track recorded or straight paths."""
        return False

    def start(self, s: Situation, trail: PoseTrail, reason: str, repeat: bool,
              path_ahead: np.ndarray | None = None) -> Correction:
        """Begin a correction: relabel the object in front (if any), plan the way back. repeat:
        no progress since the previous correction (trace back further). path_ahead: the normal
        mode's reference path (odom xy) at the stall, for the line-up after a wedge."""
        c = self.config
        self._repeat = self._repeat + 1 if repeat else 1
        forward = float(s.command[0]) >= 0.0
        oid = None
        # Relabel only what the robot was pushing on: with the command applied zeroed (the safety
        # supervisor stopped it: points it did not see as touchable in its footprint, e.g. a
        # curtain's unseen slats) the object in front did not resist a push, and "did not move"
        # says nothing about it (a wedge: reverse and line up instead).
        pushing = abs(float(s.command[0])) >= c.v_min_mps
        if self.partition is not None and pushing:
            oid = self.partition.relabel_fixed_in_front((float(s.pose[0]), float(s.pose[1]), float(s.pose[2])),
                                                        self.half_length_m, self.half_width_m, c.contact_margin_m,
                                                        forward)
        distance = c.traceback_states * c.trail_spacing_m * self._repeat
        self.backoff.distance_m = distance
        how = self.backoff.start(s, trail)
        self._phase = "reverse"
        self._line_up = None
        if oid is None and path_ahead is not None and c.line_up_distance_m > 0.0:
            self._line_up = _line_up_point(path_ahead, s.pose, s.points_fix, c.line_up_distance_m,
                                           math.hypot(self.half_length_m, self.half_width_m))
            if self._line_up is not None:
                xy, yaw = self._line_up
                if float((xy - s.pose[:2]) @ [math.cos(s.pose[2]), math.sin(s.pose[2])]) < 0.0:
                    # behind the robot: reverse straight to it (still facing the passage), not along the trail
                    self.backoff.start_path(s, np.linspace(s.pose[:2], xy, 8))
                    self._phase = "line_up"
                    how = f"reversing {np.hypot(*(xy - s.pose[:2])):.2f} m straight"
                how += f"; line up at ({xy[0]:.2f}, {xy[1]:.2f}) facing {math.degrees(yaw):.0f} deg"
        corr = Correction(s.now_s, reason, oid, distance, outcome=how)
        self.corrections.append(corr)
        return corr

    def plan(self, s: Situation) -> ModeDecision:
        d = self._plan_phase(s)
        if d.done and self.corrections and self.corrections[-1].end_s is None:
            self.corrections[-1].end_s = s.now_s
            self.corrections[-1].outcome = d.note
        return d

    def _plan_phase(self, s: Situation) -> ModeDecision:
        c = self.config
        if self._phase == "reverse":
            d = self.backoff.plan(s)
            if not d.done or self._line_up is None:
                return d
            xy, yaw = self._line_up
            self._phase, self._phase_s = "align", s.now_s
            away = xy - s.pose[:2]
            if float(away @ [math.cos(s.pose[2]), math.sin(s.pose[2])]) < 0.0 and np.hypot(*away) > 0.05:
                # the line-up point is behind: reverse straight to it (the robot keeps facing the passage)
                self.backoff.start_path(s, np.linspace(s.pose[:2], xy, 8), "to the line-up point")
                self._phase = "line_up"
        xy, yaw = self._line_up
        if self._phase == "line_up":
            d = self.backoff.plan(s)
            if not d.done:
                return replace(d, note="lining up")
            self._phase, self._phase_s = "align", s.now_s
        err = math.atan2(math.sin(yaw - s.pose[2]), math.cos(yaw - s.pose[2]))
        if abs(err) <= c.align_tolerance_rad or s.now_s - self._phase_s > c.line_up_timeout_s:
            return ModeDecision(done=True, note=f"backed off, lined up ({math.degrees(err):.0f} deg off the axis)")
        omega = max(-self.max_omega_radps, min(self.max_omega_radps, 2.0 * err))
        return ModeDecision(0.0, omega, note="turning along the passage")


def _line_up_point(path: np.ndarray, pose: np.ndarray, points_fix: np.ndarray, distance_m: float,
                   radius_m: float) -> tuple[np.ndarray, float] | None:
    """(waypoint, axis yaw) for the line-up: the reference path's direction from the stall over
    0.25-0.65 m on is the passage's axis; the waypoint lies distance_m back from the stall along
    it, shortened until the robot's circumscribed circle (radius_m + 5 cm) is clear of P_fix there.
    None when the path ahead is too short or no such point is clear."""
    path = np.asarray(path, dtype=float)
    if path.ndim != 2 or len(path) < 3:
        return None
    k = int(np.argmin(np.hypot(path[:, 0] - pose[0], path[:, 1] - pose[1])))
    ahead = path[k:]
    arc = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(ahead, axis=0).T))])
    if arc[-1] < 0.3:
        return None
    s0, s1 = min(0.25, 0.5 * arc[-1]), min(0.65, arc[-1])  # inside the passage: the path keeps to its middle
    a = np.array([np.interp(s0, arc, ahead[:, 0]), np.interp(s0, arc, ahead[:, 1])])
    b = np.array([np.interp(s1, arc, ahead[:, 0]), np.interp(s1, arc, ahead[:, 1])])
    axis = b - a
    if not np.hypot(*axis) > 0.1:
        return None
    yaw = math.atan2(axis[1], axis[0])
    u = axis / np.hypot(*axis)
    tree = cKDTree(points_fix) if len(points_fix) else None
    for dist in np.linspace(distance_m + s0, 0.5 * distance_m + s0, 4):
        xy = a - dist * u
        if tree is None or tree.query(xy)[0] >= radius_m + 0.05:
            return xy, yaw
    return None


__all__ = ["CorrectingConfig", "CorrectingMode", "Correction", "StuckDetector", "scan_fits", "slip_fraction",
           "slip_since"]
