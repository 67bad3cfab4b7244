"""Named errors of the models package: each says what was wrong and where."""
from __future__ import annotations


class DistanceNetError(RuntimeError):
    """Base class of every error raised by the distance net and its tools."""


class InvalidPointsError(ValueError):
    """Points handed to the distance net or the exact dual are not a finite (N, 2) float array."""


class FootprintMismatchError(DistanceNetError):
    """The distance-net artifact was trained for a footprint other than the robot description's."""


class DistanceNetFileError(DistanceNetError):
    """The distance-net artifact is missing, unreadable, not TorchScript, or lacks our metadata."""


class UnsupportedFootprintError(DistanceNetError):
    """The footprint is not a shape the distance net supports (a centred, axis-aligned rectangle)."""
