"""Run one lockstep episode (scene: the first argument, case1 by default) and print, as JSON,
the compiled-kernel signatures numba added (compiled, or loaded from its cache) while a controller
tick ran. Run in a process of its own (test_tick_compiles_nothing.py): in a process that already
holds a signature, a tick that needs it adds nothing."""
import json
import sys
import time

from numba.core import dispatcher

added = []
_add = dispatcher.Dispatcher.add_overload


def add_overload(self, cres):
    added.append((time.perf_counter(), f"{self.py_func.__module__}.{self.py_func.__qualname__} {cres.signature}"))
    return _add(self, cres)


dispatcher.Dispatcher.add_overload = add_overload

from runtime.controller.navigation import NavigationController  # noqa: E402

ticks = []
_tick = NavigationController.tick


def tick(self, *args, **kwargs):
    t0 = time.perf_counter()
    try:
        return _tick(self, *args, **kwargs)
    finally:
        ticks.append((t0, time.perf_counter()))


NavigationController.tick = tick

from hil_sim.episode.lockstep import run_episode  # noqa: E402

result = run_episode(sys.argv[1] if len(sys.argv) > 1 else "case1", seed=0)
in_tick = sorted({name for t, name in added if any(a <= t <= b for a, b in ticks)})
print(json.dumps({"ticks": len(ticks), "signatures_added": len(added), "in_tick": in_tick,
                  "success": bool(result.metrics["success"])}))
