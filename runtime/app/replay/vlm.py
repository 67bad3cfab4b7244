"""The VLM in a replay: the answers the live backend runner handed the VPP stage, at the live ticks.

Live, the runner (models.vlm.runner.BackendRunner) asks the backend beside the tick on the wall
clock: which answer a tick receives, and whether a request timed out, depend on the backend and the
machine at that moment. A recording of `dct run --record` keeps each answer the stage took, with
the controller's clock at the tick that took it (`/dct/vpp/backend_answer`,
runtime.io.recording.backend_answers). `ScriptedVlmRunner` stands in for the runner: it asks no
backend, and its `poll(now_s)` returns the recorded answers whose tick is due by now_s, in the
recorded order. A request the live run never got an answer to stays unanswered (the runner stays
busy, as the live one was at the end). The stage's post-processing (`post`, Phase II's image work)
runs on each valid answer just before it is delivered, as the live worker ran it before the answer
was ready.
"""
from __future__ import annotations

from collections import deque
from typing import Callable

#: The tick's clock, live and replayed, agree to this (both are the same float).
TIME_TOLERANCE_S = 1e-9


class ScriptedVlmRunner:
    """A BackendRunner's interface over recorded answers: schedule = [(the tick's now_s, answer)]
    in the recorded order."""

    name = "replay"

    def __init__(self, schedule) -> None:
        self._due: deque = deque(schedule)
        self.post: Callable | None = None
        self._requests: dict[float, object] = {}  # stamp -> the request the replay sent, unanswered
        self._pending = 0  # requests submitted and not answered yet
        self.submitted = 0
        self.delivered = 0
        self.failed = 0
        self.timed_out = 0
        self.replaced = 0
        self.mismatched = 0  # answers to an image the replay did not ask about: out of step
        self.post_failed = 0
        self.latency_s = 0.0

    @property
    def busy(self) -> bool:
        return self._pending > 0

    @property
    def left(self) -> int:
        """Recorded answers not delivered (the replay ended first)."""
        return len(self._due)

    def submit(self, request, now_s: float | None = None) -> None:
        self.submitted += 1
        self._pending += 1
        self._requests[float(request.stamp_s)] = request

    def settle(self, t_s: float) -> None:
        pass

    def poll(self, now_s: float) -> list:
        out = []
        while self._due and self._due[0][0] <= now_s + TIME_TOLERANCE_S:
            answer = self._due.popleft()[1]
            request = self._requests.pop(float(answer.stamp_s), None)
            if request is None:
                self.mismatched += 1
            elif self.post is not None and answer.error is None:
                try:
                    self.post(request, answer)
                except Exception:  # noqa: BLE001 - as live: the stage then prepares it in the tick
                    self.post_failed += 1
            self._pending = max(0, self._pending - 1)
            self.delivered += 1
            self.failed += int(answer.error is not None)
            out.append(answer)
        return out

    def counters(self) -> dict[str, int]:
        return {"submitted": self.submitted, "delivered": self.delivered, "failed": self.failed,
                "timed_out": self.timed_out, "replaced": self.replaced, "mismatched": self.mismatched, "post_failed": self.post_failed}

    def close(self) -> None:
        self._due.clear()
        self._requests.clear()


__all__ = ["ScriptedVlmRunner"]
