"""The errors of the AgileX V2 codec: each a ``FrameError`` whose ``name`` is a counter key."""
from __future__ import annotations


class FrameError(ValueError):
    """A frame that cannot be encoded or decoded. ``name`` is a snake_case counter key."""

    name: str = "frame_error"

    def __init__(self, frame_id: int | None, detail: str) -> None:
        self.frame_id = frame_id
        self.detail = detail
        where = "frame" if frame_id is None else f"frame 0x{frame_id:03X}"
        super().__init__(f"{where}: {detail}")


class UnknownFrameId(FrameError):
    name = "unknown_frame_id"


class WrongDlc(FrameError):
    name = "wrong_dlc"


class OutOfRange(FrameError):
    name = "out_of_range"


class MalformedFrame(FrameError):
    name = "malformed_frame"


class CandumpSyntaxError(FrameError):
    name = "candump_syntax"


class FlaggedRecordError(FrameError):
    """``encode()`` of a record that carries ``flagged_fields``: decoded data, not a thing to send."""

    name = "flagged_record"
