"""dct preflight's file checks: pass and fail paths, with the line a user sees."""
from __future__ import annotations

import yaml

from runtime.app.preflight.files import check_files
from tests.runtime.app.preflight.helpers import LIMO, SHIPPED_CONFIG, by_name, write_yaml


def test_files_pass_with_the_shipped_limo_and_a_nominal_calibration(nominal_cal):
    c = by_name(check_files(None, nominal_cal, None).checks)
    assert [c[n].status for n in ("robot", "config", "distance_net")] == ["PASS"] * 3
    assert "matches 'limo'" in c["distance_net"].message
    assert c["calibration"].status == "WARN" and "nominal" in c["calibration"].text()


def test_wrong_model_footprint_fails_with_a_clear_line(tmp_path, nominal_cal):
    robot = yaml.safe_load(LIMO.read_text())
    robot["footprint"]["length_m"] = 0.40
    c = by_name(check_files(write_yaml(tmp_path / "big.yaml", robot), None, None).checks)["distance_net"]
    assert c.status == "FAIL" and not c.ok
    assert c.line().startswith("FAIL  distance_net")
    assert "wrong model footprint" in c.message and "0.4" in c.message and "retrain" in c.text()


def test_calibration_for_another_robot_or_camera_fails(tmp_path, nominal_cal):
    cal = yaml.safe_load(nominal_cal.read_text())
    other = write_yaml(tmp_path / "other.yaml", {**cal, "robot": "scout"})
    c = by_name(check_files(None, other, None).checks)["calibration"]
    assert c.status == "FAIL" and "for robot 'scout', not 'limo'" in c.message
    cam = dict(cal["camera"], width_px=1280, height_px=720, cx=639.5, cy=359.5)
    wrong_size = write_yaml(tmp_path / "size.yaml", {**cal, "camera": cam})
    c = by_name(check_files(None, wrong_size, None).checks)["calibration"]
    assert c.status == "FAIL" and "1280x720" in c.message and "640x480" in c.message


def test_calibration_far_from_the_mounts_warns_and_a_missing_one_depends_on_the_mode(tmp_path, nominal_cal):
    cal = yaml.safe_load(nominal_cal.read_text())
    cal["lidar_to_camera"]["xyz_m"] = [0.3, 0.0, 0.0]
    cal["provenance"]["method"] = "checkerboard"
    c = by_name(check_files(None, write_yaml(tmp_path / "far.yaml", cal), None).checks)["calibration"]
    assert c.status == "WARN" and "from the robot description's mounts" in c.message
    # No calibration at all: mode dct projects points into the camera (FAIL: the shipped default
    # mode); all-fixed does not need the camera (WARN).
    assert by_name(check_files(None, None, None).checks)["calibration"].status == "FAIL"
    shipped = yaml.safe_load(SHIPPED_CONFIG.read_text())
    all_fixed = write_yaml(tmp_path / "all_fixed.yaml", {**shipped, "planner": {**shipped["planner"], "mode": "all-fixed"}})
    assert by_name(check_files(None, None, all_fixed).checks)["calibration"].status == "WARN"


def test_an_invalid_config_fails(tmp_path):
    bad = tmp_path / "bad.yaml"
    bad.write_text("loop: {period_s: -1}\n")
    c = by_name(check_files(None, None, bad).checks)["config"]
    assert c.status == "FAIL" and "bad.yaml" in c.message
