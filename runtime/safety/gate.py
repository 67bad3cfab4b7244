"""The safety supervisor's verdict on each command, with its stops logged once per episode.

In a tight passage the supervisor may stop and let go tick by tick: a `supervisor_stop` event is
logged when stops begin, and `supervisor_clear` only after CLEAR_TICKS ticks in a row without one.
"""
from __future__ import annotations

import numpy as np

from runtime.common.events import EventLog
from runtime.safety.supervisor import SafetySupervisor

#: Ticks in a row without a supervisor stop before `supervisor_clear` is logged.
CLEAR_TICKS = 10


class SafetyGate:
    def __init__(self, supervisor: SafetySupervisor, events: EventLog) -> None:
        self.supervisor = supervisor
        self.events = events
        self.last = None  # the last decision (runtime.safety.supervisor)
        self._stopping = False
        self._clear_ticks = 0

    def check(self, now_s: float, pose: np.ndarray, v: float, omega: float,
              points: np.ndarray) -> tuple[float, float]:
        """The command as the supervisor lets it through (zero on a stop: `last.stopped`)."""
        decision = self.supervisor.check(pose, np.array([v, omega]), points)
        self.last = decision
        if decision.stopped:
            self._clear_ticks = 0
            if not self._stopping:
                self._stopping = True
                self.events.add(now_s, "supervisor_stop", decision.reason)
        elif self._stopping:
            self._clear_ticks += 1
            if self._clear_ticks >= CLEAR_TICKS:
                self._stopping = False
                self.events.add(now_s, "supervisor_clear", f"no supervisor stop for {CLEAR_TICKS} ticks")
        return float(decision.command_out[0]), float(decision.command_out[1])
