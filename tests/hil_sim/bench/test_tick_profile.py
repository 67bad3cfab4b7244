"""dct bench tick --profile: the parts table of a short lockstep episode, and the methods it wraps
given back afterwards."""
from __future__ import annotations

import importlib

from hil_sim.bench.tick import capped_scene, resolve_scene, run_ticks
from hil_sim.bench.tick_profile import PARTS, TICK, TickProfile, parts_lines


def _originals():
    return {(m, c, f): getattr(importlib.import_module(m), c).__dict__[f] for _, m, c, f in PARTS + (("", *TICK),)}


def test_the_profile_times_every_tick_and_its_parts_then_gives_the_methods_back(tmp_path):
    before = _originals()
    profile = TickProfile()
    with profile.installed():
        ticks = run_ticks(capped_scene(resolve_scene("case1"), 1.0), 0)
    assert _originals() == before
    table = profile.table()
    assert table["ticks"] == len(profile.rows) > 0
    assert abs(2 * len(profile.rows) - len(ticks.tick_ms)) <= 2  # every other pair of ticks (the rest is cProfile's)
    parts = {p["part"]: p for p in table["parts"]}
    # every tick reads the base and writes a command; the parts never take longer than the tick
    assert parts["NavigationController._read"]["mean_ms"] > 0.0
    assert all(p["mean_ms"] <= table["tick"]["mean_ms"] + 1e-9 for p in table["parts"])
    assert any("MpcPlanner.plan" in line for line in parts_lines(table))
    profile.write(tmp_path)
    assert (tmp_path / "tick.prof").stat().st_size > 0
    assert "navigation.py" in (tmp_path / "tick_profile.txt").read_text()
