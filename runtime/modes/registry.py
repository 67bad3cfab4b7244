"""Planner modes by name (`planner.mode` in the controller config). Adding a mode adds a file
with a `build(context) -> ModeStack` and a line here, not a branch in the controller."""
from __future__ import annotations

from importlib import import_module

from runtime.modes.base import ModeContext, ModeStack

#: mode name -> module with `build(context) -> ModeStack` (imported only when used: the MPC
#: mode loads TorchScript).
MODES = {
    "pure-pursuit": "runtime.modes.pure_pursuit",
    "all-fixed": "runtime.modes.all_fixed",
    # The same planner, with the VLM partition stage: only the VPP's P_fix reaches it.
    "dct": "runtime.modes.dct",
    # Occupancy grid + A* + pure pursuit, every point fixed: the Ellis22-like baseline.
    "grid-astar": "runtime.modes.grid_astar",
}


def build_mode(name: str, context: ModeContext) -> ModeStack:
    try:
        module = MODES[name]
    except KeyError:
        raise ValueError(f"unknown planner mode {name!r}; known: {', '.join(MODES)}") from None
    return import_module(module).build(context)
