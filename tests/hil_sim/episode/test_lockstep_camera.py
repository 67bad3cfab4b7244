"""The lockstep camera: what rig a dct episode gets, unless the caller's rig config sets its own."""
from __future__ import annotations

from calibration.robot_description import load_robot_description
from hil_sim.episode.faults import FaultInjector
from hil_sim.episode.lockstep import CAMERA_LATENCY_S, DCT_CAMERA_RATE_HZ, _sensor_rig
from hil_sim.world.mujoco_world import World
from hil_sim.world.scenario import load_scenario
from hil_sim.world.sensor_rig import CameraThread, SensorRigConfig
from runtime.config.loading import load_controller_config
from runtime.io.sensor_inbox import SensorInbox

ROBOT = load_robot_description()
CONFIG = load_controller_config().with_planner_mode("dct")


def _rig(sensors):
    world = World(load_scenario("case1"), ROBOT)
    injector = FaultInjector((), None, SensorInbox(), start_s=world.time_s, far_m=10.0)
    return _sensor_rig(world, ROBOT, CONFIG, injector, sensors, 0, None)


def test_a_dct_episode_renders_beside_the_physics_and_delivers_after_the_camera_latency():
    for sensors in (True, SensorRigConfig(seed=0, lidar_enabled=False)):
        rig = _rig(sensors)
        try:
            c = rig.config
            assert c.camera_rate_hz == DCT_CAMERA_RATE_HZ and c.camera_segmentation
            assert c.camera_async and c.camera_latency_s == CAMERA_LATENCY_S > 0
            assert not c.camera_antialias  # the sim-oracle reads the segmentation, not the RGB
            assert isinstance(rig.camera, CameraThread)
        finally:
            rig.close()


def test_a_rig_config_that_sets_its_camera_keeps_it():
    rig = _rig(SensorRigConfig(seed=0, camera_rate_hz=5.0, lidar_enabled=False))
    try:
        c = rig.config
        assert c.camera_rate_hz == 5.0 and c.camera_segmentation
        assert not c.camera_async and c.camera_latency_s == 0.0
        assert not isinstance(rig.camera, CameraThread)
    finally:
        rig.close()


def test_the_tick_benchmark_renders_between_ticks_with_the_same_latency():
    """`dct bench tick` times the tick: its camera renders inline (no render thread in the
    controller's process), its images reach the controller as in `dct hil run`."""
    from hil_sim.bench.tick import inline_sensors

    rig = _rig(inline_sensors(SensorRigConfig(seed=0, lidar_enabled=False)))
    try:
        c = rig.config
        assert c.camera_rate_hz == DCT_CAMERA_RATE_HZ and c.camera_segmentation
        assert not c.camera_async and c.camera_latency_s == CAMERA_LATENCY_S
        assert not isinstance(rig.camera, CameraThread)
    finally:
        rig.close()


def test_a_threaded_camera_without_latency_is_refused_in_lockstep():
    """Handed over when its render is done, an image would reach the controller at a wall-clock
    moment: the same seed would not give the same run."""
    import pytest

    with pytest.raises(ValueError, match="camera_latency_s > 0"):
        _rig(SensorRigConfig(seed=0, camera_async=True, lidar_enabled=False))
