"""A robot variant in the simulator: rendered with its true camera, its sensors at their true mounts."""
from __future__ import annotations

import numpy as np
import pytest
import yaml

from calibration.robot_description import load_robot_description
from hil_sim.world.robot_variant import resolve_variant

mujoco = pytest.importorskip("mujoco")

ROBOT = load_robot_description()
#: Points in the optical frame (m): the centre, the middle of the image and near its corners.
PROBES = ([0.0, 0.0, 1.0], [0.25, -0.15, 1.2], [-0.3, 0.2, 1.0], [-0.55, -0.38, 1.0], [0.6, 0.4, 1.0])


@pytest.fixture(scope="module")
def pincushion(tmp_path_factory):
    path = tmp_path_factory.mktemp("variant") / "pincushion.yaml"
    path.write_text(yaml.safe_dump({"camera": {"focal_scale": [0.975, 0.98], "principal_offset_px": [-9.0, 8.0],
                                               "distortion": [0.09, 0.12, -0.002, 0.002, 0.03]}}))
    return resolve_variant(str(path), ROBOT)


def _probe_centroids(variant):
    """(rendered probe centroids, where the variant's true camera projects them, where the nominal
    camera would): pixels, one row per PROBES point."""
    from hil_sim.eval.calibration_check import build_scene, probe_offsets

    scene = build_scene(ROBOT, variant)
    truth, _ = scene.camera_model().project(np.array(PROBES))
    nominal, _ = resolve_variant("nominal", ROBOT).true_camera().project(np.array(PROBES))
    return truth + probe_offsets(scene, points_cam=PROBES), truth, nominal


@pytest.mark.parametrize("which", ["seed 7", "pincushion"])
def test_a_known_point_renders_where_the_true_camera_projects_it(which, pincushion):
    """Probe spheres at known 3-D points render (centroid) within 1 px of the variant's true K and
    distortion, and visibly away from where the nominal camera puts them."""
    variant = resolve_variant(7, ROBOT) if which == "seed 7" else pincushion
    rendered, truth, nominal = _probe_centroids(variant)
    assert np.abs(rendered - truth).max() < 1.0, rendered - truth
    moved = np.linalg.norm(rendered - nominal, axis=1)
    assert moved.max() > 8.0, moved  # near the corners the lens and the intrinsics move them most


def test_the_nominal_variant_renders_the_description_pinhole():
    rendered, truth, nominal = _probe_centroids(resolve_variant("nominal", ROBOT))
    assert np.allclose(truth, nominal) and np.abs(rendered - truth).max() < 0.3


@pytest.fixture(scope="module")
def variant_world():
    from hil_sim.world.mujoco_world import World
    from hil_sim.world.scenario import load_scenario

    variant = resolve_variant(7, ROBOT)
    return variant, World(load_scenario("case1"), ROBOT, variant=variant)


def test_the_world_puts_the_sensors_at_the_true_mounts(variant_world):
    variant, world = variant_world
    assert np.allclose(world.lidar_mount.transform(), variant.true_lidar_mount())
    base = world.data.xpos[world.robot_body_id], world.data.xmat[world.robot_body_id].reshape(3, 3)
    cam = world.data.cam_xpos[world.camera_id], world.data.cam_xmat[world.camera_id].reshape(3, 3)
    T_true = variant.true_camera_mount()
    assert np.allclose(base[1].T @ (cam[0] - base[0]), T_true[:3, 3], atol=1e-6)
    R_optical = base[1].T @ cam[1] @ np.diag([1.0, -1.0, -1.0])  # MuJoCo's camera looks along -z, y up
    assert np.allclose(R_optical, T_true[:3, :3], atol=1e-6)
    assert world.robot is variant.robot and world.robot_variant is variant


def test_the_sensor_rig_images_carry_the_true_camera(variant_world):
    """The rig's camera renders through the lens; the images (to the inbox without a calibration, and
    to the listeners always) carry the true K and distortion, as a camera driver's camera_info."""
    from hil_sim.world.sensor_rig import SensorRig, SensorRigConfig
    from runtime.io.sensor_inbox import SensorInbox

    variant, world = variant_world
    inbox = SensorInbox()
    rig = SensorRig(world, ROBOT, inbox, SensorRigConfig(lidar_enabled=False, imu_enabled=False, camera_rate_hz=10.0,
                                                         camera_segmentation=True))
    heard = []
    rig.listeners.append(heard.append)
    try:
        rig.step(world.time_s)
    finally:
        rig.close()
    image = inbox.take().image
    truth = variant.true_camera()
    for img in (image, heard[0]):
        assert np.allclose(img.K, truth.K) and np.allclose(img.distortion, truth.dist)
        assert img.pixels.shape == (480, 640, 3) and img.segmentation.shape == (480, 640)


def test_a_calibration_given_to_the_rig_is_what_the_inbox_images_carry(variant_world):
    from hil_sim.world.sensor_rig import SensorRig, SensorRigConfig
    from runtime.io.sensor_inbox import SensorInbox

    variant, world = variant_world
    nominal_K = ROBOT.sensors.camera.nominal_intrinsics()
    inbox = SensorInbox()
    rig = SensorRig(world, ROBOT, inbox, SensorRigConfig(lidar_enabled=False, imu_enabled=False, camera_rate_hz=10.0),
                    intrinsics=(nominal_K, np.zeros(5)))
    heard = []
    rig.listeners.append(heard.append)
    try:
        rig.step(world.time_s)
    finally:
        rig.close()
    assert np.allclose(inbox.take().image.K, nominal_K)
    assert np.allclose(heard[0].K, variant.true_camera().K)


def test_an_episode_reports_the_variant_it_ran(tmp_path):
    """The episode JSON's robot_variant section: the scenario's variant, its departures and truth."""
    from hil_sim.episode.lockstep import run_episode
    from hil_sim.world.scenario import load_scenario
    from runtime.config import load_controller_config

    sc = load_scenario("case1").model_copy(update={"time_limit_s": 0.3, "robot_variant": 11})
    result = run_episode(sc, robot=ROBOT, config=load_controller_config().with_planner_mode("pure-pursuit"), seed=0)
    section = result.metrics["robot_variant"]
    assert section == resolve_variant(11, ROBOT).to_dict()
    assert section["spec"] == "11" and section["source"] == "seed"
    assert "robot_variant" not in run_episode(sc.model_copy(update={"robot_variant": None}), robot=ROBOT,
                                              config=load_controller_config().with_planner_mode("pure-pursuit"),
                                              seed=0).metrics


def test_a_variant_of_another_description_is_refused():
    from hil_sim.world.model_spec import WorldError
    from hil_sim.world.mujoco_world import World
    from hil_sim.world.scenario import load_scenario

    heavier = ROBOT.model_copy(update={"mass_kg": ROBOT.mass_kg + 1.0})
    with pytest.raises(WorldError, match="another description"):
        World(load_scenario("case1"), heavier, variant=resolve_variant(7, ROBOT))
