"""runtime.app.resume and the odometry's side of it: a restarted controller continues the odometry
frame from the saved pose and the base's odometers, or says why it starts a new one."""
from __future__ import annotations

import json
import math
import time

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from runtime.app.resume import FORMAT, ResumeWriter, load_resume
from runtime.common.events import EventLog
from runtime.common.geometry import Pose2D
from runtime.odometry.stage import OdometryConfig, OdometryStage

MOUNT = np.eye(4)


def _state(**kw) -> dict:
    return {"format": FORMAT, "written_at_s": time.time(), "pose": [1.0, 2.0, 0.5], "wheels_m": [10.0, 10.2],
            "goal": [4.0, 0.0, 0.0], "goal_reached": False, "pid": 123, **kw}


def test_a_fresh_saved_state_is_taken_up_and_anything_else_says_why_not(tmp_path):
    p = tmp_path / "resume.json"
    r = load_resume(p)
    assert r.state is None and "no saved state" in r.why and "a new odometry frame" in r.line()
    p.write_text(json.dumps(_state()))
    r = load_resume(p)
    assert r.state is not None and r.state.goal == (4.0, 0.0, 0.0) and "continuing" in r.line()
    p.write_text(json.dumps(_state(written_at_s=time.time() - 100.0)))
    assert "more than --resume-max-age 60 s" in load_resume(p).why
    p.write_text(json.dumps(_state(written_at_s=time.time() + 30.0)))
    assert "in the future" in load_resume(p).why
    p.write_text(json.dumps(_state(pose=[1.0, float("nan"), 0.0])))
    assert load_resume(p).state is None
    p.write_text(json.dumps({**_state(), "format": "other"}))
    assert "not a saved state of this controller" in load_resume(p).why


@settings(max_examples=200, deadline=None)
@given(st.binary(max_size=300))
def test_any_bytes_in_the_file_give_a_state_or_a_reason_never_an_exception(tmp_path_factory, raw):
    p = tmp_path_factory.mktemp("r") / "resume.json"
    p.write_bytes(raw)
    r = load_resume(p)
    assert r.state is None and r.why


def test_the_writer_replaces_the_file_whole_and_only_with_a_wheel_reading(tmp_path):
    p = tmp_path / "resume.json"
    w = ResumeWriter(p, every_s=0.02)
    w.start()
    try:
        w.offer((0.0, 0.0, 0.0), None, (1.0, 0.0, 0.0), False)  # no odometer reading yet: nothing to save
        time.sleep(0.1)
        assert not p.exists()
        for k in range(20):
            w.offer((0.1 * k, 0.0, 0.0), (0.1 * k, 0.1 * k), (1.0, 0.0, 0.0), k == 19)
            time.sleep(0.01)
    finally:
        w.close()
    r = load_resume(p)
    assert r.state is not None and r.state.pose[0] == pytest.approx(1.9) and r.state.goal_reached and w.writes >= 2
    assert [f.name for f in tmp_path.iterdir()] == ["resume.json"]  # no temporary file left


def _stage() -> OdometryStage:
    stage = OdometryStage(OdometryConfig(source="wheels_imu"), 0.175, 1.0, MOUNT, lockstep=True, events=EventLog())
    return stage


def test_the_odometry_continues_from_the_saved_pose_plus_what_the_wheels_did_since():
    stage = _stage()
    saved = Pose2D(1.0, 2.0, math.pi / 2)
    stage.resume_from(saved, (10.0, 10.0), max_step_m=1.0)
    pose = stage.update(0.0, None, (), None)  # no wheel reading yet: waits for one
    assert stage.resume_outcome is None
    pose = stage.update(0.05, (10.3, 10.3), (), None)  # rolled 0.3 m straight on while the controller was down
    assert "continued" in stage.resume_outcome
    assert np.allclose([pose.x_m, pose.y_m, pose.yaw_rad], [1.0, 2.3, math.pi / 2], atol=1e-9)
    pose = stage.update(0.10, (10.4, 10.4), (), None)  # and drives on in the same frame
    assert np.allclose([pose.x_m, pose.y_m], [1.0, 2.4], atol=1e-9)


def test_odometers_that_jumped_further_than_the_base_could_drive_give_a_new_frame():
    stage = _stage()
    stage.resume_from(Pose2D(1.0, 2.0, 0.0), (10.0, 10.0), max_step_m=1.0)
    pose = stage.update(0.05, (0.02, 0.01), (), None)  # a rebooted base counts from zero
    assert "a new frame" in stage.resume_outcome and "rebooted" in stage.resume_outcome
    assert np.allclose([pose.x_m, pose.y_m, pose.yaw_rad], 0.0)
