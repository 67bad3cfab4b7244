"""The planners by name (`planner.algorithm` in the controller config), and what each needs.

Adding a planner adds a module with `build(context) -> ModeStack` and an entry here, not a
branch in the controller. Which lidar points the planner must keep clear of (P_fix) is the other
setting, the partition (runtime.perception.partition); presets name common pairs
(runtime.config.presets: `dct` is the MPC on the VLM partition).
"""
from __future__ import annotations

from dataclasses import dataclass
from importlib import import_module

from runtime.modes.base import ModeContext, ModeStack


@dataclass(frozen=True)
class PlannerSpec:
    #: The module with `build(context) -> ModeStack` (imported only when used: the MPC loads
    #: TorchScript).
    module: str
    #: Reads the lidar and the IMU (every planner but the blind placeholder).
    uses_lidar: bool
    #: Needs the distance net for the robot's footprint (checked at start-up).
    uses_distance_net: bool
    summary: str
    #: Its path follower's section of `planner:` (target speed within the robot's), None: none.
    follower_section: str | None = None


PLANNERS = {
    "mpc": PlannerSpec("runtime.modes.mpc", uses_lidar=True, uses_distance_net=True,
                       summary="reference path, then the OSQP MPC with the distance net's collision rows"),
    "grid-astar": PlannerSpec("runtime.modes.grid_astar", uses_lidar=True, uses_distance_net=False,
                              summary="inflated occupancy grid, A*, pure pursuit (the Ellis22-like baseline)",
                              follower_section="grid_astar"),
    "pure-pursuit": PlannerSpec("runtime.modes.pure_pursuit", uses_lidar=False, uses_distance_net=False,
                                summary="straight at the goal, blind to obstacles (tests and benches only)",
                                follower_section="pure_pursuit"),
}


def planner_spec(name: str) -> PlannerSpec:
    try:
        return PLANNERS[name]
    except KeyError:
        raise ValueError(f"unknown planner {name!r}; known: {', '.join(PLANNERS)}") from None


def build_planner(name: str, context: ModeContext) -> ModeStack:
    return import_module(planner_spec(name).module).build(context)
