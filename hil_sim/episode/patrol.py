"""Patrols: a scenario's goals (`goals:`) visited in order, round and round (`patrol:`).

`PatrolSequencer` is the operator of a patrol. It knows the ground truth (the world) and watches
what the controller says of itself: its current goal and whether it has finished (at the goal
with a zero command). When the controller has finished with the goal the sequencer sent, the
visit ends (reached when the robot really is within the goal's tolerance, else missed: the
controller's odometry put the goal elsewhere), and the next goal is sent; a goal not reached
within `patrol.goal_timeout_s` is missed and the next one sent. The patrol ends after `loops`
times round the goals, or `duration_s` after its start (the goal in progress then counts as
neither), or when the controller stops (a latched stop).

It decides on the time and the states it is given only (no wall clock): in lockstep
(hil_sim.episode.lockstep) those are simulated time and the controller object itself, and the next goal
goes to `NavigationController.request_goal` between two ticks; in real time (`dct hil serve`)
the controller's state comes from its DiagnosticArray and the next goal is published as a
geometry_msgs/PoseStamped on the goal topic (/goal_pose), as an operator would send it, and sent
again every RESEND_S until the controller reports it. Either way the controller takes the goal
through the same `request_goal`.

Goals are sent in the odometry frame, which starts at the robot's start pose
(`runner.goal_in_odom_frame`): the odometry's drift goes into where the robot drives, as it would
with an operator who has no map. With `patrol.localized` the operator places each goal as a
localizer would (a map frame corrected onto the odometry's): from the ground truth, the world
goal is put into the controller's odometry frame as it is at the moment the goal is sent (the
robot stands still then: it has just finished the previous goal), so a long patrol keeps testing
navigation and timing rather than the odometry's drift. Either way each visit reports the drift
(`odometry_drift_m`: where the controller's pose puts the robot, through the start frame, against
where it is).
"""
from __future__ import annotations

import math
import random
from dataclasses import asdict, dataclass

from hil_sim.world.scenario import MAX_EPISODE_S, Patrol, Scenario
from runtime.common.geometry import Pose2D

#: The controller's goal equals the one sent when within this (m): it has taken it.
SAME_GOAL_M = 1e-3
#: Real time: send the current goal again when the controller has not reported it for this long
#: (a lost or late sample; the controller ignores a repeat of its current goal).
RESEND_S = 1.0


class PatrolError(ValueError):
    """A patrol option that does not fit the scenario (one line naming the option)."""


def with_duration(scenario: Scenario, duration_s: float | None) -> Scenario:
    """The scenario patrolled for `duration_s` seconds (`--duration`) instead of its own `patrol`
    (the time limit becomes the duration). None: unchanged. PatrolError for a scenario that has a
    single goal (only a patrol can run for a set time) or a duration out of range."""
    if duration_s is None:
        return scenario
    if not scenario.is_patrol:
        raise PatrolError(f"--duration: scenario {scenario.name} has a single goal; only a patrol (goals: and "
                          "patrol: in the scenario file) runs for a set time")
    if not (math.isfinite(duration_s) and 0.0 < duration_s <= MAX_EPISODE_S):
        raise PatrolError(f"--duration: {duration_s!r} s is not in (0, {MAX_EPISODE_S:g}]")
    timeout = scenario.patrol.goal_timeout_s if scenario.patrol is not None else Patrol.model_fields[
        "goal_timeout_s"].default
    localized = scenario.patrol.localized if scenario.patrol is not None else False
    order = scenario.patrol.order if scenario.patrol is not None else "in_order"
    patrol = Patrol(duration_s=float(duration_s), goal_timeout_s=timeout, localized=localized, order=order)
    # validated again (model_copy would skip the validators): a looped patrol's last -> first
    # pair is checked like the others
    try:
        return type(scenario).model_validate({**scenario.model_dump(), "patrol": patrol.model_dump(),
                                              "time_limit_s": float(duration_s)})
    except ValueError as exc:
        raise PatrolError(f"--duration: {exc}") from exc


def goal_in_odom(scenario: Scenario, index: int, world_pose=None, odom_pose: Pose2D | None = None) -> Pose2D:
    """Goal `index` of the sequence in the odometry frame: the start pose's, or with the robot's
    true pose `world_pose` (x, y, yaw) and the controller's `odom_pose` at the same moment, the
    odometry frame as it lies in the world now (a localizer's map -> odom)."""
    g = scenario.goal_sequence[index]
    goal = Pose2D(g.x_m, g.y_m, g.yaw_rad)
    if world_pose is not None and odom_pose is not None:
        world_odom = Pose2D(*map(float, world_pose)).compose(odom_pose.inverse())
        return world_odom.inverse().compose(goal)
    s = scenario.robot_start
    return Pose2D(s.x_m, s.y_m, s.yaw_rad).inverse().compose(goal)


