"""The small state machine that chooses the navigation mode each tick.

normal mode (pure-pursuit, all-fixed, dct) --stall--> backoff --done--> normal mode (replans)

with correcting mode (runtime.modes.correcting, DCT IV-C-3; config `correcting.enabled`) in
place of the backoff:

normal mode --stuck (v_cmd >= v_min forward, moved < d_stuck for tau_stuck) or stall--> correcting
            (relabel the object pushed fixed, reverse along the recorded states) --done--> normal
            mode (replans on the new P_fix)

A stall: no progress along the path to the goal (its remaining length did not shrink by
`min_progress_m`) for `window_s`, while the reference path is valid (not blocked, not at the
goal). A replanned path that is much longer than the best so far (new obstacles seen) restarts
the clock: that is new information, not a stall. After `max_backoffs` recoveries for one goal
the selector stops trying and the stall stays reported (the episode's failure reason).

A new goal (`new_goal`): the normal mode again with a fresh plan (a recovery in progress is
abandoned: it was getting out of the way of the old route), and the per-goal counts (backoffs,
corrections) start from zero for it. Objects correcting mode relabelled stay relabelled.
"""
from __future__ import annotations

import math
from dataclasses import replace

import numpy as np

from pydantic import BaseModel, ConfigDict, Field

from runtime.common.events import EventLog
from runtime.modes.backoff import BackoffMode, PoseTrail
from runtime.modes.base import ModeDecision, NavigationMode, Situation
from runtime.modes.correcting import CorrectingMode, StuckDetector

#: A correction that starts within this of where the previous one started (no way found past
#: the place since) traces back further (CorrectingMode.start).
REPEAT_RADIUS_M = 0.3


class RecoveryConfig(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)

    enabled: bool = True
    stall_window_s: float = Field(default=3.0, gt=0.0, le=120.0)
    min_progress_m: float = Field(default=0.10, gt=0.0, le=10.0)
    path_change_reset_m: float = Field(default=0.30, gt=0.0, le=100.0)
    backoff_distance_m: float = Field(default=0.35, gt=0.0, le=5.0)
    backoff_speed_mps: float = Field(default=0.2, gt=0.0, le=2.0)
    backoff_timeout_s: float = Field(default=4.0, gt=0.0, le=60.0)
    max_backoffs: int = Field(default=3, ge=0, le=100)


class StallDetector:
    """Progress along the path (module docstring); all on the controller's clock."""

    def __init__(self, config: RecoveryConfig) -> None:
        self.config = config
        self._best_m = math.inf
        self._since_s: float | None = None
        self.stalled = False
        self.stalls = 0

    def restart(self, now_s: float) -> None:
        self._best_m = math.inf
        self._since_s = now_s
        self.stalled = False

    def no_progress_s(self, now_s: float) -> float:
        return 0.0 if self._since_s is None else now_s - self._since_s

    def update(self, now_s: float, decision: ModeDecision) -> bool:
        """True on the tick a stall begins (once per stall; `stalled` stays set until progress)."""
        c = self.config
        if decision.at_goal or decision.blocked or not math.isfinite(decision.remaining_m):
            self.restart(now_s)
            return False
        r = decision.remaining_m
        if self._since_s is None or r < self._best_m - c.min_progress_m or r > self._best_m + c.path_change_reset_m:
            self._best_m = r
            self._since_s = now_s
            self.stalled = False
            return False
        if self.stalled or now_s - self._since_s < c.stall_window_s:
            return False
        self.stalled = True
        self.stalls += 1
        return True


