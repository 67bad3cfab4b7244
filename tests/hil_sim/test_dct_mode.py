"""Planner mode dct (the default) end to end in HIL: camera at 2 Hz with ground-truth
segmentation, the sim-oracle beside the tick (1.5 s simulated latency), mask memory, warp and
partition in the tick, the MPC on the partition's P_fix only.

It waits for the first answer, then drives at the box the oracle calls movable and pushes it
(point tracking keeps the pushed box movable). These tests pin the pipeline; whole episodes are
in test_episodes.py and the slow campaigns."""
from __future__ import annotations

import numpy as np

from hil_sim.runner import run_episode
from hil_sim.scenario import load_scenario
from runtime.config import load_controller_config


def test_dct_mode_partitions_the_box_as_movable_and_never_touches_a_fixed_object():
    cfg = load_controller_config().with_planner_mode("dct")
    scenario = load_scenario("case2").model_copy(update={"time_limit_s": 3.5})
    movable_points, waited = [], []

    mov_costs = []

    def observe(controller):
        frame = controller.vpp.last_frame
        movable_points.append(0 if frame is None else frame.movable_count)
        waited.append(controller.vpp.answers == 0 and controller.command == (0.0, 0.0))
        mov_costs.extend(np.unique(controller.costs_mov).tolist())

    result = run_episode(scenario, config=cfg, seed=0, observe=observe)
    vpp = result.controller["vpp"]
    assert vpp["requests"] >= 1 and vpp["answers"] >= 1 and vpp["failed_answers"] == 0
    assert not vpp["gave_up_waiting"] and vpp["images_refused"] == 0
    assert max(movable_points) > 100  # the box's points left P_fix once the answer came
    assert sum(waited) >= 20  # ~1.5 s at 20 Hz: no driving before the first answer
    assert result.metrics["fixed_contacts"] == 0
    # P_mov reached the reference path with the box's contact cost, and it chose to push
    # (the belief's expected cost: the sim-oracle's movable_cost 2 at its confidence, the rest
    # heavy or fragile at 10)
    assert len(set(mov_costs)) == 1 and 2.0 < mov_costs[0] < 2.5
    assert result.controller["reference_pushes"] >= 1
    # Moved straight at the box instead of detouring: the pose's x grew, y stayed near the axis.
    x, y, _ = result.controller["pose_odom"]
    assert x > 0.5 and abs(y) < 0.2


def test_the_default_mode_is_dct_with_the_sim_oracle():
    cfg = load_controller_config()
    assert cfg.planner.mode == "dct" and cfg.vpp.backend.kind == "sim-oracle"


def test_all_fixed_mode_has_no_vpp_and_runs_without_a_camera():
    cfg = load_controller_config().with_planner_mode("all-fixed")
    result = run_episode(load_scenario("case1").model_copy(update={"time_limit_s": 1.0}), config=cfg, seed=0)
    assert "vpp" not in result.controller and result.controller["mode"] == "all-fixed"
    assert result.extra["sensor_frames"]["camera"] == 0, result.extra["sensor_frames"]


def test_a_calibrated_camera_reaches_the_vpp_stage_and_its_images_are_taken():
    """With a calibration file's camera (intrinsics 1% off the nominal ones, some distortion),
    the VPP stage projects with the calibration's model and the images reach it carrying it
    (as the ROS conversion does on the robot): none refused, the box still leaves P_fix."""
    import numpy as np

    from calibration.camera_model import CameraModel
    from calibration.robot_description import load_robot_description

    cam = load_robot_description().sensors.camera
    K = cam.nominal_intrinsics() * np.array([[1.01, 1, 1], [1, 1.01, 1], [1, 1, 1]])
    calibrated = CameraModel(K, np.array([-0.02, 0.005, 0.0, 0.0, 0.0]), cam.width_px, cam.height_px)
    cfg = load_controller_config().with_planner_mode("dct")
    scenario = load_scenario("case2").model_copy(update={"time_limit_s": 3.5})
    movable, stage_K = [], []

    def observe(controller):
        frame = controller.vpp.last_frame
        movable.append(0 if frame is None else frame.movable_count)
        stage_K.append(controller.vpp.camera.K)

    result = run_episode(scenario, config=cfg, seed=0, observe=observe, camera_calibration=(calibrated, None))
    vpp = result.controller["vpp"]
    assert vpp["images_refused"] == 0 and vpp["answers"] >= 1
    assert np.array_equal(stage_K[-1], K)
    assert max(movable) > 100
    assert result.metrics["fixed_contacts"] == 0
