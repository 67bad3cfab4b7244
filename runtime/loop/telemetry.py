"""Per-tick timing records in a preallocated ring buffer.

The tick writes one fixed-size record per period into a numpy structured array: no
allocation, no I/O in the tick. Readers (the latency report, the HIL metrics, a disk
writer thread) take copies with `snapshot()`.
"""
from __future__ import annotations

import threading
from dataclasses import dataclass

import numpy as np

#: Stages timed in every tick, in order. The tick reads like Algorithm 1 of the DCT paper:
#: read inputs -> odometry -> partition (VPP) -> planner (reference + MPC) -> safety -> write.
STAGES: tuple[str, ...] = ("read", "odometry", "partition", "planner", "safety", "write")


def tick_record_dtype(n_stages: int) -> np.dtype:
    return np.dtype(
        [
            ("tick", np.int64),  # tick index since start
            ("scheduled_s", np.float64),  # scheduled start on the loop clock
            ("lateness_s", np.float64),  # actual start - scheduled start (wake-up latency)
            ("stage_s", np.float64, (n_stages,)),  # duration of each stage (monotonic clock)
            ("tick_s", np.float64),  # whole tick: start of read() to end of write()
            ("slack_work_s", np.float64),  # work deferred to the slack after write() (replans); not in tick_s
            # Where in the tick (wall clock, seconds after its start; NaN: did not happen): the
            # command written, the slack work started. The stages start where the one before ended.
            ("command_written_s", np.float64),
            ("slack_work_start_s", np.float64),
            ("command_latency_s", np.float64),  # scheduled start -> command written (loop clock)
            ("overrun_mask", np.uint32),  # bit i set: stage i exceeded its budget (wall clock)
            ("deadline_missed", np.bool_),  # judged on the loop clock: what the controller acts on
            ("wall_command_latency_s", np.float64),  # the same, measured on the wall clock
            ("wall_deadline_missed", np.bool_),  # measured; in lockstep a report, not a verdict
            ("state", np.int8),  # controller state code (runtime.controller.navigation.ControllerState)
            ("v_cmd_mps", np.float32),
            ("omega_cmd_radps", np.float32),
        ]
    )


@dataclass(frozen=True)
class StageStats:
    name: str
    count: int
    median_ms: float
    p99_ms: float
    max_ms: float
    overruns: int


class TickTelemetry:
    """A ring buffer of the last `capacity` tick records plus running counters.

    `begin_tick` returns the row to fill; the loop fills it in place. Counters (overruns per
    stage, deadline misses) cover the whole run, not only what is still in the buffer.
    """

    def __init__(self, capacity: int = 1 << 14, stages: tuple[str, ...] = STAGES) -> None:
        if capacity <= 0:
            raise ValueError(f"telemetry capacity must be positive, got {capacity}")
        self.stages = stages
        self.capacity = capacity
        self._buf = np.zeros(capacity, dtype=tick_record_dtype(len(stages)))
        self._count = 0
        self.stage_overruns = np.zeros(len(stages), dtype=np.int64)
        self.deadline_misses = 0
        self.wall_deadline_misses = 0
        self.ticks_skipped = 0  # scheduled ticks dropped because a tick ran past its period
        self.slack_work_runs = 0  # ticks after which slack work ran and did something
        self.slack_windows_skipped = 0  # ticks that left too little of the period for slack work
        self._lock = threading.Lock()

    def stage_index(self, name: str) -> int:
        return self.stages.index(name)

    def begin_tick(self) -> np.void:
        row = self._buf[self._count % self.capacity]
        row["stage_s"][:] = 0.0
        row["overrun_mask"] = 0
        row["deadline_missed"] = False
        row["wall_deadline_missed"] = False
        row["wall_command_latency_s"] = 0.0
        row["slack_work_s"] = 0.0
        row["command_written_s"] = np.nan
        row["slack_work_start_s"] = np.nan
        return row

    def commit_tick(self, row: np.void) -> None:
        mask = int(row["overrun_mask"])
        if mask:
            for i in range(len(self.stages)):
                if mask & (1 << i):
                    self.stage_overruns[i] += 1
        if row["deadline_missed"]:
            self.deadline_misses += 1
        if row["wall_deadline_missed"]:
            self.wall_deadline_misses += 1
        with self._lock:
            self._count += 1

    @property
    def ticks(self) -> int:
        return self._count

    def snapshot(self) -> np.ndarray:
        """The records still in the buffer, oldest first (a copy)."""
        with self._lock:
            n = self._count
            if n <= self.capacity:
                return self._buf[:n].copy()
            start = n % self.capacity
            return np.concatenate([self._buf[start:], self._buf[:start]])

    def stage_stats(self) -> list[StageStats]:
        records = self.snapshot()
        out = []
        for i, name in enumerate(self.stages):
            d = records["stage_s"][:, i] * 1e3 if len(records) else np.zeros(0)
            out.append(
                StageStats(
                    name=name,
                    count=int(len(d)),
                    median_ms=float(np.median(d)) if len(d) else 0.0,
                    p99_ms=float(np.percentile(d, 99)) if len(d) else 0.0,
                    max_ms=float(d.max()) if len(d) else 0.0,
                    overruns=int(self.stage_overruns[i]),
                )
            )
        return out

    def _slack_work_stats(self, records: np.ndarray) -> dict:
        """Work done after write() in the slack (reference searches): ticks with some, its times."""
        ms = records["slack_work_s"][records["slack_work_s"] > 0.0] * 1e3
        return {
            "runs": int(self.slack_work_runs),
            "windows_skipped": int(self.slack_windows_skipped),
            "ticks": int(len(ms)),
            "median_ms": float(np.median(ms)) if len(ms) else 0.0,
            "p99_ms": float(np.percentile(ms, 99)) if len(ms) else 0.0,
            "max_ms": float(ms.max()) if len(ms) else 0.0,
        }

    def summary(self) -> dict:
        records = self.snapshot()
        tick_ms = records["tick_s"] * 1e3
        return {
            "ticks": self.ticks,
            "deadline_misses": int(self.deadline_misses),
            "wall_deadline_misses": int(self.wall_deadline_misses),
            "ticks_skipped": int(self.ticks_skipped),
            "tick_median_ms": float(np.median(tick_ms)) if len(tick_ms) else 0.0,
            "tick_p99_ms": float(np.percentile(tick_ms, 99)) if len(tick_ms) else 0.0,
            "tick_max_ms": float(tick_ms.max()) if len(tick_ms) else 0.0,
            "stages": {
                s.name: {"median_ms": s.median_ms, "p99_ms": s.p99_ms, "max_ms": s.max_ms, "overruns": s.overruns}
                for s in self.stage_stats()
            },
            "slack_work": self._slack_work_stats(records),
        }