@dataclass
class GoalVisit:
    """One goal sent: which, when, and how it ended."""

    visit: int              # 0, 1, ... in the order sent
    goal_index: int         # into the scenario's goals
    loop: int               # 0-based time round the goals
    goal_world: tuple[float, float]
    goal_odom: tuple[float, float, float]  # as sent (odometry frame)
    sent_at_s: float        # from the patrol's start
    ended_at_s: float | None = None
    #: reached | missed_odometry (the controller finished away from it) | missed_timeout |
    #: in_progress (the patrol ended first)
    outcome: str = "in_progress"
    world_error_m: float | None = None  # robot to goal (ground truth) when it ended
    #: where the controller's pose (through the start frame) puts the robot, against where it is,
    #: when it ended (None: the controller's pose unknown)
    odometry_drift_m: float | None = None

    def to_dict(self) -> dict:
        d = asdict(self)
        d["goal_world"] = list(self.goal_world)
        d["goal_odom"] = list(self.goal_odom)
        d["time_s"] = None if self.ended_at_s is None else self.ended_at_s - self.sent_at_s
        return d


class PatrolSequencer:
    """The patrol's operator (module docstring). `t0_s` is when the first goal was given (the
    episode's start); every time passed in is on the same clock."""

    def __init__(self, scenario: Scenario, t0_s: float, seed: int = 0) -> None:
        if not scenario.is_patrol:
            raise PatrolError(f"scenario {scenario.name} is not a patrol (no goals:)")
        self.scenario = scenario
        self.goals = scenario.goal_sequence
        patrol = scenario.patrol or Patrol(loops=1)
        self.loops = patrol.loops
        self.duration_s = patrol.duration_s
        self.goal_timeout_s = patrol.goal_timeout_s
        self.localized = patrol.localized
        #: random order: the next goal's draw (from the episode's seed, so the same seed drives the
        #: same sequence of goals whatever the timing)
        self._rng = random.Random(int(seed)) if patrol.order == "random" else None
        self.t0_s = float(t0_s)
        self.visits: list[GoalVisit] = []
        self._drift_m: float | None = None
        self.done = False
        self.end_reason: str | None = None
        self._last_sent_s = self.t0_s
        self._start_visit(0, self.t0_s, None, None)  # the controller starts with goal 0 (start frame)

    # -- state
    @property
    def current(self) -> GoalVisit:
        return self.visits[-1]

    def current_goal_odom(self) -> Pose2D:
        return Pose2D(*self.current.goal_odom)

    def _next_index(self, k: int) -> int:
        """The goal of visit k: in order, or (random order) any goal but the current one."""
        n = len(self.goals)
        if self._rng is None or k == 0:
            return k % n
        current = self.visits[-1].goal_index
        return (current + 1 + self._rng.randrange(n - 1)) % n

    def _start_visit(self, k: int, t_s: float, world_pose, odom_pose: Pose2D | None) -> None:
        n = len(self.goals)
        i = self._next_index(k)
        g = self.goals[i]
        odom = (goal_in_odom(self.scenario, i, world_pose, odom_pose) if self.localized
                else goal_in_odom(self.scenario, i))
        self.visits.append(GoalVisit(k, i, k // n, (g.x_m, g.y_m), (odom.x_m, odom.y_m, odom.yaw_rad),
                                     t_s - self.t0_s))
        self._last_sent_s = t_s

    def _end(self, reason: str) -> None:
        self.done = True
        self.end_reason = reason

    def controller_has_goal(self, controller_goal_xy: tuple[float, float] | None) -> bool:
        """Whether the controller's goal (odom frame) is the one sent last."""
        if controller_goal_xy is None:
            return False
        g = self.current_goal_odom()
        return math.hypot(controller_goal_xy[0] - g.x_m, controller_goal_xy[1] - g.y_m) <= SAME_GOAL_M

    # -- the operator's step
    def update(self, t_s: float, robot_world_pose, controller_goal_xy: tuple[float, float] | None,
               controller_finished: bool, controller_stopped: bool,
               controller_pose: Pose2D | None = None) -> Pose2D | None:
        """One look at the scene at time t_s: the robot's true pose (x, y, yaw), the controller's goal
        (odom frame; None when unknown), whether it has finished or stopped, and its pose (odom
        frame; None when unknown). Returns the next goal to send (odom frame), or None. Sets `done`
        when the patrol is over."""
        if self.done:
            return None
        robot_world_xy = (float(robot_world_pose[0]), float(robot_world_pose[1]))
        self._drift_m = self._drift(robot_world_xy, controller_pose)
        visit = self.current
        if self.duration_s is not None and t_s - self.t0_s >= self.duration_s:
            self._end("duration")
            return None
        if controller_stopped:
            self._finish_visit(visit, t_s, robot_world_xy, "missed_stopped")
            self._end("controller_stopped")
            return None
        if controller_finished and self.controller_has_goal(controller_goal_xy):
            g = self.goals[visit.goal_index]
            err = math.hypot(robot_world_xy[0] - g.x_m, robot_world_xy[1] - g.y_m)
            self._finish_visit(visit, t_s, robot_world_xy, "reached" if err <= g.tolerance_m else "missed_odometry")
        elif t_s - self.t0_s - visit.sent_at_s >= self.goal_timeout_s:
            self._finish_visit(visit, t_s, robot_world_xy, "missed_timeout")
        else:
            return None
        k = visit.visit + 1
        if self.loops is not None and k >= self.loops * len(self.goals):
            self._end("loops_done")
            return None
        self._start_visit(k, t_s, robot_world_pose, controller_pose)
        return self.current_goal_odom()

    def resend_due(self, t_s: float, controller_goal_xy: tuple[float, float] | None) -> bool:
        """Real time: the goal sent last is not the controller's yet, RESEND_S after sending it."""
        if self.done or self.controller_has_goal(controller_goal_xy) or t_s - self._last_sent_s < RESEND_S:
            return False
        self._last_sent_s = t_s
        return True

    def _finish_visit(self, visit: GoalVisit, t_s: float, robot_world_xy, outcome: str) -> None:
        g = self.goals[visit.goal_index]
        visit.ended_at_s = t_s - self.t0_s
        visit.outcome = outcome
        visit.world_error_m = math.hypot(robot_world_xy[0] - g.x_m, robot_world_xy[1] - g.y_m)
        visit.odometry_drift_m = self._drift_m

    def _drift(self, robot_world_xy, controller_pose: Pose2D | None) -> float | None:
        if controller_pose is None:
            return None
        s = self.scenario.robot_start
        seen = Pose2D(s.x_m, s.y_m, s.yaw_rad).compose(controller_pose)
        return math.hypot(seen.x_m - robot_world_xy[0], seen.y_m - robot_world_xy[1])

    def distance_to_current_m(self, robot_world_xy: tuple[float, float]) -> float:
        x, y = self.current.goal_world
        return math.hypot(robot_world_xy[0] - x, robot_world_xy[1] - y)

    # -- the verdict
    def counts(self) -> dict:
        outcomes = [v.outcome for v in self.visits]
        return {
            "goals_sent": len(self.visits),
            "goals_reached": outcomes.count("reached"),
            "goals_missed": sum(o.startswith("missed") for o in outcomes),
            "goals_in_progress": outcomes.count("in_progress"),
            # times round the goals with every visit ended (reached or missed)
            "loops_completed": sum(o != "in_progress" for o in outcomes) // len(self.goals),
        }

    @property
    def succeeded(self) -> bool:
        """Every goal that ended was reached (at least one), the patrol ran to its end (loops done or
        its duration), not cut short by a stop or the time limit."""
        c = self.counts()
        return (self.done and self.end_reason in ("loops_done", "duration") and c["goals_missed"] == 0
                and c["goals_reached"] >= 1)

    def report(self, t_end_s: float) -> dict:
        """JSON-ready: counts, the end, and every visit."""
        times = [v.ended_at_s - v.sent_at_s for v in self.visits if v.outcome == "reached"]
        drifts = [v.odometry_drift_m for v in self.visits if v.odometry_drift_m is not None]
        return {
            **self.counts(),
            "goals_in_sequence": len(self.goals),
            "localized": self.localized,
            "odometry_drift_m_max": max(drifts) if drifts else None,
            "loops": self.loops,
            "duration_s": self.duration_s,
            "goal_timeout_s": self.goal_timeout_s,
            "end_reason": self.end_reason or "time_limit",
            "patrol_time_s": t_end_s - self.t0_s,
            "time_per_goal_s": {"mean": sum(times) / len(times) if times else None,
                                "max": max(times) if times else None},
            "visits": [v.to_dict() for v in self.visits],
        }


