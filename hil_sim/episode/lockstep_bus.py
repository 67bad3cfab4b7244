"""An in-process CAN channel for lockstep simulation: a python-can bus (`can.BusABC`) without the
per-frame costs of python-can's `virtual` interface.

The lockstep simulator polls its bus every 1 ms physics step and the base sends about 350
feedback frames a second. python-can's VirtualBus deep-copies every frame for every receiver
(`copy.deepcopy` of the Message), stamps it with the wall clock (unless `preserve_timestamps`),
and a poll of an empty bus goes through `queue.Queue.get`, a lock and a raised `queue.Empty`.
That was a tenth of the simulator's step (docs/decisions/sim-lockstep-speed.md). `LockstepBus`
keeps python-can's Bus interface (send, recv with a timeout, filters, shutdown, context manager),
so the firmware emulator, the controller's driver and the recorder's bus proxy use it unchanged.

Semantics, as python-can's virtual bus: every bus on the same channel name (in this process)
receives each frame sent by the others (and its own with `receive_own_messages`), in order,
without loss. Differences, both for determinism and cost:

* a frame keeps the sender's `timestamp` (the emulated firmware stamps simulation time; the
  virtual bus would stamp `time.time()`, which nothing may read in lockstep);
* each receiver gets its own Message built from the sent one's fields (`is_rx`, `channel` set
  for that receiver), not a deep copy: the data bytes are copied, nothing else is mutable.
"""
from __future__ import annotations

import threading
from collections import deque
from typing import Any

import can

_channels: dict[str, list["LockstepBus"]] = {}
_channels_lock = threading.Lock()


class LockstepBus(can.BusABC):
    """One end of an in-process CAN channel (see the module docstring)."""

    def __init__(self, channel: str, receive_own_messages: bool = False,
                 can_filters: can.typechecking.CanFilters | None = None, **kwargs: Any) -> None:
        if not isinstance(channel, str) or not channel:
            raise ValueError(f"LockstepBus: channel must be a non-empty string, got {channel!r}")
        self.channel_id = channel
        self.channel_info = f"Lockstep bus channel {channel}"
        self.receive_own_messages = bool(receive_own_messages)
        self._queue: deque[can.Message] = deque()
        self._cond = threading.Condition()
        self._open = True
        super().__init__(channel=channel, can_filters=can_filters, **kwargs)
        with _channels_lock:
            self._peers = _channels.setdefault(channel, [])
            self._peers.append(self)

    def _check_if_open(self) -> None:
        if not self._open:
            raise can.CanOperationError("Cannot operate on a closed bus")

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        """Deliver `msg` to every other bus on the channel (and to this one with
        receive_own_messages). Never blocks: the queues are unbounded, like the virtual bus's."""
        self._check_if_open()
        data = bytes(msg.data)
        for bus in tuple(self._peers):
            own = bus is self
            if own and not self.receive_own_messages:
                continue
            bus._put(can.Message(
                timestamp=msg.timestamp, arbitration_id=msg.arbitration_id, is_extended_id=msg.is_extended_id,
                is_remote_frame=msg.is_remote_frame, is_error_frame=msg.is_error_frame, channel=self.channel_id,
                dlc=msg.dlc, data=data, is_fd=msg.is_fd, is_rx=not own, bitrate_switch=msg.bitrate_switch,
                error_state_indicator=msg.error_state_indicator))

    def _put(self, msg: can.Message) -> None:
        with self._cond:
            self._queue.append(msg)
            self._cond.notify()

    def recv(self, timeout: float | None = None) -> can.Message | None:
        """As `can.BusABC.recv`; a poll (timeout 0, what the lockstep firmware and driver do every
        step) reads the queue directly, without the base class's clock and retry loop."""
        if timeout == 0:
            self._check_if_open()
            queue = self._queue
            while queue:
                msg = queue.popleft()
                if self._matches_filters(msg):
                    return msg
            return None
        return super().recv(timeout)

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        self._check_if_open()
        with self._cond:
            if not self._queue and timeout != 0:
                self._cond.wait(timeout)
            if self._queue:
                return self._queue.popleft(), False
        return None, False

    def shutdown(self) -> None:
        super().shutdown()
        if self._open:
            self._open = False
            with _channels_lock:
                self._peers.remove(self)
                if not self._peers and _channels.get(self.channel_id) is self._peers:
                    del _channels[self.channel_id]


__all__ = ["LockstepBus"]
