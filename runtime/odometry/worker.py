"""Where KISS-ICP runs: beside the tick, never in it.

KISS-ICP's registration holds Python's GIL for its whole duration, so a thread would stall the
tick. It runs in its own process (`ProcessIcpWorker`): jobs and results cross a pipe, the tick
only sends and polls, never waits (docs/decisions/odometry-icp-worker-process.md).

Two clocks (real time and lockstep, docs/architecture.md):
- Real time: a result is used when it has arrived. One frame is registered at a time; while the
  worker is busy, the newest frame waits and an older waiting one is dropped (counted): ICP
  always works on the newest data and its latency stays bounded.
- Lockstep: every frame is registered, and its result is delivered at exactly
  `end_s + latency_s` of simulated time, however long it took on this machine. The simulator
  waits for it (`settle(t)`, called by the lockstep clock before time t is reached) instead of
  racing it, so the same seed gives the same poses under any load. `InlineIcpWorker` computes the
  job right there, in the simulator's time advance (no process: cheaper for short runs);
  `ProcessIcpWorker` lets the registration overlap the physics.
"""
from __future__ import annotations

import itertools
import os
import pickle
import queue
import struct
import subprocess
import sys
import threading
import time
from collections import deque
from typing import Callable, Protocol

import numpy as np

from runtime.common.child_process import IdleChildren, spawn_module
from runtime.odometry.icp import IcpEngine, IcpJob, IcpResult, warm_up


class IcpWorker(Protocol):
    def submit(self, job: IcpJob) -> None: ...

    def poll(self, now_s: float) -> list[IcpResult]: ...

    def settle(self, t_s: float) -> None: ...

    def wait_ready(self) -> None: ...

    def close(self) -> None: ...


#: The worker process runs this much below the controller (os.nice): when the cores are
#: contended, the scheduler gives the tick the core before the registration. ICP's results may
#: come later then; the tick never waits for them (dead reckoning carries the pose meanwhile).
#: See docs/decisions/odometry-icp-worker-process.md.
WORKER_NICENESS = 10


def _serve(conn) -> None:
    """The worker process: build the engine it is sent, register every job, answer each; handed
    to a next run (ProcessIcpWorker's reuse), build that run's engine. Each run's engine comes
    with the run's generation, which its "ready" carries back."""
    try:
        os.nice(WORKER_NICENESS)
    except OSError:  # pragma: no cover - not permitted here: runs at the controller's priority
        pass
    try:
        generation, factory = conn.recv()
        engine = factory()
    except BaseException as exc:  # pragma: no cover - reported to the parent
        conn.send(("fatal", f"ICP worker could not start: {type(exc).__name__}: {exc}"))
        return
    try:  # a throwaway engine: the first real frame finds the kernels loaded
        warm_up(factory)
    except Exception:  # noqa: BLE001 - speed only: the real engine's frames report their own errors
        pass
    conn.send(("ready", generation))
    while True:
        try:
            job = _recv_job(conn)
        except (EOFError, OSError):
            return
        if job is None:
            return
        if isinstance(job, str) and job == _NEXT_RUN:  # handed to the next run: its engine follows
            engine = None  # the last run's engine and map go now
            try:
                message = conn.recv()
            except (EOFError, OSError):  # idle until its process ended: nothing to say
                return
            if message is None:  # no next run after all (the parent's pool was full)
                return
            generation, factory = message
            try:
                engine = factory()
            except BaseException as exc:  # pragma: no cover - reported to the parent
                conn.send(("fatal", f"ICP worker could not start: {type(exc).__name__}: {exc}"))
                return
            conn.send(("ready", generation))
            continue
        try:
            conn.send(("result", engine.process(job)))
        except BaseException as exc:  # only the job's identity goes back, never its points
            conn.send(("error", (_identity(job), f"{type(exc).__name__}: {exc}")))


