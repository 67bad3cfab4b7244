"""Navigation modes: strategies the tick calls through one interface (DESIGN.md section 11).

- `pure-pursuit` (pure_pursuit.py): the step-1 placeholder, blind to obstacles.
- `all-fixed` (all_fixed.py): reference path + OSQP MPC with every lidar point in P_fix.
- `dct` (dct.py): the all-fixed planner with the VLM partition stage (runtime.perception.partition):
  only the points the VPP keeps fixed are P_fix.
- `grid-astar` (grid_astar.py): inflated occupancy grid from every point, A*, pure pursuit along the
  path (the Ellis22-like baseline of DCT Table I).
- `backoff` (backoff.py): the stall recovery: reverse along the recorded path, then replan
  (the seed of the paper's correcting mode).

`ModeSelector` (selector.py) is the small state machine that chooses among them.
"""
from runtime.modes.base import ModeDecision, NavigationMode, Situation

__all__ = ["ModeDecision", "NavigationMode", "Situation"]
