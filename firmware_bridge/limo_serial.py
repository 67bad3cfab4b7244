"""The LIMO chassis UART link as a python-can bus (docs/protocol.md, section LIMO serial link).

Each frame is 14 bytes: ``0x55 0x0E idH idL d0..d7 count checksum`` with
``checksum = sum(d0..d7) mod 256``. The host sends ``count = 0``. The reader resynchronises on
a bad header, length or checksum by dropping one byte and searching for the next ``0x55``; each
rejected candidate frame is counted in ``bad_frames``.
"""
from __future__ import annotations

import time
from typing import Any

import can
import serial

LIMO_HEADER = 0x55
LIMO_FRAME_LEN = 0x0E  # 14 bytes, also the second byte of every frame
LIMO_DEFAULT_BAUD = 460800


def limo_checksum(payload: bytes) -> int:
    """(sum of the 8 payload bytes) mod 256."""
    return sum(payload) & 0xFF


def frame_limo(arbitration_id: int, data: bytes, count: int = 0) -> bytes:
    """Wrap a CAN id and up to 8 payload bytes (zero-padded to 8) in a LIMO serial frame."""
    if not 0 <= arbitration_id <= 0x7FF:
        raise ValueError(f"LIMO serial frame: id 0x{arbitration_id:X} is not an 11-bit id")
    if len(data) > 8:
        raise ValueError(f"LIMO serial frame 0x{arbitration_id:03X}: {len(data)} data bytes > 8")
    if not 0 <= count <= 0xFF:
        raise ValueError(f"LIMO serial frame 0x{arbitration_id:03X}: count {count} not in 0..255")
    payload = bytes(data).ljust(8, b"\0")
    return bytes((LIMO_HEADER, LIMO_FRAME_LEN, arbitration_id >> 8, arbitration_id & 0xFF)) + payload + bytes(
        (count, limo_checksum(payload)))


class LimoFrameParser:
    """Incremental parser of the LIMO byte stream with resynchronisation."""

    def __init__(self) -> None:
        self._buf = bytearray()
        self.bad_frames = 0
        self.frames_ok = 0

    def feed(self, chunk: bytes) -> None:
        self._buf.extend(chunk)

    def next_frame(self) -> tuple[int, bytes, int] | None:
        """The next valid ``(id, payload, count)``, or None when more bytes are needed."""
        buf = self._buf
        while True:
            start = buf.find(LIMO_HEADER)
            if start < 0:
                buf.clear()
                return None
            if start:
                del buf[:start]
            if len(buf) < 2:
                return None
            if buf[1] != LIMO_FRAME_LEN:
                self.bad_frames += 1
                del buf[:1]
                continue
            if len(buf) < LIMO_FRAME_LEN:
                return None
            frame = bytes(buf[:LIMO_FRAME_LEN])
            payload = frame[4:12]
            fid = (frame[2] << 8) | frame[3]
            if limo_checksum(payload) != frame[13] or fid > 0x7FF:
                self.bad_frames += 1
                del buf[:1]
                continue
            del buf[:LIMO_FRAME_LEN]
            self.frames_ok += 1
            return fid, payload, frame[12]

    def frames(self) -> list[tuple[int, bytes, int]]:
        """All complete valid frames currently buffered."""
        out = []
        while (f := self.next_frame()) is not None:
            out.append(f)
        return out


class LimoSerialBus(can.BusABC):
    """python-can bus over the LIMO UART (pyserial), so the driver does not care which link it has.

    ``channel`` is a serial port path (``/dev/ttyTHS1``, a pty slave) or a pyserial URL.
    """

    def __init__(self, channel: str, baudrate: int = LIMO_DEFAULT_BAUD, can_filters: Any = None,
                 **kwargs: Any) -> None:
        if not channel:
            raise can.CanInitializationError("limo_serial: a serial port path is required as channel")
        try:
            self._serial = serial.serial_for_url(channel, baudrate=int(baudrate), bytesize=8,
                                                 parity="N", stopbits=1, timeout=0)
        except (serial.SerialException, ValueError, OSError) as exc:
            raise can.CanInitializationError(f"limo_serial: cannot open {channel!r}: {exc}") from exc
        self.channel = channel
        self.channel_info = f"LIMO serial {channel} @ {baudrate} baud"
        self._parser = LimoFrameParser()
        self.last_rx_count = 0
        self._protocol = can.CanProtocol.CAN_20
        super().__init__(channel=channel, can_filters=can_filters, **kwargs)

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        if msg.is_extended_id or msg.is_remote_frame or msg.is_error_frame or msg.is_fd:
            raise can.CanOperationError(
                f"limo_serial: frame 0x{msg.arbitration_id:X} must be a classic standard-id data frame")
        try:
            frame = frame_limo(int(msg.arbitration_id), bytes(msg.data))
        except ValueError as exc:
            raise can.CanOperationError(str(exc)) from exc
        try:
            self._serial.write_timeout = timeout
            self._serial.write(frame)
        except (serial.SerialException, OSError) as exc:
            raise can.CanOperationError(f"limo_serial: write failed: {exc}") from exc

    @property
    def bad_frames(self) -> int:
        """Candidate frames rejected (bad length byte, bad checksum or id) since the bus opened."""
        return self._parser.bad_frames

    @property
    def frames_received(self) -> int:
        return self._parser.frames_ok

    def _parse_one(self) -> can.Message | None:
        frame = self._parser.next_frame()
        if frame is None:
            return None
        fid, payload, count = frame
        self.last_rx_count = count
        return can.Message(timestamp=time.time(), arbitration_id=fid, is_extended_id=False,
                           dlc=8, data=payload, channel=self.channel)

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        deadline = None if timeout is None else time.monotonic() + timeout
        while True:
            msg = self._parse_one()
            if msg is not None:
                return msg, False
            try:
                waiting = self._serial.in_waiting
                if waiting:
                    self._serial.timeout = 0
                    chunk = self._serial.read(waiting)
                else:
                    remaining = None if deadline is None else max(0.0, deadline - time.monotonic())
                    if remaining == 0.0:
                        return None, False
                    # Block for at least one byte, at most the remaining time.
                    self._serial.timeout = remaining
                    chunk = self._serial.read(1)
            except (serial.SerialException, OSError) as exc:
                raise can.CanOperationError(f"limo_serial: read failed: {exc}") from exc
            if chunk:
                self._parser.feed(chunk)
            elif deadline is not None and time.monotonic() >= deadline:
                return None, False

    def fileno(self) -> int:
        return self._serial.fileno()

    def shutdown(self) -> None:
        if self._is_shutdown:
            return
        super().shutdown()
        try:
            self._serial.close()
        except (serial.SerialException, OSError):
            pass
