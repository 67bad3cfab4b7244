"""The replay's clock: the recording drives time, the controller's own fixed-rate loop runs on it.

The loop (runtime.loop.fixed_rate) asks its clock for the time and sleeps until each tick's
scheduled time, as on the robot. `ReplayClock` answers from a plan of ticks:

- a dct recording: the live ticks, each at its live grid index, scheduled time and the
  controller's clock reading (`now`, the scheduled time plus the live lateness), with what it took
  in. A tick the live loop skipped (it ran late) is skipped here too: after a tick the clock
  reads just before the next planned one, and the loop's own catch-up rule steps over the rest.
- a bag: ticks every period from the first sample, `now` the scheduled time.

Before a tick's time is reached, `before_tick(plan)` hands over the inputs the tick must find
(sensor samples, CAN frames, a new goal) and waits for the work beside the tick due by then (ICP
results, as the lockstep simulator's barriers do). Time never moves inside a tick, so nothing the
controller decides depends on this machine's speed: the same recording gives the same outputs.

Rates: `max` runs as fast as the work allows; `recorded` also sleeps on the wall clock so that
ticks come at the recorded pace (what an engineer watching a viewer wants).
"""
from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Callable, Iterator

#: A loop time and a planned tick time are the same instant within this (both are t0 + k * period).
SAME_TIME_S = 1e-6


class ReplayDesyncError(RuntimeError):
    """The loop asked for a time the plan does not have (it ran a tick the live run did not)."""


@dataclass(frozen=True)
class TickPlan:
    tick: int  # grid index: scheduled = t0 + tick * period
    scheduled_s: float
    now_s: float  # the controller's clock during the tick
    #: The live tick's inputs (runtime.app.replay.source.TickInputs), None for a bag's tick.
    live: object = None


class ReplayClock:
    """now() and sleep_until() for the loop (module docstring); `after_tick()` from the loop's hook."""

    def __init__(self, plans: Iterator[TickPlan], before_tick: Callable[[TickPlan, TickPlan | None], None],
                 period_s: float, pace: bool = False) -> None:
        self._plans = plans
        self._before_tick = before_tick
        self.period_s = float(period_s)
        self.pace = pace
        self.current: TickPlan | None = None
        self.next: TickPlan | None = next(plans, None)
        self._after: TickPlan | None = next(plans, None) if self.next is not None else None
        first = self.next
        self.t = first.scheduled_s - first.tick * self.period_s if first is not None else 0.0
        self.ticks = 0
        self._wall0: float | None = None
        self._now0 = 0.0

    @property
    def t0_s(self) -> float:
        return self.t

    @property
    def done(self) -> bool:
        """No planned tick is left (the loop's should_stop)."""
        return self.next is None

    def now(self) -> float:
        return self.t

    def sleep_until(self, t_s: float) -> None:
        nxt = self.next
        if nxt is None or t_s < nxt.scheduled_s - SAME_TIME_S:
            self.t = max(self.t, t_s)  # between ticks (a keep-alive): time passes, nothing comes in
            return
        if t_s > nxt.scheduled_s + SAME_TIME_S:
            raise ReplayDesyncError(f"the loop asked for {t_s:.6f} s, past the next planned tick {nxt.tick} at "
                                    f"{nxt.scheduled_s:.6f} s")
        self._pace_to(nxt.now_s)
        self.t = nxt.now_s
        self._before_tick(nxt, self._after)
        self.current, self.next = nxt, self._after
        self._after = next(self._plans, None) if self._after is not None else None
        self.ticks += 1

    def after_tick(self) -> None:
        """After a tick (the loop's after_tick hook): when the live loop skipped grid points before
        the next planned tick, read just before it, so that the loop's catch-up skips them too."""
        cur, nxt = self.current, self.next
        if cur is not None and nxt is not None and nxt.tick > cur.tick + 1:
            self.t = max(self.t, nxt.scheduled_s - SAME_TIME_S)

    def _pace_to(self, now_s: float) -> None:
        if not self.pace:
            return
        if self._wall0 is None:
            self._wall0, self._now0 = time.monotonic(), now_s
            return
        wait = self._wall0 + (now_s - self._now0) - time.monotonic()
        if wait > 0:
            time.sleep(wait)


def recorded_plans(ticks) -> Iterator[TickPlan]:
    """The live ticks of a dct recording (runtime.app.replay.source.TickInputs)."""
    for t in ticks:
        yield TickPlan(t.tick, t.scheduled_s, t.now_s, t)


def grid_plans(t0_s: float, period_s: float, end_s: float) -> Iterator[TickPlan]:
    """A bag's ticks: every period from t0 until end_s."""
    k = 0
    while True:
        t = t0_s + k * period_s
        if t > end_s:
            return
        yield TickPlan(k, t, t)
        k += 1


__all__ = ["ReplayClock", "ReplayDesyncError", "TickPlan", "grid_plans", "recorded_plans"]
