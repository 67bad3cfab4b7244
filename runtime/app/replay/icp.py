"""KISS-ICP in a replay: the frames the live run registered, each result at the tick it came live.

On the robot ICP runs beside the tick on the wall clock (runtime.odometry.worker): while the worker
is busy a newer frame replaces a waiting one, and a result is fused at whichever tick it has
arrived by. Both depend on the machine's load at that moment, so the live odometry does too. The
recording says, per tick, which results the tick received (`/dct/inputs`: job number and frame
stamp); `ScriptedIcpWorker` makes the replay do the same: a frame the live run never registered is
dropped, and each registered one is delivered at the live tick (its `ready_at_s` is that tick's
clock, and the lockstep worker it wraps waits for it there). The registration itself is KISS-ICP on
one thread, deterministic: the same frames in the same order give the same poses.
"""
from __future__ import annotations

import dataclasses

#: Stamps of the same frame, live and replayed, agree to this (both are the same float).
STAMP_TOLERANCE_S = 1e-6


class ScriptedIcpWorker:
    """A lockstep worker (ProcessIcpWorker or InlineIcpWorker with lockstep delivery) told which
    jobs to register and when to deliver them: schedule[seq] = (delivery time, frame stamp)."""

    def __init__(self, inner, schedule: dict[int, tuple[float, float]]) -> None:
        self.inner = inner
        self.schedule = dict(schedule)
        self.dropped = 0  # frames the live run did not register (its worker was busy)
        self.mismatched = 0  # frames whose stamp is not the live job's: the replay is out of step
        self.submitted = 0

    @property
    def failed(self) -> str | None:
        return self.inner.failed

    @property
    def round_trip_s(self):
        return getattr(self.inner, "round_trip_s", ())

    def submit(self, job) -> None:
        live = self.schedule.get(job.seq)
        if live is None:
            self.dropped += 1
            return
        deliver_at, stamp = live
        if abs(job.stamp_s - stamp) > STAMP_TOLERANCE_S:
            self.mismatched += 1
        self.submitted += 1
        self.inner.submit(dataclasses.replace(job, ready_at_s=deliver_at))

    def poll(self, now_s: float):
        self.inner.settle(now_s)  # a result due at this very tick is waited for, not left to the next
        return self.inner.poll(now_s)

    def settle(self, t_s: float) -> None:
        self.inner.settle(t_s)

    def wait_ready(self) -> None:
        self.inner.wait_ready()

    def close(self) -> None:
        self.inner.close()


def icp_schedule(ticks) -> dict[int, tuple[float, float]]:
    """seq -> (the controller's clock at the tick that received it, frame stamp), from the
    recording's per-tick inputs (runtime.app.replay.source.TickInputs)."""
    out = {}
    for t in ticks:
        for seq, stamp in t.icp_results:
            out[seq] = (t.now_s, stamp)
    return out


__all__ = ["ScriptedIcpWorker", "icp_schedule"]
