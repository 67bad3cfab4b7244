"""A loop clock on ROS time: time.monotonic shifted once, at start, onto the system clock.

Sensor stamps are ROS time (the system clock; the Livox driver stamps its frames with it), the
loop needs a monotonic clock. `EpochMonotonicClock` never jumps, and a stamp and a loop time can
be compared (the input watchdogs, the deskew, the sensor-to-command latency). A MonotonicClock,
so the loop treats it as the wall clock.

When the system clock is stepped later (NTP, a person setting the time), the stamps the drivers
write jump with it and the loop's clock does not: `system_step_s()` says by how much, and the
sensor inbox puts the stamps back onto the loop's clock with it (runtime.io.sensor_inbox).
"""
from __future__ import annotations

import time

from runtime.loop.fixed_rate import MonotonicClock


class EpochMonotonicClock(MonotonicClock):
    def __init__(self) -> None:
        self.offset_s = self._system_minus_monotonic()

    @staticmethod
    def _system_minus_monotonic() -> float:
        """The system clock minus the monotonic one, from a read of each taken within 1 ms (a
        thread preempted between the two reads would otherwise make a step of its pause)."""
        for _ in range(5):
            m0 = time.monotonic()
            wall = time.time()
            m1 = time.monotonic()
            if m1 - m0 < 1e-3:
                break
        return wall - 0.5 * (m0 + m1)

    def now(self) -> float:
        return time.monotonic() + self.offset_s

    def system_step_s(self) -> float:
        """How far the system clock has been stepped since this clock started (s; about 0, to the
        microsecond, until something steps it)."""
        return self._system_minus_monotonic() - self.offset_s

    def sleep_until(self, t_s: float) -> None:
        while True:
            remaining = t_s - self.now()
            if remaining <= 0.0:
                return
            time.sleep(remaining)
