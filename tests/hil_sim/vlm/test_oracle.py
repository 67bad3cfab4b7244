"""The sim-oracle on real simulator frames: its table comes from the World, its movable masks
are exactly the movable objects' pixels of a rendered geom segmentation."""
from __future__ import annotations

import numpy as np
import pytest

from calibration.robot_description import load_robot_description
from hil_sim.sensors.camera import SimCamera
from hil_sim.world.scenario import load_scenario
from hil_sim.vlm.oracle import oracle_backend, oracle_request, oracle_table
from hil_sim.world.mujoco_world import World
from models.vlm.runner import BackendRunner
from models.vlm.sim_oracle import SimOracleConfig, SimOracleError

ROBOT = load_robot_description()


def _camera_pose_world(world: World) -> np.ndarray:
    """T_world<-optical (MuJoCo's camera looks along -z with y up)."""
    cid = world.camera_id
    t = np.eye(4)
    t[:3, :3] = world.data.cam_xmat[cid].reshape(3, 3) @ np.diag([1.0, -1.0, -1.0])
    t[:3, 3] = world.data.cam_xpos[cid]
    return t


@pytest.fixture(scope="module", params=["case1", "case2"])
def frame(request):
    return _render(request.param)


def _render(scenario: str):
    world = World(load_scenario(scenario), ROBOT)
    cam = ROBOT.sensors.camera
    camera = SimCamera(world.model, world.data, world.camera_name, cam.width_px, cam.height_px,
                       hidden_geom_groups=world.camera_hidden_geom_groups)
    try:
        image = camera.render_rgb_with_segmentation(world.time_s, kind="geom")
    finally:
        camera.close()
    return world, image


def test_table_names_every_obstacle_and_wall(frame):
    world, _ = frame
    table = oracle_table(world)
    assert sorted(e.name for e in table.values()) == sorted(world.obstacle_names)
    for gid, entry in table.items():
        assert world.obstacle_geom_id(entry.name) == gid
        assert entry.obstacle_class == world.obstacle_class(entry.name)
        assert entry.structure == (entry.name in world.scenario.wall_names())
    with pytest.raises(SimOracleError, match="does not have: ghost"):
        oracle_table(world, costs={"ghost": 1.0})


def test_perfect_oracle_masks_are_exactly_the_movable_pixels(frame):
    world, image = frame
    seg = image.segmentation
    movable_ids = [world.obstacle_geom_id(n) for n in world.obstacle_names if world.obstacle_class(n) == "movable"]
    truth = np.isin(seg, movable_ids)
    assert truth.sum() > 1000  # the box is in view, large
    oracle = oracle_backend(world, SimOracleConfig(precision=1.0, recall=1.0, min_pixels=1), costs={"box": 1.0})
    answer = oracle.query(oracle_request(image, _camera_pose_world(world), "push what you may"))
    assert answer.error is None
    movable = [o for o in answer.objects if o.movable]
    assert [o.label for o in movable] == ["box"] and movable[0].contact_cost == 1.0
    union = np.logical_or.reduce([o.mask for o in movable])
    np.testing.assert_array_equal(union, truth)
    # Every other object in view is reported fixed at cost 10, each with exactly its pixels.
    for o in answer.objects:
        if not o.movable:
            assert o.contact_cost == 10.0
            np.testing.assert_array_equal(o.mask, seg == world.obstacle_geom_id(o.label))
    seen = {world.geom_obstacle_index[g] for g in np.unique(seg) if g >= 0} - {-1}
    assert len(answer.objects) == len(seen)


def test_runner_delivers_the_frame_answer_at_the_default_latency(frame):
    world, image = frame
    runner = BackendRunner(oracle_backend(world))
    runner.submit(oracle_request(image, _camera_pose_world(world)))
    runner.settle(image.stamp_s + 1.5)
    assert runner.poll(image.stamp_s + 1.49) == []
    (answer,) = runner.poll(image.stamp_s + 1.5)
    assert answer.latency_s == 1.5 and any(o.movable for o in answer.objects)


def test_request_needs_segmentation(frame):
    world, image = frame
    from runtime.common.sensor_data import CameraImage

    plain = CameraImage(stamp_s=image.stamp_s, pixels=image.pixels, K=image.K, distortion=image.distortion)
    with pytest.raises(SimOracleError, match="no segmentation"):
        oracle_request(plain, np.eye(4))


def test_heavy_look_alike_is_called_movable_unless_configured():
    world, image = _render("push_30kg")
    request = oracle_request(image, _camera_pose_world(world))
    (crate,) = [o for o in oracle_backend(world).query(request).objects if o.label == "box"]
    assert crate.movable and crate.contact_cost == 2.0  # looks like push_1kg's box
    honest = oracle_backend(world, SimOracleConfig(heavy_looks_movable=False))
    (crate,) = [o for o in honest.query(request).objects if o.label == "box"]
    assert not crate.movable and crate.contact_cost == 10.0
