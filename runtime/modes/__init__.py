"""Navigation modes: the strategies the tick calls through one interface (docs/architecture.md).

- The planners (registry.py, `planner.algorithm`): `mpc` (mpc.py: reference path + OSQP MPC with
  the distance net), `grid-astar` (grid_astar.py: the Ellis22-like baseline), `pure-pursuit`
  (pure_pursuit.py: blind to obstacles).
- The recoveries: `backoff` (backoff.py: reverse along the recorded path, then replan) and
  `correcting` (correcting.py: the DCT paper's correcting mode).

`ModeSelector` (selector.py) is the small state machine that chooses among them each tick.
Which points are P_fix is not a mode's choice (runtime.perception.partition), nor is safety
(the controller checks every command with runtime.safety.supervisor).
"""
from runtime.modes.base import ModeDecision, NavigationMode, Situation

__all__ = ["ModeDecision", "NavigationMode", "Situation"]
