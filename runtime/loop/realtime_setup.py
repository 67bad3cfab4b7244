"""Ask the OS for real-time scheduling (SCHED_FIFO) and CPU pinning for the control loop.

On the robot the loop may ask for SCHED_FIFO and CPU affinity when allowed,
and says so at start. `request_realtime` does the asking and never raises: what was granted and
what was refused (with the OS reason and how to allow it) comes back in a `RealtimeGrant` whose
`summary()` is the start-up line. The loop runs either way; without SCHED_FIFO it runs at normal
priority (SCHED_OTHER), where a busy machine can delay a tick (counted as lateness and deadline
misses, as always), and without pinning the kernel may move it between CPUs.

Linux applies both settings per thread when given pid 0: call it from the loop's own thread
(the tick thread), not from the main thread before starting it, so that helper threads (the
MCAP writer, the DDS receiver, the ICP worker) keep normal priority and never compete with
the tick at real-time priority.

`dct preflight` runs the same request on a throwaway thread to say in advance what the loop
will get (runtime.app.preflight).
"""
from __future__ import annotations

import dataclasses
import os
import resource
import sys
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

from pydantic import BaseModel, ConfigDict, Field, field_validator

#: How to allow SCHED_FIFO for the controller's user; appended to a refusal.
FIFO_FIX = ("run as root, or allow real-time priority: LimitRTPRIO=<priority> in the systemd unit "
            "(the bundle's unit sets it) or '<user> - rtprio 99' in /etc/security/limits.conf")
AFFINITY_FIX = "list only CPUs this process may use (see `nproc`, `taskset -p $$`) in realtime.cpus"