def _job_message(job: IcpJob | str | None) -> list:
    """A job as the parts the sender thread writes: a small header (the pickle of everything
    but the arrays, and how many arrays follow) and the arrays' own memory, out of band
    (pickle protocol 5): the tick copies nothing and allocates only the header."""
    buffers: list[pickle.PickleBuffer] = []
    header = pickle.dumps(job, protocol=5, buffer_callback=buffers.append)
    return [struct.pack("<I", len(buffers)) + header, *(b.raw() for b in buffers)]


def _recv_job(conn) -> IcpJob | str | None:
    """The worker's side of _job_message."""
    head = conn.recv_bytes()
    (n,) = struct.unpack_from("<I", head)
    buffers = [conn.recv_bytes() for _ in range(n)]
    return pickle.loads(head[4:], buffers=buffers)


#: The message that stops the worker (None) and its sender thread.
_CLOSE = _job_message(None)
#: The message that hands the worker to the next run (ProcessIcpWorker's `reuse`): it drops its
#: engine and builds one from the (generation, factory) sent next (None: it ends); the sender
#: thread stops after writing it.
_NEXT_RUN = "next run"
_NEXT = _job_message(_NEXT_RUN)

#: Idle workers kept for the next run in this process (`reuse`): a fresh interpreter takes 0.3-0.5 s
#: to import and warm up, which every lockstep episode of a campaign waited for at its activation.
MAX_IDLE_WORKERS = 1
_IDLE = IdleChildren(MAX_IDLE_WORKERS)
#: Each run's number (its worker's "ready" carries it: a ready left unread by an earlier run of
#: the same worker is not this run's).
_GENERATIONS = itertools.count(1)


def _spawn():
    """A fresh worker process and our end of its socket pair."""
    return spawn_module("runtime.odometry.worker")


def _take_idle() -> tuple[subprocess.Popen, object] | None:
    return _IDLE.take()


def _identity(job: IcpJob) -> tuple[int, float, float, float, int]:
    return job.seq, job.stamp_s, job.end_s, job.ready_at_s, len(job.points)


def _failed(identity: tuple[int, float, float, float, int], why: str) -> IcpResult:
    seq, stamp_s, end_s, ready_at_s, n = identity
    return IcpResult(seq=seq, stamp_s=stamp_s, end_s=end_s, ready_at_s=ready_at_s, pose_base=np.zeros(3),
                     delta_base=None, prev_end_s=None, constraint=None, points_in=n, points_registered=0,
                     deskewed=False, compute_s=0.0, error=why)


class InlineIcpWorker:
    """Lockstep only: the job is computed in `settle`, in the simulator's time advance."""

    def __init__(self, engine_factory: Callable[[], IcpEngine]) -> None:
        self._factory = engine_factory
        self._engine: IcpEngine | None = None
        self._jobs: deque[IcpJob] = deque()
        self._done: deque[IcpResult] = deque()
        self.dropped = 0  # never: every frame is registered
        self.failed: str | None = None
        self.round_trip_s: deque[float] = deque()  # no round trip: computed in place

    def submit(self, job: IcpJob) -> None:
        self._jobs.append(job)

    def settle(self, t_s: float) -> None:
        while self._jobs and self._jobs[0].ready_at_s <= t_s + 1e-9:
            job = self._jobs.popleft()
            if self._engine is None:
                self._engine = self._factory()
            try:
                self._done.append(self._engine.process(job))
            except Exception as exc:  # a registration that raised: the frame is lost, named
                self._done.append(_failed(_identity(job), f"{type(exc).__name__}: {exc}"))

    def poll(self, now_s: float) -> list[IcpResult]:
        out = []
        while self._done and self._done[0].ready_at_s <= now_s + 1e-9:
            out.append(self._done.popleft())
        return out

    def wait_ready(self) -> None:
        """Nothing to wait for: the engine is built at the first settle that has a job."""

    def close(self) -> None:
        self._jobs.clear()


