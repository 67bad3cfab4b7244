"""The controller's event log: every stop, resume, restart and degraded mode, with its reason.

Events are rare (a handful per run), so the tick may append one; the log is bounded (the
oldest are dropped and counted) so that a flapping input cannot grow memory without limit.
Each event names the input or the rule behind it ("lidar blind", "0x311 stale", "E-stop").

Event names:
- `stop`: a controlled stop while an input is faulty (the reason lists every faulty input; a
  new event whenever that set changes).
- `resume`: every input good again, driving resumes.
- `restart`: the start-up sequence again (fresh enable, commands ramp from zero), after an
  E-stop or a base that lost our command stream.
- `safety_stop`: a latched stop (deadline misses in real time, a base fault, the base left
  command mode, no base at start-up); only a new run clears it.
- `blocked` / `unblocked`: no path to the goal in the local map (the robot holds still) / a
  path again.
- `supervisor_stop` / `supervisor_clear`: the safety supervisor replaced the planner's command by
  a stop / no stop for 10 ticks in a row (once per episode of stops, not per tick).
- `stall`: no progress towards the goal with a valid reference path; `backoff`: the recovery
  reverses along the recorded path; `backoff_end`: it is done and the planner replans.
- `stuck`: commanding motion without moving (DCT's correcting-mode trigger); `correcting`: correcting
  mode starts (the object relabelled fixed, or none, and the reverse); `correcting_end`: it is done
  (with its duration) and the planner replans.
- `degraded` / `restored`: the planner falls back to the previous plan (a failed solve).
- `goal_reached`; `new_goal`: a goal replaced the current one (from which source, and whether
  while driving or waiting at the last goal).
"""
from __future__ import annotations

from collections import deque
from dataclasses import dataclass


@dataclass(frozen=True)
class ControllerEvent:
    t_s: float
    event: str
    reason: str

    def to_dict(self, t0_s: float = 0.0) -> dict:
        return {"t_s": round(self.t_s - t0_s, 6), "event": self.event, "reason": self.reason}


class EventLog:
    def __init__(self, capacity: int = 1000) -> None:
        self._events: deque[ControllerEvent] = deque(maxlen=capacity)
        self.dropped = 0

    def add(self, t_s: float, event: str, reason: str) -> None:
        if len(self._events) == self._events.maxlen:
            self.dropped += 1
        self._events.append(ControllerEvent(float(t_s), event, reason))

    def __iter__(self):
        return iter(tuple(self._events))

    def __len__(self) -> int:
        return len(self._events)

    def last(self, event: str | None = None) -> ControllerEvent | None:
        for e in reversed(self._events):
            if event is None or e.event == event:
                return e
        return None

    def to_list(self, t0_s: float = 0.0) -> list[dict]:
        return [e.to_dict(t0_s) for e in self._events]


__all__ = ["ControllerEvent", "EventLog"]
