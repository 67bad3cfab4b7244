"""Glue between the simulator and the `sim-oracle` backend (models.vlm.sim_oracle).

The oracle answers from a segmentation image and a table id -> (object, class, cost); this
module builds that table from a World, so models/ never imports the simulator. The ids are
MuJoCo geom ids: render the camera with `kind="geom"` (SimCamera.render_rgb_with_segmentation's
default, SensorRigConfig.camera_segmentation). Body ids would not do: every wall and fixed
obstacle is a geom of the one world body.

Each scenario obstacle is one geom named after it (hil_sim.world.model_spec.build_spec); walls are fixed
and marked as structure (the precision knob does not call a wall movable). The floor and the
robot are not in the table: the oracle ignores their pixels. A curtain is one geom per slat:
every slat's id names the curtain.

Classes and costs. The oracle knows fixed, movable and heavy; the scenario's other classes
answer as a VLM would see them:
* fragile: `movable` when it is a free body (a vase can be moved, at a cost), `fixed` when it
  is static; its cost (9 unless the file says) tells the planner never to touch it;
* deformable (a curtain): `movable` and `deformable`, cost 1 unless the file says;
* person: `fixed`, cost 10, whatever the file says (never pushed).
Costs: the scenario's `contact_cost` where the file gives one, the class default for the new
classes (fragile, deformable, person), else the oracle's own defaults (SimOracleConfig:
fixed_cost, movable_cost). `costs` (name -> 0..10) overrides them.
"""
from __future__ import annotations

from collections.abc import Mapping

import numpy as np

from hil_sim.world.mujoco_world import World
from models.vlm.interface import VlmRequest
from models.vlm.sim_oracle import OracleEntry, SimOracleBackend, SimOracleConfig, SimOracleError
from runtime.common.sensor_data import CameraImage


def oracle_table(world: World, costs: Mapping[str, float] | None = None) -> dict[int, OracleEntry]:
    """geom id -> OracleEntry for every obstacle and wall of the world's scenario."""
    costs = dict(costs or {})
    unknown = sorted(set(costs) - set(world.obstacle_names))
    if unknown:
        raise SimOracleError(f"oracle costs name objects the scenario does not have: {', '.join(unknown)}; "
                             f"known: {', '.join(world.obstacle_names)}")
    walls = set(world.scenario.wall_names())
    scenario_costs = {o.name: (o.cost if (o.contact_cost is not None or o.obstacle_class not in _ORACLE_CLASSES)
                               else None) for o in world.scenario.obstacles}
    free = {o.name for o in world.scenario.obstacles if o.is_free_body}
    table: dict[int, OracleEntry] = {}
    for name in world.obstacle_names:
        cls = oracle_class(world.obstacle_class(name), name in free)
        cost = costs.get(name, scenario_costs.get(name))
        if world.obstacle_class(name) == "person":
            cost = 10.0  # never pushed, whatever a table says
        entry = OracleEntry(name=name, obstacle_class=cls, contact_cost=cost, structure=name in walls,  # type: ignore[arg-type]
                            deformable=world.obstacle_class(name) == "deformable")
        for gid in world.obstacle_geom_ids(name):
            table[int(gid)] = entry
    return table


_ORACLE_CLASSES = ("fixed", "movable", "heavy")


def oracle_class(scenario_class: str, free_body: bool) -> str:
    """The oracle's class (fixed, movable, heavy) of a scenario class (module docstring)."""
    if scenario_class in _ORACLE_CLASSES:
        return scenario_class
    if scenario_class == "fragile":
        return "movable" if free_body else "fixed"
    if scenario_class == "deformable":
        return "movable"
    if scenario_class == "person":
        return "fixed"
    raise SimOracleError(f"oracle_class: unknown scenario class {scenario_class!r}")


def oracle_backend(world: World, config: SimOracleConfig | None = None,
                   costs: Mapping[str, float] | None = None) -> SimOracleBackend:
    """The sim-oracle for this world."""
    return SimOracleBackend(oracle_table(world, costs), config)


def oracle_request(image: CameraImage, camera_pose_odom: np.ndarray, prompt: str = "") -> VlmRequest:
    """A request from a simulated camera image that carries its segmentation (kind 'geom')."""
    if image.segmentation is None:
        raise SimOracleError("oracle_request: the camera image has no segmentation; render it with "
                             "render_rgb_with_segmentation (or SensorRigConfig.camera_segmentation)")
    return VlmRequest(image=image.pixels, stamp_s=image.stamp_s, camera_pose_odom=np.asarray(camera_pose_odom, float),
                      prompt=prompt, segmentation=image.segmentation)


__all__ = ["oracle_backend", "oracle_class", "oracle_request", "oracle_table"]