class ModeSelector:
    def __init__(self, normal: NavigationMode, recovery: BackoffMode | None, config: RecoveryConfig,
                 events: EventLog, correcting: CorrectingMode | None = None, label: str | None = None) -> None:
        """correcting: correcting mode (None: the stall backoff alone). label: the name reported
        while the normal mode drives (the configured preset; None: the mode's own name)."""
        self.normal = normal
        self.label = label or normal.name
        self.recovery = recovery if config.enabled else None
        self.correcting = correcting
        self.config = config
        self.events = events
        self.stall = StallDetector(config)
        self.stuck = StuckDetector(correcting.config) if correcting is not None else None
        self.trail = PoseTrail(correcting.config.trail_spacing_m) if correcting is not None else PoseTrail()
        self.active: NavigationMode = normal
        self.backoffs = 0
        #: backoffs and corrections before the current goal (the limits are per goal)
        self._backoffs_before_goal = 0
        self._corrections_before_goal = 0
        self.last_decision = ModeDecision()
        self._last_correction_xy: np.ndarray | None = None
        #: Wheel slip the lidar found (correcting mode), summed: the odom frame moved under the
        #: world by it, so the goal in the odom frame moves with it. Until the next goal: a goal
        #: given later is taken as given in the odom frame as it is then (an operator's click on
        #: the map the robot shows, a localizer's goal), slip and all.
        self.goal_shift_xy = np.zeros(2)

    @property
    def mode_name(self) -> str:
        return self.label if self.active is self.normal else self.active.name

    def counters(self) -> dict:
        out = {**self.normal.counters(), "stalls": self.stall.stalls, "stalled_now": self.stall.stalled,
               "backoffs": self.backoffs}
        if self.correcting is not None:
            out.update(correcting_events=len(self.correcting.corrections),
                       correcting=self.correcting_report())
        return out

    def correcting_report(self, t0_s: float = 0.0) -> list[dict]:
        """Each correction: start (s from t0_s), duration, object relabelled (None), reason."""
        return [c.to_dict(t0_s) for c in self.correcting.corrections] if self.correcting is not None else []

    def reset(self, now_s: float) -> None:
        """After a stop or a restart: the normal mode, a fresh plan, the stall clock from now."""
        if self.active is not self.normal and self.recovery is not None:
            self.recovery.reset()
        if self.active is self.correcting:
            self.correcting.reset()
        self.active = self.normal
        self.normal.reset()
        self.stall.restart(now_s)
        if self.stuck is not None:
            self.stuck.forget()

    def new_goal(self, now_s: float) -> None:
        """The goal changed (module docstring): a fresh plan, per-goal counts from zero."""
        if self.active is self.correcting and self.correcting.corrections:
            last = self.correcting.corrections[-1]
            if last.end_s is None:
                last.end_s, last.outcome = now_s, "abandoned: a new goal"
        self.reset(now_s)
        self.goal_shift_xy = np.zeros(2)
        self._backoffs_before_goal = self.backoffs
        if self.correcting is not None:
            self._corrections_before_goal = len(self.correcting.corrections)
        self._last_correction_xy = None

    def slack_work(self) -> bool:
        """The normal mode's deferred work (its reference searches); none during a recovery (the
        normal mode is reset when it ends, which would throw the result away)."""
        return self.active is self.normal and self.normal.slack_work()

    def plan(self, s: Situation) -> ModeDecision:
        if self.goal_shift_xy.any():
            s = replace(s, goal_xy=s.goal_xy + self.goal_shift_xy)
        if self.active is self.normal:
            self.trail.record(s.pose)
            d = self.normal.plan(s)
            if s.unclassified:
                # Before the first VLM answer: closing in on an unknown obstacle and stopping short
                # of it is waiting for the answer, not a stall or a stuck push.
                self.stall.restart(s.now_s)
                if self.stuck is not None:
                    self.stuck.forget()
            else:
                if self.stuck is not None and (d.at_goal or d.blocked):
                    # waiting for the way to clear (or at the goal) is not a stuck push: the window
                    # starts afresh (measured: a robot that waited 5 s for a person standing in a
                    # corridor was found "stuck" the tick the way cleared, and reversed)
                    self.stuck.restart()
                stuck = (self.stuck.update(s, d.v_mps) if self.stuck is not None and not (d.at_goal or d.blocked)
                         else None)
                if stuck is not None:
                    d = self._on_stuck(s, d, stuck)
                elif self.stall.update(s.now_s, d):
                    d = self._on_stall(s, d)
        else:
            d = self.active.plan(s)
            if d.done:
                if self.active is self.correcting:
                    c = self.correcting.corrections[-1]
                    self.events.add(s.now_s, "correcting_end",
                                    f"{d.note} after {s.now_s - c.start_s:.2f} s; replanning")
                else:
                    self.events.add(s.now_s, "backoff_end", f"{d.note}; replanning")
                self.reset(s.now_s)
                d = self.normal.plan(s)
        self.last_decision = d
        return d

    def _on_stall(self, s: Situation, d: ModeDecision) -> ModeDecision:
        self.events.add(
            s.now_s, "stall",
            f"no progress for {self.config.stall_window_s:g} s with a valid reference path "
            f"({d.remaining_m:.2f} m to go)",
        )
        if self.correcting is not None:
            return self._correct(s, d, f"stall: no progress for {self.config.stall_window_s:g} s "
                                       f"({d.remaining_m:.2f} m to go)")
        if self.recovery is None or self.backoffs - self._backoffs_before_goal >= self.config.max_backoffs:
            return d
        self.backoffs += 1
        how = self.recovery.start(s, self.trail)
        self.events.add(s.now_s, "backoff", f"attempt {self.backoffs - self._backoffs_before_goal}/"
                                            f"{self.config.max_backoffs}: {how}")
        self.active = self.recovery
        return self.recovery.plan(s)

    def _on_stuck(self, s: Situation, d: ModeDecision, reason: str) -> ModeDecision:
        self.events.add(s.now_s, "stuck", reason)
        slip = self.stuck.last_slip_xy
        if slip.any():
            self.goal_shift_xy = self.goal_shift_xy + slip
            self.stuck.last_slip_xy = np.zeros(2)
            self.events.add(s.now_s, "odometry_slip",
                            f"the wheels slipped {np.hypot(*slip):.2f} m the lidar did not see: goal moved with the odom frame")
        return self._correct(s, d, f"stuck: {reason}")

    def _correct(self, s: Situation, d: ModeDecision, reason: str) -> ModeDecision:
        """Correcting mode (DCT IV-C-3): relabel, reverse, then the normal mode replans."""
        corr = self.correcting
        done = len(corr.corrections) - self._corrections_before_goal
        if done >= corr.config.max_corrections:
            return d
        last = self._last_correction_xy
        repeat = last is not None and math.hypot(s.pose[0] - last[0], s.pose[1] - last[1]) <= REPEAT_RADIUS_M
        self._last_correction_xy = s.pose[:2].copy()
        ref = getattr(self.normal, "last_reference", None)  # the MPC modes' reference path (None: none)
        c = corr.start(s, self.trail, reason, repeat, ref.path_world if ref is not None else None)
        what = f"object {c.object_id} relabelled fixed" if c.object_id is not None else "no movable object in front"
        self.events.add(s.now_s, "correcting",
                        f"attempt {done + 1}/{corr.config.max_corrections} ({reason}): {what}; {c.outcome}")
        self.active = corr
        return corr.plan(s)