class ProcessIcpWorker:
    """KISS-ICP in a child process (see the module docstring for the two clocks)."""

    def __init__(self, engine_factory: Callable[[], IcpEngine], lockstep: bool,
                 start_timeout_s: float = 60.0, reuse: bool = False) -> None:
        """reuse: take an idle worker a closed run of this process left (its engine is rebuilt
        from engine_factory; what the last run left in the pipe is discarded up to its ready),
        and leave this one idle at close. Lockstep campaigns: every episode is a run."""
        # A fresh interpreter running this module (`python -m runtime.odometry.worker FD`), joined
        # by a socket pair: no fork of a process that holds CAN-bus threads, and, unlike
        # multiprocessing's spawn, no re-import of the caller's main script.
        self.reuse = reuse
        self._factory = engine_factory
        self._generation = next(_GENERATIONS)
        idle = _take_idle() if reuse else None
        #: This run took an idle worker (a fresh one replaces it if it does not come back).
        self._reused = idle is not None
        self.lockstep = lockstep
        self._start_timeout_s = start_timeout_s
        self._in_flight: deque[IcpJob] = deque()  # sent, result not received (in order)
        self._waiting: IcpJob | None = None  # real time: the newest frame while the worker is busy
        self._done: deque[IcpResult] = deque()
        self.dropped = 0
        self.failed: str | None = None
        #: Real time: wall-clock seconds from a job's send to its result (pose latency part).
        self.round_trip_s: deque[float] = deque(maxlen=2000)
        self._sent_at: dict[int, float] = {}
        #: The worker said it has built its engine and registered its warm-up frames.
        self.ready = False
        self._attach(idle if idle is not None else _spawn())  # last: its sender thread may set `failed`

    # -- plumbing ------------------------------------------------------------------------------
    def _attach(self, worker) -> None:
        """Send the worker (process, connection) this run's engine, and start the sender thread.
        A reused worker that died while idle is replaced by a fresh one."""
        self._proc, self._conn = worker
        try:
            self._conn.send((self._generation, self._factory))
        except BaseException:
            self._proc.kill()
            self._proc.wait()
            self._conn.close()
            if not self._reused:
                raise
            self._reused = False
            self._attach(_spawn())
            return
        # Sending a 20k-point frame (320 kB) blocks while the worker is still registering the
        # previous one (the socket buffer is smaller): a sender thread writes it, the tick only
        # pickles its small header and queues it with views of the frame's arrays (no copy:
        # pickle protocol 5, out of band; a validated frame's arrays are read-only,
        # runtime.common.sensor_data). The thread then holds the GIL only between its socket writes (which release
        # it); pickling the whole frame in the thread let it take the GIL from the tick
        # mid-stage, for as long as the OS kept it off a core.
        self._outbox: queue.SimpleQueue = queue.SimpleQueue()
        self._sender = threading.Thread(target=self._send_loop, args=(self._outbox, self._conn), name="dct-icp-send",
                                        daemon=True)
        self._sender.start()

    def _send_loop(self, outbox: queue.SimpleQueue, conn) -> None:
        """The sender thread of one worker connection (a replaced worker's thread keeps its own)."""
        while True:
            parts = outbox.get()
            try:
                for part in parts:
                    conn.send_bytes(part)
            except (OSError, ValueError) as exc:
                if conn is self._conn:
                    self.failed = self.failed or f"ICP worker gone ({exc})"
                return
            if parts is _CLOSE or parts is _NEXT:
                return

    def _send(self, job: IcpJob) -> None:
        self._sent_at[job.seq] = time.perf_counter()
        self._in_flight.append(job)
        self._outbox.put(_job_message(job))

    def _receive(self, block: bool) -> bool:
        """Take one message; False when none (non-blocking) or the worker is gone."""
        try:
            if not block and not self._conn.poll(0):
                return False
            if block and not self._conn.poll(self._start_timeout_s):
                self.failed = f"ICP worker did not answer within {self._start_timeout_s:.0f} s"
                return False
            kind, payload = self._conn.recv()
        except (EOFError, OSError) as exc:
            self.failed = self.failed or f"ICP worker gone ({type(exc).__name__})"
            return False
        if kind == "ready":
            self.ready = self.ready or payload == self._generation  # not an earlier run's unread one
        elif kind == "fatal":
            self.failed = payload
        elif kind in ("result", "error") and not self.ready:
            pass  # an idle worker's answers to its last run, sent before this run's ready
        elif kind in ("result", "error"):
            result = payload if kind == "result" else _failed(*payload)
            if self._in_flight and self._in_flight[0].seq == result.seq:
                self._in_flight.popleft()
            sent = self._sent_at.pop(result.seq, None)
            if sent is not None:
                self.round_trip_s.append(time.perf_counter() - sent)
            self._done.append(result)
        return True

    # -- the interface -------------------------------------------------------------------------
    def submit(self, job: IcpJob) -> None:
        if self.failed:
            return
        if self.lockstep or not self._in_flight:
            self._send(job)
            return
        if self._waiting is not None:
            self.dropped += 1
        self._waiting = job

    def poll(self, now_s: float) -> list[IcpResult]:
        while self._receive(block=False):
            pass
        if not self.lockstep and not self._in_flight and self._waiting is not None:
            job, self._waiting = self._waiting, None
            self._send(job)
        out = []
        while self._done and (not self.lockstep or self._done[0].ready_at_s <= now_s + 1e-9):
            out.append(self._done.popleft())
        return out

    def settle(self, t_s: float) -> None:
        """Lockstep: block until every job due by t_s has its result."""
        if not self.lockstep:
            return
        while not self.failed and self._in_flight and self._in_flight[0].ready_at_s <= t_s + 1e-9:
            if not self._receive(block=True):
                break

    def wait_ready(self) -> None:
        """Block until the worker has started (a fresh interpreter, its engine built and warmed up:
        0.3-0.5 s), or failed to (`failed` says why). Start-up work, never in a tick."""
        while not self.ready and not self.failed:  # this run's "ready" or "fatal" comes first
            if not self._receive(block=True):
                break
        if self.failed and self._reused:  # the idle worker did not come back: a fresh one, once
            self._outbox.put(_CLOSE)
            self._proc.kill()
            threading.Thread(target=_reap, args=(self._proc, self._conn), name="dct-icp-reap", daemon=True).start()
            self.failed, self._reused = None, False
            self._attach(_spawn())
            self.wait_ready()

    def close(self) -> None:
        """Ask the worker to end and return; the process is reaped by a thread (the child's
        interpreter takes 0.1-0.2 s to end, which an episode in a campaign need not wait for).
        With reuse, a worker that is well is left idle for the next run instead (at most
        MAX_IDLE_WORKERS; it ends with this process, when its socket closes)."""
        if self.reuse and not self.failed and self._proc.poll() is None:
            self._outbox.put(_NEXT)
            self._sender.join(timeout=2.0)
            if self._sender.is_alive():  # the worker reads nothing any more
                self._proc.kill()
            else:
                if _IDLE.offer(self._proc, self._conn):
                    return
                try:  # enough idle ones: no next run for this one, which ends
                    self._conn.send(None)
                except (OSError, ValueError):
                    self._proc.kill()
        else:
            self._outbox.put(_CLOSE)
            self._sender.join(timeout=2.0)
        threading.Thread(target=_reap, args=(self._proc, self._conn), name="dct-icp-reap", daemon=True).start()


def _reap(proc: subprocess.Popen, conn, timeout_s: float = 2.0) -> None:
    """Wait for a worker process that was asked to end (kill it when it does not), then close
    its connection: open until then, so the results it still sends find a reader's socket."""
    try:
        proc.wait(timeout=timeout_s)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait(timeout=timeout_s)
    finally:
        conn.close()


__all__ = ["IcpWorker", "InlineIcpWorker", "ProcessIcpWorker"]


if __name__ == "__main__":  # the worker process (started by ProcessIcpWorker)
    import signal
    from multiprocessing.connection import Connection as _Connection

    # Ctrl-C in a terminal reaches the whole process group: the controller stops this worker
    # itself (closing the pipe) after its own orderly stop, so the worker ignores the signal.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    _serve(_Connection(int(sys.argv[1])))
