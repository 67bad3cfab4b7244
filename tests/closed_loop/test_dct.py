"""Planner mode dct (the default) end to end in HIL: camera at 2 Hz with ground-truth
segmentation, the sim-oracle beside the tick (1.5 s simulated latency), mask memory, warp and
partition in the tick, the MPC on the partition's P_fix only.

Before the first answer it drives where its path touches nothing (case1's detour) and waits where
the way leads through something (case2's box); then it drives at the box the oracle calls movable
and pushes it (point tracking keeps the pushed box movable). These tests pin the pipeline; whole episodes are
in test_episodes.py and the slow campaigns."""
from __future__ import annotations

import numpy as np

from hil_sim.episode.lockstep import run_episode
from hil_sim.world.scenario import load_scenario
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
        mov_costs.extend(np.unique(controller.perception.costs_mov).tolist())

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


def test_before_the_first_answer_the_robot_drives_a_path_that_touches_nothing():
    """case1: the box sits in open space. With every point P_fix and of unknown touchability the
    reference goes round it, and the robot is on its way before the VLM has answered."""
    cfg = load_controller_config().with_planner_mode("dct")
    scenario = load_scenario("case1").model_copy(update={"time_limit_s": 1.4})
    moved_before_answer = []

    def observe(controller):
        if controller.vpp.answers == 0:
            moved_before_answer.append(controller.pose.x_m)

    result = run_episode(scenario, config=cfg, seed=0, observe=observe)
    assert result.controller["vpp"]["answers"] == 0  # the first answer comes at 1.5 s
    assert max(moved_before_answer) > 0.5 and result.metrics["fixed_contacts"] == 0


def test_goal_when_ready_gives_the_goal_after_the_first_answer_and_starts_the_clock_there():
    cfg = load_controller_config().with_planner_mode("dct")
    scenario = load_scenario("case2").model_copy(update={"time_limit_s": 6.0})
    result = run_episode(scenario, config=cfg, seed=0, goal_when_ready=True)
    m = result.metrics
    assert m["navigation_clock"] == "goal-when-ready"
    assert 1.5 <= m["standby_s"] <= 1.8  # the start-up sequence and the sim-oracle's 1.5 s
    assert m["events"][0]["event"] == "goal" and m["events"][0]["t_s"] == 0.0
    assert m["success"] and m["fixed_contacts"] == 0
    assert m["navigation_time_s"] < 4.0 and m["sim_time_s"] > m["navigation_time_s"] + m["standby_s"] - 1e-9
