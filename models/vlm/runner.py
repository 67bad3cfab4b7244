"""Runs a contact-tolerance backend beside the tick and hands its answers back when they are due.

A backend answers in about a second (a hosted VLM) or hangs (a server that is down); the tick
must never wait for it (docs/algorithms/vpp.md, docs/architecture.md). The tick calls `submit(request)`, which
returns at once, and `poll(now_s)` each tick, which returns the answers ready by then. A backend
that is down, slow or raising degrades to error answers (no objects): the mask memory ages out
and points fall back to P_fix, never a stall.

One request is in flight at a time. A request submitted while one is in flight waits; a newer
one replaces a waiting one (counted in `replaced`): the backend always works on the newest
image, and the latency of what it answers stays bounded.

Two clocks (docs/architecture.md), as runtime.odometry.worker:
- Lockstep (`clock="lockstep"`): behaviour depends on simulated time only. A request that
  starts at simulated time t0 (its submit time, `now_s` or else its stamp, or when the one
  before it was delivered, whichever is later) is delivered at exactly t0 + latency_s of
  simulated time, however long the backend took on this machine. The answer is computed inline
  in `settle(t_s)` (the barrier the simulator calls before time t_s; or in `poll` when nobody
  settled), or, with `lockstep_thread=True`, in a worker thread started when the request starts
  (overlapping the physics) and waited for in settle/poll. No wall-clock timeout applies, except
  `stall_guard_s`, a generous guard against a hung backend (an error answer, counted in
  `timed_out`): a run that needs it is broken, not slow.
- Real time (`clock="realtime"`): each request runs in its own daemon thread. An answer is
  delivered at the first poll after it is ready and after latency_s of wall time since the start
  (the simulated latency of the sim-oracle; 0 for a real backend, whose latency is real). A
  request not answered within timeout_s of wall time is abandoned (its thread is left to finish
  on its own; its answer is thrown away) and an error answer is delivered (`timed_out`). While
  `max_abandoned` abandoned threads are still running, new requests get an error answer at once
  instead of a thread (a hung backend does not pile up threads).

Post-processing beside the tick: `post(request, answer)`, if set, is called with every valid
answer (no error) right after the backend's, where the backend ran (the worker thread, or
inline in settle in lockstep), before the answer is ready: the VPP stage prepares Phase II there
(runtime.vpp.stage). An exception from it turns the answer into an error answer (named).

Every answer carries the request's stamp and camera pose, `sent_s`, when the request went to the
backend (after any wait behind the one before; None for a request never sent), and `answered_s`,
when the answer was ready (in real time: the poll that delivers it), both on the runner's clock.
`latency_s` of an answer: simulated in lockstep, the wall time from start to delivery-ready in
real time.

Counters: submitted (requests given to submit), replaced (waiting requests a newer one
replaced, never sent), delivered (answers poll returned, errors included), failed (delivered
answers with an error, timeouts included), timed_out (those abandoned for the timeout or the
stall guard).
"""
from __future__ import annotations

import dataclasses
import threading
import time
from collections import deque
from dataclasses import dataclass, field
from typing import Callable, Literal

import numpy as np

from pydantic import BaseModel, ConfigDict, Field, model_validator

from models.vlm.interface import VlmAnswer, VlmAnswerError, VlmBackend, VlmRequest, validate_object

_EPS_S = 1e-9