def patrol_failure_reason(metrics: dict) -> str | None:
    """Why a patrol failed after the reasons every episode shares (contacts, stops, holds: the
    caller's), in words; None when the patrol itself succeeded."""
    p = metrics["patrol"]
    missed = [v for v in p["visits"] if v["outcome"].startswith("missed")]
    if missed:
        v = missed[0]
        how = {"missed_timeout": f"not reached within {p['goal_timeout_s']:g} s",
               "missed_odometry": f"the controller stopped {v['world_error_m']:.2f} m from it (odometry drift)",
               "missed_stopped": "the controller stopped (latched)"}.get(v["outcome"], v["outcome"])
        return (f"patrol: {p['goals_missed']} of {p['goals_sent']} goals missed; first: visit {v['visit']} "
                f"(goals[{v['goal_index']}] at ({v['goal_world'][0]:g}, {v['goal_world'][1]:g}), loop {v['loop']}) "
                f"{how}")
    if p["end_reason"] not in ("loops_done", "duration"):
        return f"patrol: ended by {p['end_reason']} after {p['goals_reached']} goals reached"
    if p["goals_reached"] == 0:
        return "patrol: no goal reached"
    return None


__all__ = ["PatrolSequencer", "GoalVisit", "PatrolError", "with_duration", "goal_in_odom", "patrol_failure_reason",
           "RESEND_S", "SAME_GOAL_M"]
