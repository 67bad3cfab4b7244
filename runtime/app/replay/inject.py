"""How `dct replay` hands the recorded inputs to the controller, through the code the robot runs.

- `ReplayTransport`: a runtime.io.ros.transport.Transport whose readers serve the recorded CDR
  bytes. The replay pushes one sample and has the ordinary RosSensorReceiver process it
  (`poll`), so each sample goes through the same decoders, conversions and validation as live,
  in the order it was received, and into the same SensorInbox.
- `ReplayCanBus`: a python-can bus that the AgileX driver reads as it reads the robot's; the replay
  queues the frames the live driver received before the tick that read them, and every frame the
  controller sends (its commands) is kept, as the live run would have put them on the bus.
- `ReplayVlm`: the VLM backend of a replay. Asking a live VLM would make the replay depend on it;
  a recording that carries the live runner's answers replaces the runner altogether
  (runtime.app.replay.vlm). Without them (an older recording, a bag) every request fails at once,
  named, so the vpp partition treats the points as it does when the VLM is down (deterministic).
"""
from __future__ import annotations

from collections import deque

import can

from runtime.io.ros.transport import QosSpec, TopicReader, TopicWriter, Transport


class ReplayReader(TopicReader):
    def __init__(self, topic: str) -> None:
        self.topic = topic
        self.pending: deque[bytes] = deque()

    def take_raw(self, n: int = 64) -> list[bytes]:
        out = []
        while self.pending and len(out) < n:
            out.append(self.pending.popleft())
        return out


class _NullWriter(TopicWriter):
    def __init__(self, topic: str, cls: type) -> None:
        self.topic, self.cls = topic, cls

    def write_cdr(self, cdr: bytes) -> None:  # a replay publishes nothing
        pass


class ReplayTransport(Transport):
    """Readers that serve what the replay pushes (`push`); writers that drop what they get."""

    name = "replay"
    domain_id = -1
    discovery = "localhost"

    def __init__(self) -> None:
        super().__init__()
        self.readers: dict[str, ReplayReader] = {}

    def reader(self, topic: str, cls: type, qos: QosSpec) -> ReplayReader:
        r = self.readers.setdefault(topic, ReplayReader(topic))
        self._route("in", topic, cls, qos, self.name, "the recording")
        return r

    def writer(self, topic: str, cls: type, qos: QosSpec) -> TopicWriter:
        return _NullWriter(topic, cls)

    def push(self, topic: str, data: bytes) -> None:
        self.readers[topic].pending.append(data)

    def wait(self, timeout_s: float) -> None:
        pass

    def wake(self) -> None:
        pass

    def close(self) -> None:
        self.readers.clear()


class ReplayCanBus(can.BusABC):
    """The base's side as recorded: `queue()` puts received frames where the driver's next
    `recv` finds them; `send` keeps the controller's frames (`sent`)."""

    def __init__(self) -> None:
        super().__init__(channel="replay")
        self.channel_info = "dct replay"
        self._rx: deque[can.Message] = deque()
        self.sent: list[tuple[int, bytes]] = []

    def queue(self, t_s: float, can_id: int, data: bytes) -> None:
        self._rx.append(can.Message(timestamp=t_s, arbitration_id=can_id, data=data, is_extended_id=False))

    def _recv_internal(self, timeout):
        return (self._rx.popleft() if self._rx else None), False

    def send(self, msg, timeout=None) -> None:
        self.sent.append((int(msg.arbitration_id), bytes(msg.data)))

    def shutdown(self) -> None:
        self._rx.clear()
        super().shutdown()


class ReplayVlm:
    """A VLM backend that answers nothing (module docstring)."""

    name = "replay"
    latency_s = 0.0

    def query(self, request):
        raise RuntimeError("no VLM in a replay: the recording does not carry the VLM's answers")


__all__ = ["ReplayCanBus", "ReplayReader", "ReplayTransport", "ReplayVlm"]
