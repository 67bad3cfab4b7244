"""The fixed-rate loop: read() -> update() -> write() at an absolute period.

Shaped like ros2_control's controller manager. Ticks are scheduled on an absolute grid
t_k = t_0 + k * period on the loop's clock, so there is no drift; a tick that runs past
its period is counted and the loop resumes at the next future grid point (never a burst
of catch-up ticks, never a negative sleep). Between ticks the loop re-sends the current
wheel command at the CAN command rate (0x111 at 50 Hz) from this same thread: if the loop
hangs, the commands stop and the base firmware's 500 ms timeout stops the wheels.

The clock is injected: `MonotonicClock` runs on the wall clock (the robot, real-time HIL);
in lockstep HIL the simulator supplies a clock whose `sleep_until` advances physics, so the
same loop runs on simulation time. Stage durations are always measured on the monotonic
wall clock (they are what the computer really spent).

Two clocks, never mixed (docs/architecture.md): the command deadline that the controller acts on
is judged on the loop's clock (the wall clock on the robot; simulated time in lockstep, where
the simulator waits for the tick, so a lockstep verdict never depends on the machine's load).
The wall-clock latency of every command is measured beside it and recorded as what it is
(`wall_command_latency_s`, `wall_deadline_missed`): in lockstep a report, not a verdict.
"""
from __future__ import annotations

import contextlib
import gc
import math
import time
from typing import Callable, Iterator, Protocol

import numpy as np

from runtime.loop.heap import TRIM_EVERY_TICKS, HeapTrimmer
from runtime.loop.telemetry import STAGES, TickTelemetry


#: Ticks between full collections (the loop's default).
FULL_COLLECTION_EVERY_TICKS = 200


@contextlib.contextmanager
def collector_outside_ticks() -> Iterator[None]:
    """Python's garbage collector as the loop runs it: the start-up heap frozen (never scanned
    again), the automatic collector off, so no collection pause lands inside a tick; the caller
    collects between ticks with `collect_between_ticks`. Restored on exit."""
    was_enabled = gc.isenabled()
    gc.collect(1)  # the young garbage; a full pass over the start-up heap (torch's) costs 0.2 s
    gc.freeze()
    gc.disable()
    try:
        yield
    finally:
        gc.unfreeze()
        if was_enabled:
            gc.enable()


def collect_between_ticks(ticks_run: int, full_every: int) -> None:
    """The collection after tick number `ticks_run` (counted from 1): the youngest generation
    every 10 ticks, everything every `full_every` ticks (0: never)."""
    if full_every and ticks_run % full_every == 0:
        gc.collect()
    elif ticks_run % 10 == 0:
        gc.collect(0)


class Clock(Protocol):
    def now(self) -> float:
        """Current time in seconds."""

    def sleep_until(self, t_s: float) -> None:
        """Return at (or as soon as possible after) time t_s; return at once if it has passed."""


class MonotonicClock:
    """The wall clock (time.monotonic) with absolute-time sleeps."""

    def now(self) -> float:
        return time.monotonic()

    def sleep_until(self, t_s: float) -> None:
        while True:
            remaining = t_s - time.monotonic()
            if remaining <= 0.0:
                return
            time.sleep(remaining)


class StageClock:
    """Times the stages of one tick into its telemetry record: `mark(i)` closes stage i.

    Preallocated and reused every tick; marking costs one perf_counter_ns call.
    """

    def __init__(self, budgets_s: np.ndarray, loop_clock: Callable[[], float] | None = None) -> None:
        self.budgets_s = np.asarray(budgets_s, dtype=np.float64)
        self._row: np.void | None = None
        self._t0_ns = 0
        self._last_ns = 0
        self._loop_clock = loop_clock
        self.write_done_s = 0.0  # wall clock: tick start -> command written
        self.write_done_loop_s: float | None = None  # the loop's clock when the command was written

    def start(self, row: np.void) -> None:
        self._row = row
        self._t0_ns = self._last_ns = time.perf_counter_ns()
        self.write_done_s = 0.0
        self.write_done_loop_s = None

    def mark(self, stage_index: int) -> None:
        now = time.perf_counter_ns()
        duration_s = (now - self._last_ns) * 1e-9
        self._last_ns = now
        row = self._row
        row["stage_s"][stage_index] = duration_s
        if duration_s > self.budgets_s[stage_index]:
            row["overrun_mask"] |= np.uint32(1 << stage_index)

    def mark_command_written(self) -> None:
        """Call right after the command left for the bus (the command deadline is measured here)."""
        self.write_done_s = (time.perf_counter_ns() - self._t0_ns) * 1e-9
        if self._loop_clock is not None:
            self.write_done_loop_s = self._loop_clock()

    def elapsed_s(self) -> float:
        return (time.perf_counter_ns() - self._t0_ns) * 1e-9

    def offset_s(self, t_ns: int) -> float:
        """A perf_counter_ns reading as seconds after this tick's start."""
        return (t_ns - self._t0_ns) * 1e-9