class RealtimeConfig(BaseModel):
    """The `realtime:` section of the controller config."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    #: Ask for SCHED_FIFO at `fifo_priority` (1-99). False: stay SCHED_OTHER (HIL on a laptop).
    fifo: bool = True
    fifo_priority: int = Field(default=50, ge=1, le=99)
    #: CPUs to pin the loop thread to (e.g. [1], leaving CPU 0 to the OS and the sensor
    #: drivers); None or empty: no pinning.
    cpus: tuple[int, ...] | None = None
    #: CPython's switch interval (sys.setswitchinterval), set for the process when the loop
    #: starts: how long a thread that wants the interpreter lock waits before the thread holding
    #: it is made to let go (Python's default is 5 ms). The loop thread shares the lock with the
    #: DDS receiver, the recorder and the VPP's helpers; every time it takes the lock back (after
    #: numpy, the solver or I/O released it) it may wait this long, whatever its OS priority.
    gil_switch_interval_ms: float = Field(default=0.5, gt=0.0, le=100.0)
    #: The most glibc malloc arenas the controller process keeps (runtime.loop.heap.limit_arenas),
    #: set before its threads start; None: glibc's default (eight per core).
    malloc_arena_max: int | None = Field(default=2, ge=1, le=64)

    @field_validator("cpus")
    @classmethod
    def _cpus(cls, v: tuple[int, ...] | None) -> tuple[int, ...] | None:
        if v is None or len(v) == 0:
            return None
        bad = [c for c in v if c < 0 or c > 4095]
        if bad:
            raise ValueError(f"CPU numbers must be in 0..4095, got {bad}")
        if len(set(v)) != len(v):
            raise ValueError(f"CPU numbers repeat: {list(v)}")
        return tuple(sorted(v))


@dataclass(frozen=True)
class RealtimeGrant:
    """What `request_realtime` asked for and got. `fifo_granted` / `affinity_granted` are None
    when that was not asked for."""

    fifo_requested: bool
    fifo_priority: int
    fifo_granted: bool | None
    fifo_reason: str | None
    cpus_requested: tuple[int, ...] | None
    affinity_granted: bool | None
    affinity_reason: str | None
    cpus_now: tuple[int, ...] = field(default=())
    #: The interpreter's switch interval set for the process (ms); None: left as it was.
    switch_interval_ms: float | None = None

    def summary(self) -> str:
        """One start-up line: what the loop runs with and, when something was refused, why."""
        if not self.fifo_requested:
            sched = "SCHED_OTHER (realtime.fifo is off)"
        elif self.fifo_granted:
            sched = f"SCHED_FIFO priority {self.fifo_priority}"
        else:
            sched = (f"SCHED_OTHER: SCHED_FIFO priority {self.fifo_priority} refused ({self.fifo_reason}); "
                     "ticks may be delayed by other work, and lateness is counted as usual")
        if self.cpus_requested is None:
            pin = f"not pinned (CPUs {_cpu_list(self.cpus_now)})"
        elif self.affinity_granted:
            pin = f"pinned to CPUs {_cpu_list(self.cpus_requested)}"
        else:
            pin = f"not pinned: CPUs {_cpu_list(self.cpus_requested)} refused ({self.affinity_reason})"
        gil = "" if self.switch_interval_ms is None else f"; GIL switch interval {self.switch_interval_ms:g} ms"
        return f"real-time: {sched}; {pin}{gil}"


def _cpu_list(cpus: Sequence[int]) -> str:
    return ",".join(str(c) for c in cpus) if cpus else "?"


def rtprio_limit() -> int | None:
    """The soft RLIMIT_RTPRIO (the highest SCHED_FIFO priority an unprivileged process may ask
    for); None where the platform has no such limit."""
    try:
        soft, _hard = resource.getrlimit(resource.RLIMIT_RTPRIO)
    except (AttributeError, OSError, ValueError):
        return None
    return None if soft == resource.RLIM_INFINITY else int(soft)


def _os_reason(exc: OSError) -> str:
    import errno

    code = errno.errorcode.get(exc.errno or 0)
    return f"{exc.strerror or exc} [{code}]" if code else str(exc)


def request_realtime(priority: int = 50, cpus: Sequence[int] | None = None, *, fifo: bool = True,
                     setscheduler: Callable[[int, int, object], None] | None = None,
                     setaffinity: Callable[[int, set[int]], None] | None = None,
                     getaffinity: Callable[[int], set[int]] | None = None) -> RealtimeGrant:
    """Ask for SCHED_FIFO at `priority` and pinning to `cpus` for the calling thread; never raises.

    The setscheduler / setaffinity / getaffinity arguments stand in for os.sched_* in tests.
    """
    setscheduler = setscheduler or getattr(os, "sched_setscheduler", None)
    setaffinity = setaffinity or getattr(os, "sched_setaffinity", None)
    getaffinity = getaffinity or getattr(os, "sched_getaffinity", None)
    if not 1 <= int(priority) <= 99:
        raise ValueError(f"request_realtime: priority must be in 1..99, got {priority}")
    fifo_granted: bool | None = None
    fifo_reason: str | None = None
    if fifo:
        if setscheduler is None or not hasattr(os, "SCHED_FIFO"):
            fifo_granted, fifo_reason = False, "this platform has no SCHED_FIFO"
        else:
            try:
                setscheduler(0, os.SCHED_FIFO, os.sched_param(int(priority)))
                fifo_granted = True
            except OSError as exc:
                limit = rtprio_limit()
                allowed = f"RLIMIT_RTPRIO is {limit}" if limit is not None else "RLIMIT_RTPRIO unlimited"
                fifo_granted, fifo_reason = False, f"{_os_reason(exc)}; {allowed}; fix: {FIFO_FIX}"
    cpus_req = tuple(sorted(set(int(c) for c in cpus))) if cpus else None
    affinity_granted: bool | None = None
    affinity_reason: str | None = None
    if cpus_req is not None:
        if setaffinity is None:
            affinity_granted, affinity_reason = False, "this platform has no sched_setaffinity"
        else:
            try:
                setaffinity(0, set(cpus_req))
                affinity_granted = True
            except (OSError, ValueError) as exc:
                why = _os_reason(exc) if isinstance(exc, OSError) else str(exc)
                affinity_granted, affinity_reason = False, f"{why}; fix: {AFFINITY_FIX}"
    try:
        now = tuple(sorted(getaffinity(0))) if getaffinity is not None else ()
    except OSError:
        now = ()
    return RealtimeGrant(fifo_requested=bool(fifo), fifo_priority=int(priority), fifo_granted=fifo_granted,
                         fifo_reason=fifo_reason, cpus_requested=cpus_req, affinity_granted=affinity_granted,
                         affinity_reason=affinity_reason, cpus_now=now)


def request_realtime_from_config(config: RealtimeConfig) -> RealtimeGrant:
    """`request_realtime` with the config's `realtime:` section (call from the loop thread), and
    the interpreter's switch interval (RealtimeConfig.gil_switch_interval_ms) for the process."""
    grant = request_realtime(config.fifo_priority, config.cpus, fifo=config.fifo)
    return dataclasses.replace(grant, switch_interval_ms=apply_switch_interval(config))


def apply_switch_interval(config: RealtimeConfig) -> float:
    """Set the interpreter's switch interval for the process (RealtimeConfig.gil_switch_interval_ms);
    returns it in ms."""
    sys.setswitchinterval(config.gil_switch_interval_ms * 1e-3)
    return config.gil_switch_interval_ms


__all__ = ["RealtimeConfig", "RealtimeGrant", "apply_switch_interval", "request_realtime", "request_realtime_from_config",
           "rtprio_limit"]
