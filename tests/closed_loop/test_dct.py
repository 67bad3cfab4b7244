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
    assert result.metrics["partition_fallback"] is None and result.controller["calibration"]["mismatch"] is None
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


def _calibration(K, dist, lidar_rpy_deg=None):
    """A calibration of the shipped LIMO (as calibration.sensor_calibration builds it from a file
    named my_robot.yaml) with this camera and, when given, the lidar mount rotated."""
    from calibration.calibration_file import CalibrationFile
    from calibration.robot_description import load_robot_description
    from calibration.sensor_calibration import sensor_calibration

    robot = load_robot_description()
    data = {"robot": "limo", "provenance": {"date": "2025-01-01T00:00:00", "method": "test"},
            "camera": {"width_px": 640, "height_px": 480, "fx": float(K[0, 0]), "fy": float(K[1, 1]),
                       "cx": float(K[0, 2]), "cy": float(K[1, 2]), "distortion": [float(d) for d in dist]}}
    if lidar_rpy_deg is not None:
        data["lidar_mount"] = {"xyz_m": list(robot.sensors.lidar.mount.xyz_m), "rpy_deg": list(lidar_rpy_deg)}
    return sensor_calibration(robot, CalibrationFile.model_validate(data), "my_robot.yaml")


def test_a_calibrated_camera_reaches_the_vpp_stage_and_its_images_are_taken():
    """With a calibration file's camera (within the check's tolerances of the simulated camera:
    intrinsics 0.3% off, a little distortion), the VPP stage projects with the calibration's
    model and the images reach it carrying it (as the ROS conversion does on the robot): none
    refused, no mismatch, the box still leaves P_fix."""
    from calibration.robot_description import load_robot_description

    cam = load_robot_description().sensors.camera
    K = cam.nominal_intrinsics() * np.array([[1.003, 1, 1], [1, 1.003, 1], [1, 1, 1]])
    calibrated = _calibration(K, [-0.002, 0.0, 0.0, 0.0, 0.0])
    cfg = load_controller_config().with_planner_mode("dct")
    scenario = load_scenario("case2").model_copy(update={"time_limit_s": 3.5})
    movable, stage_K = [], []

    def observe(controller):
        frame = controller.vpp.last_frame
        movable.append(0 if frame is None else frame.movable_count)
        stage_K.append(controller.vpp.camera.K)

    result = run_episode(scenario, config=cfg, seed=0, observe=observe, sensor_calibration=calibrated)
    vpp = result.controller["vpp"]
    assert vpp["images_refused"] == 0 and vpp["answers"] >= 1
    assert np.array_equal(stage_K[-1], K)
    assert max(movable) > 100
    assert result.metrics["fixed_contacts"] == 0
    assert result.metrics["partition_fallback"] is None
    assert result.controller["calibration"]["intrinsics"] == "ok"


def test_a_camera_calibration_off_the_simulated_camera_is_named_and_the_robot_drives_all_fixed():
    """The file's fx and fy 3% off the simulated camera's (which reports its true intrinsics as a
    driver's CameraInfo): the first image's CameraInfo names the file's field, the partition is
    all-fixed from then on (the box stays an obstacle) and the robot drives round it."""
    from calibration.robot_description import load_robot_description

    K = load_robot_description().sensors.camera.nominal_intrinsics() * np.array([[1.03, 1, 1], [1, 1.03, 1], [1, 1, 1]])
    cfg = load_controller_config().with_planner_mode("dct")
    scenario = load_scenario("case1").model_copy(update={"time_limit_s": 3.0})
    result = run_episode(scenario, config=cfg, seed=0, sensor_calibration=_calibration(K, [0.0] * 5))
    fallback = result.metrics["partition_fallback"]
    assert fallback is not None and fallback["configured"] == "vpp" and fallback["since_s"] < 0.6
    assert fallback["reason"].startswith(f"camera intrinsics: my_robot.yaml camera.fx: {K[0, 0]:.1f}, the camera "
                                         f"reports {K[0, 0] / 1.03:.1f} (-2.9%, tolerance 1%); my_robot.yaml camera.fy")
    said = [e["event"] for e in result.metrics["events"]]
    assert "calibration_mismatch" in said and "partition_fallback" in said
    assert "vpp" in result.controller and result.controller["vpp"]["answers"] == 0  # never asked again
    x, _, _ = result.controller["pose_odom"]
    assert x > 0.5 and result.metrics["fixed_contacts"] == 0 and result.metrics["movable_contacts"] == 0


def test_a_lidar_mount_off_the_simulated_one_is_named_from_the_floor():
    """The file's lidar mount pitched 2 deg down; the simulated lidar is level: the floor seen
    through the file's mount rises 2 deg ahead, three fits a second apart say so."""
    from calibration.robot_description import load_robot_description

    K = load_robot_description().sensors.camera.nominal_intrinsics()
    cfg = load_controller_config().with_planner_mode("dct")
    scenario = load_scenario("case1").model_copy(update={"time_limit_s": 3.0})
    result = run_episode(scenario, config=cfg, seed=0,
                         sensor_calibration=_calibration(K, [0.0] * 5, lidar_rpy_deg=(0.0, -2.0, 0.0)))
    fallback = result.metrics["partition_fallback"]
    assert fallback is not None, result.controller["calibration"]
    assert fallback["reason"].startswith("lidar mount: my_robot.yaml lidar_mount: the floor seen through it is "
                                         "tilted 2.0 deg (rising +2.0 deg towards +x")
    assert result.controller["calibration"]["intrinsics"] == "ok"
    assert result.metrics["fixed_contacts"] == 0
    # (3 s is short of the goal) the failure names the mismatch beside its own reason: the floor seen
    # 2 deg tilted rises into the obstacle band ahead and may block the robot
    assert result.metrics["failure_reason"].endswith(f"(after a calibration mismatch: {fallback['reason']})")


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
    # the nominal robot with its nominal calibration: checked (camera info, the open room's floor), no alarm
    cal = result.controller["calibration"]
    assert cal["intrinsics"] == "ok" and cal["floor_fits"] >= 1 and cal["mismatch"] is None
    assert result.metrics["partition_fallback"] is None


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