class LoopControlled(Protocol):
    """What the loop drives: one tick per period and keep-alive writes in between."""

    def tick(self, scheduled_s: float, stages: StageClock) -> None: ...

    def keepalive(self, now_s: float) -> None: ...

    def note_deadline(self, missed: bool) -> None: ...

    def slack_work(self) -> bool:
        """Work that need not delay the command (a reference search): run after write(), in the
        slack before the next tick, when enough of it is left (FixedRateLoop.slack_work_min_s).
        Returns whether there was any."""

    state_code: int  # recorded in telemetry
    command: tuple[float, float]  # (v_mps, omega_radps) written this tick


class FixedRateLoop:
    def __init__(
        self,
        clock: Clock,
        *,
        period_s: float,
        stage_budgets_s: dict[str, float],
        command_deadline_s: float,
        keepalive_period_s: float | None,
        telemetry: TickTelemetry | None = None,
        gc_every_ticks: int = FULL_COLLECTION_EVERY_TICKS,
        trim_every_ticks: int = TRIM_EVERY_TICKS,
        slack_work_min_s: float = 0.02,
        slack_work_max_postpone: int = 2,
        after_tick: Callable[[np.void], None] | None = None,
    ) -> None:
        """slack_work_min_s: the controller's slack work runs after a tick only while at least
        this much of the period is left on the loop's clock (in lockstep always: simulated time
        stands still during a tick); otherwise it waits for the slack of a later tick, at most
        slack_work_max_postpone ticks in a row: then it runs whatever is left (a search must not
        starve: without a path the robot holds still), and a next tick that starts late is counted
        as such (lateness, skipped ticks).
        after_tick: called with each tick's committed telemetry row, outside the tick's timings (a
        recorder copies it into its queue: runtime.io.recording); it must be short and must not block.
        `before_tick` (an attribute, None by default): called with the tick's scheduled time once the
        clock reached it, before the tick and outside its timings: a lockstep simulator finishes
        there what the tick must find in its inputs (a camera image whose render is still running)."""
        if not (period_s > 0.0 and math.isfinite(period_s)):
            raise ValueError(f"loop period must be a positive number of seconds, got {period_s}")
        if keepalive_period_s is not None and not 0.0 < keepalive_period_s <= period_s:
            raise ValueError(f"keepalive period {keepalive_period_s} s must be in (0, period={period_s}] s")
        unknown = set(stage_budgets_s) - set(STAGES)
        if unknown:
            raise ValueError(f"stage budgets name unknown stages {sorted(unknown)}; stages are {STAGES}")
        self.clock = clock
        self.period_s = period_s
        self.command_deadline_s = command_deadline_s
        self.keepalive_period_s = keepalive_period_s
        self.telemetry = telemetry or TickTelemetry()
        budgets = np.array([stage_budgets_s.get(s, period_s) for s in self.telemetry.stages])
        self.stage_clock = StageClock(budgets, loop_clock=clock.now)
        self.gc_every_ticks = gc_every_ticks
        #: The C heap's free pages given back between ticks (runtime.loop.heap).
        self.heap = HeapTrimmer(trim_every_ticks)
        self.slack_work_min_s = slack_work_min_s
        self.slack_work_max_postpone = slack_work_max_postpone
        self.after_tick = after_tick
        self.before_tick: Callable[[float], None] | None = None
        self.after_tick_errors = 0
        self.after_tick_error: str | None = None
        self._postponed_in_row = 0
        self.keepalives_sent = 0
        #: The loop's clock is the wall clock (its lateness is real waiting time).
        self.wall_clock_loop = isinstance(clock, MonotonicClock)

    def run(self, controlled: LoopControlled, should_stop: Callable[[], bool], max_ticks: int | None = None) -> None:
        """Run ticks until should_stop() (checked before each tick) or max_ticks."""
        with collector_outside_ticks():
            self._run(controlled, should_stop, max_ticks)

    def _run(self, controlled: LoopControlled, should_stop: Callable[[], bool], max_ticks: int | None) -> None:
        clock, telemetry, stages = self.clock, self.telemetry, self.stage_clock
        slack_work = getattr(controlled, "slack_work", None)
        t0 = clock.now()
        k = 0
        ticks_run = 0
        while not should_stop() and (max_ticks is None or ticks_run < max_ticks):
            scheduled = t0 + k * self.period_s
            clock.sleep_until(scheduled)
            if self.before_tick is not None:
                self.before_tick(scheduled)
            row = telemetry.begin_tick()
            row["tick"] = k
            row["scheduled_s"] = scheduled
            lateness = max(0.0, clock.now() - scheduled)
            row["lateness_s"] = lateness
            stages.start(row)
            controlled.tick(scheduled, stages)
            row["tick_s"] = stages.elapsed_s()
            row["state"] = controlled.state_code
            row["v_cmd_mps"], row["omega_cmd_radps"] = controlled.command
            controlled.note_deadline(self._judge_command(row, scheduled, lateness))
            if slack_work is not None:
                self._slack_work(slack_work, row, t0 + (k + 1) * self.period_s)
            telemetry.commit_tick(row)
            if self.after_tick is not None:
                self._call_after_tick(row)
            ticks_run += 1

            k, next_tick = self._next_grid_point(t0, k + 1)
            collect_between_ticks(ticks_run, self.gc_every_ticks)  # after write(), never inside a tick
            self.heap.between_ticks(ticks_run)
            self._keepalives(controlled, scheduled, next_tick)

    def _judge_command(self, row: np.void, scheduled: float, lateness: float) -> bool:
        """Record the command's latency: the verdict on the loop's clock (module docstring), the
        measurement on the wall clock. Returns whether the command missed its deadline."""
        stages = self.stage_clock
        written = stages.write_done_loop_s if stages.write_done_loop_s is not None else self.clock.now()
        latency = max(0.0, written - scheduled)
        row["command_latency_s"] = latency
        missed = latency > self.command_deadline_s
        row["deadline_missed"] = missed
        if stages.write_done_loop_s is not None:
            row["command_written_s"] = stages.write_done_s
        wall_latency = (lateness if self.wall_clock_loop else 0.0) + stages.write_done_s
        row["wall_command_latency_s"] = wall_latency
        row["wall_deadline_missed"] = wall_latency > self.command_deadline_s
        return missed

    def _slack_work(self, slack_work: Callable[[], bool], row: np.void, period_end: float) -> None:
        """Run the controller's slack work when enough of the period is left (or it was postponed
        too often); time it into the row when there was any."""
        telemetry = self.telemetry
        left = period_end - self.clock.now()
        if left >= self.slack_work_min_s or self._postponed_in_row >= self.slack_work_max_postpone:
            self._postponed_in_row = 0
            w0 = time.perf_counter_ns()
            if slack_work():
                row["slack_work_s"] = (time.perf_counter_ns() - w0) * 1e-9
                row["slack_work_start_s"] = self.stage_clock.offset_s(w0)
                telemetry.slack_work_runs += 1
        else:
            self._postponed_in_row += 1
            telemetry.slack_windows_skipped += 1

    def _call_after_tick(self, row: np.void) -> None:
        try:
            self.after_tick(row)
        except Exception as exc:  # noqa: BLE001 - an observer (a recorder) never ends the loop
            self.after_tick_errors += 1
            self.after_tick_error = f"{type(exc).__name__}: {exc}"
            self.after_tick = None  # off for the rest of the run; said in after_tick_error

    def _next_grid_point(self, t0: float, k: int) -> tuple[int, float]:
        """Grid point k, or the first one not yet passed (the ones skipped are counted)."""
        now = self.clock.now()
        next_tick = t0 + k * self.period_s
        if now > next_tick:
            behind = int((now - next_tick) // self.period_s) + 1
            self.telemetry.ticks_skipped += behind
            k += behind
            next_tick = t0 + k * self.period_s
        return k, next_tick

    def _keepalives(self, controlled: LoopControlled, tick_start: float, next_tick: float) -> None:
        """Re-send the current command at the CAN command rate until the next tick."""
        if self.keepalive_period_s is None:
            return
        j = 1
        while True:
            t = tick_start + j * self.keepalive_period_s
            if t >= next_tick - 1e-9:
                return
            if t > self.clock.now():
                self.clock.sleep_until(t)
                controlled.keepalive(t)
                self.keepalives_sent += 1
            j += 1
