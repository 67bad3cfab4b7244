"""The controller's lifecycle states (the state machine is in runtime.controller.navigation)."""
from __future__ import annotations

from enum import IntEnum


class ControllerState(IntEnum):
    INITIALIZING = 0  # start-up sequence: base enabled, waiting for it and for every input
    ACTIVE = 1  # navigating
    GOAL_REACHED = 2  # at the goal, commanding zero; waiting for the next goal (idle, not a fault)
    STOPPED = 3  # latched stop: commanding zero until a new run
    HOLDING = 4  # controlled stop while an input is faulty; resumes by itself
