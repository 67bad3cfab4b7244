"""The small state machine that chooses the navigation mode each tick.

normal mode (pure-pursuit or all-fixed) --stall--> backoff --done--> normal mode (replans)

A stall: no progress along the path to the goal (its remaining length did not shrink by
`min_progress_m`) for `window_s`, while the reference path is valid (not blocked, not at the
goal). A replanned path that is much longer than the best so far (new obstacles seen) restarts
the clock: that is new information, not a stall. After `max_backoffs` recoveries for one goal
the selector stops trying and the stall stays reported (the episode's failure reason).
"""
from __future__ import annotations

import math

from pydantic import BaseModel, ConfigDict, Field

from runtime.events import EventLog
from runtime.modes.backoff import BackoffMode, PoseTrail
from runtime.modes.base import ModeDecision, NavigationMode, Situation


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

    def stalled_for_s(self, now_s: float) -> float:
        """Seconds without progress beyond the window (0 when not stalled)."""
        if self._since_s is None:
            return 0.0
        return max(0.0, now_s - self._since_s - self.config.stall_window_s)

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
                 events: EventLog) -> None:
        self.normal = normal
        self.recovery = recovery if config.enabled else None
        self.config = config
        self.events = events
        self.stall = StallDetector(config)
        self.trail = PoseTrail()
        self.active: NavigationMode = normal
        self.backoffs = 0
        self.last_decision = ModeDecision()

    @property
    def mode_name(self) -> str:
        return self.active.name

    def counters(self) -> dict:
        return {**self.normal.counters(), "stalls": self.stall.stalls, "stalled_now": self.stall.stalled,
                "backoffs": self.backoffs}

    def reset(self, now_s: float) -> None:
        """After a stop or a restart: the normal mode, a fresh plan, the stall clock from now."""
        if self.active is not self.normal and self.recovery is not None:
            self.recovery.reset()
        self.active = self.normal
        self.normal.reset()
        self.stall.restart(now_s)

    def slack_work(self) -> bool:
        """The normal mode's deferred work (its reference searches); none during a recovery (the
        normal mode is reset when it ends, which would throw the result away)."""
        return self.active is self.normal and self.normal.slack_work()

    def plan(self, s: Situation) -> ModeDecision:
        if self.active is self.normal:
            self.trail.record(s.pose)
            d = self.normal.plan(s)
            if self.stall.update(s.now_s, d):
                d = self._on_stall(s, d)
        else:
            d = self.recovery.plan(s)
            if d.done:
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
        if self.recovery is None or self.backoffs >= self.config.max_backoffs:
            return d
        self.backoffs += 1
        how = self.recovery.start(s, self.trail)
        self.events.add(s.now_s, "backoff", f"attempt {self.backoffs}/{self.config.max_backoffs}: {how}")
        self.active = self.recovery
        return self.recovery.plan(s)
