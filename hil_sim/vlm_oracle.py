"""Glue between the simulator and the `sim-oracle` backend (models.vlm.sim_oracle).

The oracle answers from a segmentation image and a table id -> (object, class, cost); this
module builds that table from a World, so models/ never imports the simulator. The ids are
MuJoCo geom ids: render the camera with `kind="geom"` (SimCamera.render_rgb_with_segmentation's
default, SensorRigConfig.camera_segmentation). Body ids would not do: every wall and fixed
obstacle is a geom of the one world body.

Each scenario obstacle is one geom named after it (hil_sim.world.build_spec); walls are fixed
and marked as structure (the precision knob does not call a wall movable). The floor and the
robot are not in the table: the oracle ignores their pixels. Scenarios carry no contact cost;
`costs` (name -> 0..10) gives some, the rest get the oracle's defaults (SimOracleConfig).
"""
from __future__ import annotations

from collections.abc import Mapping

import numpy as np

from hil_sim.world import World
from models.vlm.interface import VlmRequest
from models.vlm.sim_oracle import OracleEntry, SimOracleBackend, SimOracleConfig, SimOracleError
from runtime.sensor_data import CameraImage


def oracle_table(world: World, costs: Mapping[str, float] | None = None) -> dict[int, OracleEntry]:
    """geom id -> OracleEntry for every obstacle and wall of the world's scenario."""
    costs = dict(costs or {})
    unknown = sorted(set(costs) - set(world.obstacle_names))
    if unknown:
        raise SimOracleError(f"oracle costs name objects the scenario does not have: {', '.join(unknown)}; "
                             f"known: {', '.join(world.obstacle_names)}")
    walls = set(world.scenario.wall_names())
    table: dict[int, OracleEntry] = {}
    for name in world.obstacle_names:
        cls = world.obstacle_class(name)  # fixed / movable / heavy: the oracle's classes
        table[int(world.obstacle_geom_id(name))] = OracleEntry(name=name, obstacle_class=cls,  # type: ignore[arg-type]
                                                               contact_cost=costs.get(name), structure=name in walls)
    return table


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


__all__ = ["oracle_backend", "oracle_request", "oracle_table"]
