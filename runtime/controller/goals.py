"""Goals: validated where they enter, handed to the tick through a one-slot mailbox.

A goal may come at any time from any source (`dct run --goal`, /goal_pose, the simulator's
patrol); `GoalMailbox.request` checks it at once (GoalError naming the source and the field) and
leaves it for the next tick's read stage, which takes it (the newest request wins).
"""
from __future__ import annotations

import math
import threading

from runtime.common.geometry import Pose2D

#: A requested goal within this of the current one (x and y, m) is the same goal (not replanned).
GOAL_SAME_TOLERANCE_M = 1e-3
#: Goals farther than this from the odometry frame's origin (m) are refused (not a place).
GOAL_MAX_ABS_M = 1.0e4


class GoalError(ValueError):
    """A goal that cannot be driven to (not finite, out of range): names the source and field."""


def check_goal(goal: Pose2D, source: str) -> Pose2D:
    """The goal as floats, or GoalError naming `source` and the bad field."""
    for name in ("x_m", "y_m", "yaw_rad"):
        v = getattr(goal, name)
        try:
            v = float(v)
        except (TypeError, ValueError):
            raise GoalError(f"goal from {source}: {name} {v!r} is not a number") from None
        if not math.isfinite(v):
            raise GoalError(f"goal from {source}: {name} {v!r} is not finite")
        if name != "yaw_rad" and abs(v) > GOAL_MAX_ABS_M:
            raise GoalError(f"goal from {source}: {name} {v!r} is farther than {GOAL_MAX_ABS_M:g} m from the "
                            "odometry frame's origin")
    return Pose2D(float(goal.x_m), float(goal.y_m), float(goal.yaw_rad))


def same_goal(a: Pose2D, b: Pose2D) -> bool:
    return math.hypot(a.x_m - b.x_m, a.y_m - b.y_m) <= GOAL_SAME_TOLERANCE_M


class GoalMailbox:
    """The newest goal requested since the last tick (any thread may request)."""

    def __init__(self) -> None:
        self._pending: tuple[Pose2D, str] | None = None
        self._lock = threading.Lock()

    def request(self, goal: Pose2D, source: str) -> None:
        checked = check_goal(goal, source)
        with self._lock:
            self._pending = (checked, source)

    @property
    def pending(self) -> bool:
        return self._pending is not None

    def take(self) -> tuple[Pose2D, str] | None:
        with self._lock:
            pending, self._pending = self._pending, None
        return pending