class BackendRunnerConfig(BaseModel):
    """How a backend runs beside the tick (module docstring)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    #: Set by the controller (lockstep in the simulator, realtime on the robot); not in dumps, so
    #: that a dumped controller config loads again (runtime.vpp.config refuses it from a file).
    clock: Literal["lockstep", "realtime"] = Field("lockstep", exclude=True)
    #: Seconds from start to delivery (simulated in lockstep; a minimum in real time). None: the
    #: backend's own `latency_s` attribute (the sim-oracle's), else 0.
    latency_s: float | None = Field(None, ge=0.0, le=120.0)
    #: Real time: wall seconds after which a request is abandoned with an error answer.
    timeout_s: float = Field(5.0, gt=0.0, le=600.0)
    #: Real time: abandoned threads still running beyond which new requests fail at once.
    max_abandoned: int = Field(2, ge=1, le=100)
    #: Lockstep: compute in a worker thread (overlaps the physics) instead of inline in settle.
    lockstep_thread: bool = False
    #: Lockstep: wall seconds a settle waits for a hung backend before giving up on it.
    stall_guard_s: float = Field(120.0, gt=0.0, le=3600.0)

    @model_validator(mode="after")
    def _latency_below_timeout(self) -> "BackendRunnerConfig":
        if self.clock == "realtime" and self.latency_s is not None and self.latency_s >= self.timeout_s:
            raise ValueError(f"latency_s {self.latency_s} must be below timeout_s {self.timeout_s}: "
                             "every request would time out")
        return self


@dataclass
class _Job:
    request: VlmRequest
    submit_s: float  # lockstep: simulated submit time; real time: wall (monotonic)
    start_s: float = 0.0  # lockstep: simulated; real time: wall
    ready_s: float = 0.0  # lockstep: the simulated delivery time
    answer: VlmAnswer | None = None
    done: threading.Event = field(default_factory=threading.Event)
    thread: threading.Thread | None = None
    finished_wall_s: float = 0.0


class BackendRunner:
    """A backend run beside the tick: submit, poll, settle, close (module docstring)."""

    def __init__(self, backend: VlmBackend, config: BackendRunnerConfig | None = None) -> None:
        self.backend = backend
        self.config = c = config or BackendRunnerConfig()
        lat = c.latency_s if c.latency_s is not None else float(getattr(backend, "latency_s", 0.0) or 0.0)
        if c.clock == "realtime" and lat >= c.timeout_s:
            raise ValueError(f"BackendRunner: latency_s {lat} (the backend's) must be below timeout_s {c.timeout_s}")
        worst = getattr(getattr(backend, "config", None), "worst_case_s", None)
        if c.clock == "realtime" and callable(worst) and worst() > c.timeout_s:
            raise ValueError(f"BackendRunner: the backend may take up to {worst():.1f} s (its timeout x retries), more "
                             f"than the runner's timeout_s {c.timeout_s}: its answers would be abandoned")
        self.latency_s = lat
        self.lockstep = c.clock == "lockstep"
        #: Called beside the tick with (request, answer) for every valid answer (module docstring).
        self.post: Callable[[VlmRequest, VlmAnswer], None] | None = None
        self._in_flight: _Job | None = None
        self._waiting: _Job | None = None
        self._done: deque[tuple[float, VlmAnswer]] = deque()  # (ready time, answer), in order
        self._abandoned: list[threading.Thread] = []
        self._closed = False
        self.submitted = 0
        self.delivered = 0
        self.failed = 0
        self.timed_out = 0
        self.replaced = 0

    # -- helpers ------------------------------------------------------------------------------
    @property
    def name(self) -> str:
        return str(getattr(self.backend, "name", type(self.backend).__name__))

    @property
    def busy(self) -> bool:
        """A request is in flight (or waiting)."""
        return self._in_flight is not None or self._waiting is not None

    def _error(self, request: VlmRequest, why: str, latency_s: float) -> VlmAnswer:
        return VlmAnswer(stamp_s=request.stamp_s, camera_pose_odom=request.camera_pose_odom, objects=(),
                         backend=self.name, latency_s=latency_s, error=why)

    def _call(self, job: _Job) -> None:
        """Ask the backend; any exception or a non-answer becomes an error answer."""
        try:
            answer = self.backend.query(job.request)
            if not isinstance(answer, VlmAnswer):
                answer = self._error(job.request, f"{self.name}: backend returned {type(answer).__name__}, "
                                                  "not a VlmAnswer", 0.0)
            else:
                answer = self._validated(job.request, answer)
        except Exception as exc:  # a backend that raises: an error answer, never the caller's exception
            answer = self._error(job.request, f"{self.name}: {type(exc).__name__}: {exc}"[:500], 0.0)
        if self.post is not None and answer.error is None:
            try:
                self.post(job.request, answer)
            except Exception as exc:  # a bug in the post-processing: named, and the answer not used
                answer = self._error(job.request, f"post-processing: {type(exc).__name__}: {exc}"[:500], 0.0)
        job.answer = answer
        job.finished_wall_s = time.monotonic()
        job.done.set()

    def _validated(self, request: VlmRequest, answer: VlmAnswer) -> VlmAnswer:
        """Every object checked where it enters (interface.validate_object, against the request's
        image): a bad one is dropped and named in `rejected`, the others pass; whatever the
        backend's own checks were."""
        shape = np.asarray(request.image).shape[:2]
        keep, rejected = [], list(answer.rejected)
        for i, obj in enumerate(answer.objects):
            try:
                keep.append(validate_object(obj, shape, f"{self.name} object {i}"))
            except VlmAnswerError as exc:
                rejected.append(str(exc))
        if len(keep) == len(answer.objects):
            return answer
        return dataclasses.replace(answer, objects=tuple(keep), rejected=tuple(rejected))

    def _start_thread(self, job: _Job) -> None:
        job.thread = threading.Thread(target=self._call, args=(job,), name="dct-vlm-backend", daemon=True)
        job.thread.start()

    def _emit(self, ready_s: float, answer: VlmAnswer, **changes) -> None:
        """Queue an answer, ready at ready_s (one copy of it, with `changes` and its times)."""
        self._done.append((ready_s, dataclasses.replace(answer, answered_s=ready_s, **changes)))

    # -- the interface --------------------------------------------------------------------------
    def submit(self, request: VlmRequest, now_s: float | None = None) -> None:
        """Queue a request; returns at once. now_s: the submit time in the controller's clock
        (lockstep: simulated; default the request's stamp)."""
        if self._closed:
            raise RuntimeError("BackendRunner: submit after close")
        self.submitted += 1
        if self.lockstep:
            job = _Job(request, float(request.stamp_s if now_s is None else now_s))
        else:
            job = _Job(request, time.monotonic())
        if self._in_flight is None:
            self._start(job, job.submit_s)
        else:
            if self._waiting is not None:
                self.replaced += 1
            self._waiting = job

    def _start(self, job: _Job, start_s: float) -> None:
        job.start_s = start_s
        self._in_flight = job
        if self.lockstep:
            job.ready_s = start_s + self.latency_s
            if self.config.lockstep_thread:
                self._start_thread(job)
            return
        self._abandoned = [t for t in self._abandoned if t.is_alive()]
        if len(self._abandoned) >= self.config.max_abandoned:
            self._in_flight = None
            self._emit(start_s, self._error(job.request, f"{self.name}: backend hung ({len(self._abandoned)} "
                                                          "abandoned requests still running); request not sent", 0.0))
            return
        self._start_thread(job)

    def _finish_lockstep(self, job: _Job) -> None:
        """Lockstep: the in-flight job is due; get its answer (compute or wait) and queue it."""
        if job.thread is None:
            self._call(job)
        elif not job.done.wait(self.config.stall_guard_s):
            self.timed_out += 1
            job.answer = self._error(job.request, f"{self.name}: no answer within the lockstep stall guard of "
                                                  f"{self.config.stall_guard_s:.0f} s wall time", self.latency_s)
        assert job.answer is not None
        self._emit(job.ready_s, job.answer, stamp_s=job.request.stamp_s, camera_pose_odom=job.request.camera_pose_odom,
                   latency_s=self.latency_s, sent_s=job.start_s)
        self._in_flight = None
        if self._waiting is not None:
            nxt, self._waiting = self._waiting, None
            self._start(nxt, max(nxt.submit_s, job.ready_s))

    def _advance_lockstep(self, t_s: float) -> None:
        while self._in_flight is not None and self._in_flight.ready_s <= t_s + _EPS_S:
            self._finish_lockstep(self._in_flight)

    def _advance_realtime(self) -> None:
        while self._in_flight is not None:
            job, now = self._in_flight, time.monotonic()
            # (differences of clock readings, not (start + latency) - start: in floating point that
            # came out a hair under the latency when the monotonic clock reads in the thousands)
            if job.done.is_set() and now - job.start_s >= self.latency_s:
                assert job.answer is not None
                self._emit(now, job.answer, stamp_s=job.request.stamp_s, camera_pose_odom=job.request.camera_pose_odom,
                           latency_s=max(job.finished_wall_s - job.start_s, self.latency_s), sent_s=job.start_s)
            elif now - job.start_s >= self.config.timeout_s:
                self.timed_out += 1
                if job.thread is not None:
                    self._abandoned.append(job.thread)
                self._emit(now, self._error(job.request, f"{self.name}: no answer within {self.config.timeout_s:g} s "
                                                         "(abandoned)", now - job.start_s), sent_s=job.start_s)
            else:
                return
            self._in_flight = None
            if self._waiting is not None:
                nxt, self._waiting = self._waiting, None
                self._start(nxt, time.monotonic())

    def settle(self, t_s: float) -> None:
        """Lockstep: make every answer due by simulated time t_s ready (computes or waits).
        Real time: nothing (answers arrive when they arrive)."""
        if self.lockstep:
            self._advance_lockstep(t_s)

    def poll(self, now_s: float) -> list[VlmAnswer]:
        """The answers ready by now_s (lockstep: simulated; real time: now), oldest first.
        Never blocks in real time; in lockstep it computes (or waits for) what settle did not."""
        if self.lockstep:
            self._advance_lockstep(now_s)
        else:
            self._advance_realtime()
        out: list[VlmAnswer] = []
        while self._done and (not self.lockstep or self._done[0][0] <= now_s + _EPS_S):
            answer = self._done.popleft()[1]
            self.delivered += 1
            if answer.error is not None:
                self.failed += 1
            out.append(answer)
        return out

    def counters(self) -> dict[str, int]:
        return {"submitted": self.submitted, "delivered": self.delivered, "failed": self.failed,
                "timed_out": self.timed_out, "replaced": self.replaced}

    def close(self) -> None:
        """Drop whatever is pending; threads still running are daemons and are left to end."""
        self._closed = True
        self._in_flight = None
        self._waiting = None
        self._done.clear()


__all__ = ["BackendRunner", "BackendRunnerConfig"]
