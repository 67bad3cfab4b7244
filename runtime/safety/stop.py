"""The controller's stop latch: feedback lost, start-up timeout, repeated deadline misses.

Separate from the point-based safety supervisor (which checks the command against raw
obstacle points): this one watches the loop and the base link. Once tripped it latches
STOPPED with the reason; only an explicit `reset()` clears it.
"""
from __future__ import annotations


class SafetyStop:
    def __init__(self, max_consecutive_deadline_misses: int, startup_timeout_s: float) -> None:
        self.max_consecutive_deadline_misses = max_consecutive_deadline_misses
        self.startup_timeout_s = startup_timeout_s
        self.consecutive_deadline_misses = 0
        self.tripped_reason: str | None = None
        self.trips = 0

    @property
    def tripped(self) -> bool:
        return self.tripped_reason is not None

    def trip(self, reason: str) -> None:
        if self.tripped_reason is None:
            self.tripped_reason = reason
            self.trips += 1

    def note_deadline(self, missed: bool) -> None:
        self.consecutive_deadline_misses = self.consecutive_deadline_misses + 1 if missed else 0
        if self.consecutive_deadline_misses >= self.max_consecutive_deadline_misses:
            self.trip(f"command deadline missed {self.consecutive_deadline_misses} ticks in a row")

    def reset(self) -> None:
        self.tripped_reason = None
        self.consecutive_deadline_misses = 0
