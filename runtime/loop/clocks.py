"""A loop clock on ROS time: time.monotonic shifted once, at start, onto the system clock.

Sensor stamps are ROS time (the system clock; the Livox driver stamps its frames with it), the
loop needs a monotonic clock. `EpochMonotonicClock` never jumps, and a stamp and a loop time can
be compared (the input watchdogs, the deskew, the sensor-to-command latency). A MonotonicClock,
so the loop treats it as the wall clock.
"""
from __future__ import annotations

import time

from runtime.loop.fixed_rate import MonotonicClock


class EpochMonotonicClock(MonotonicClock):
    def __init__(self) -> None:
        self.offset_s = time.time() - time.monotonic()

    def now(self) -> float:
        return time.monotonic() + self.offset_s

    def sleep_until(self, t_s: float) -> None:
        while True:
            remaining = t_s - self.now()
            if remaining <= 0.0:
                return
            time.sleep(remaining)
