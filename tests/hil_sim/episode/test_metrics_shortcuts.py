"""The metrics' per-step shortcuts give what the full computation gives: the contact scan (a
Python loop for few contacts, numpy for many) and the clearance pairs pruned before
mj_geomDistance (a pruned pair is never one within CLEARANCE_MAX_M)."""
from __future__ import annotations

import math

import mujoco
import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from hil_sim.episode import metrics as metrics_module
from hil_sim.episode.metrics import CLEARANCE_MAX_M, EpisodeMetrics
from hil_sim.world.mujoco_world import World
from hil_sim.world.scenario import load_scenario
from tests.firmware_bridge.test_firmware_emulator import ROBOT

_WORLDS: dict[str, World] = {}


def _world(name: str) -> World:
    if name not in _WORLDS:
        _WORLDS[name] = World(load_scenario(name), ROBOT)
    return _WORLDS[name]


class _Contacts:
    """Stands in for MjData in the contact scan: ncon and contact.geom."""

    def __init__(self, geoms: np.ndarray) -> None:
        self.ncon = len(geoms)
        self.contact = type("C", (), {"geom": geoms})()


def _reference_touching(m: EpisodeMetrics, geoms: np.ndarray) -> np.ndarray:
    """The scan as it was written first: four lookups and a concatenation."""
    touching = np.zeros(len(m.names), dtype=bool)
    if len(geoms):
        g1, g2 = geoms[:, 0], geoms[:, 1]
        r1, r2 = m._is_robot_geom[g1], m._is_robot_geom[g2]
        o1, o2 = m._geom_obstacle[g1], m._geom_obstacle[g2]
        touching[np.concatenate([o2[r1 & (o2 >= 0)], o1[r2 & (o1 >= 0)]])] = True
    return touching


@settings(max_examples=150, deadline=None)
@given(st.data())
def test_contact_scan_finds_the_touched_obstacles_for_few_and_many_contacts(data):
    world = _world("push_1kg")
    m = EpisodeMetrics(world)
    ngeom = world.model.ngeom
    n = data.draw(st.sampled_from([0, 1, 5, 40, metrics_module._CONTACT_LOOP_MAX + 1, 150]))
    geoms = np.array(data.draw(st.lists(st.tuples(st.integers(0, ngeom - 1), st.integers(0, ngeom - 1)),
                                        min_size=n, max_size=n)), dtype=np.int32).reshape(-1, 2)
    got = np.zeros(len(m.names), dtype=bool)
    hit = m._touched_obstacles(_Contacts(geoms))
    if hit is not None:
        got[hit] = True
    assert np.array_equal(got, _reference_touching(m, geoms))


@settings(max_examples=60, deadline=None)
@given(scene=st.sampled_from(["case1", "corridor_boxes", "push_1kg"]), x=st.floats(-3.0, 3.0),
       y=st.floats(-2.5, 2.5), yaw=st.floats(-math.pi, math.pi))
def test_pruned_clearance_pairs_are_never_within_the_clearance_range(scene, x, y, yaw):
    world = _world(scene)
    m = EpisodeMetrics(world)
    d, model = world.data, world.model
    q = d.qpos[world._base_qpos:world._base_qpos + 7]
    q[0], q[1] = x, y
    q[3:7] = [math.cos(yaw / 2), 0.0, 0.0, math.sin(yaw / 2)]
    mujoco.mj_forward(model, d)
    near = set(m._clearance_prune.near(d))
    for k, (_, robot_geom, obstacle_geom) in enumerate(m._clearance_pairs):
        dist = mujoco.mj_geomDistance(model, d, robot_geom, obstacle_geom, CLEARANCE_MAX_M, None)
        if dist < CLEARANCE_MAX_M:
            assert k in near, (scene, x, y, yaw, robot_geom, obstacle_geom, dist)
    world.reset(0)


def test_a_nan_position_is_never_pruned():
    world = World(load_scenario("case1"), ROBOT)
    m = EpisodeMetrics(world)
    world.data.geom_xpos[:] = np.nan
    assert m._clearance_prune.near(world.data) == list(range(len(m._clearance_pairs)))


def test_the_reported_clearance_is_capped_for_an_obstacle_never_near():
    world = World(load_scenario("case1"), ROBOT)
    m = EpisodeMetrics(world)
    for _ in range(10):
        world.step()
        m.update(world)
    out = m.to_dict(goal_reached=False, navigation_time_s=0.01)
    far = [o for o in out["obstacles"] if o["min_clearance_m"] == CLEARANCE_MAX_M]
    assert far and all(math.isinf(m.min_clearance_m[m.names.index(o["name"])]) for o in far)
    assert out["min_fixed_clearance_m"] <= CLEARANCE_MAX_M
