"""`dct calibrate wheels`: fits a recorded run into the calibration file, atomically, never over an
input or an earlier fit without --force; every input error is one line and exit 2."""
from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest
from click.testing import CliRunner

from calibration.calibration_file import load_calibration, make_calibration, save_calibration
from calibration.cli import calibrate_group

from .wheel_runs import simulate_run

K = np.array([[336.0, 0.0, 319.5], [0.0, 336.0, 239.5], [0.0, 0.0, 1.0]])


def _run(*args):
    return CliRunner().invoke(calibrate_group, ["wheels", *[str(a) for a in args]])


def _one_line_error(r, *fragments, exit_code=2) -> str:
    assert r.exit_code == exit_code, r.output
    assert isinstance(r.exception, SystemExit), repr(r.exception)
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("Error: "), r.stderr
    for f in fragments:
        assert str(f) in lines[0], lines[0]
    return lines[0]


@pytest.fixture
def files(tmp_path):
    run = tmp_path / "run.npz"
    simulate_run(0.525, 0.97, seed=2, source="hil case1").save(run)
    cal = tmp_path / "cal.yaml"
    T = np.eye(4)
    T[:3, 3] = [0.0, 0.05, -0.08]
    save_calibration(make_calibration("limo", K, np.zeros(5), 640, 480, T, method="test"), cal)
    return run, cal


def test_listed_in_the_calibrate_group():
    r = CliRunner().invoke(calibrate_group, ["--help"])
    assert r.exit_code == 0 and "wheels" in r.output
    r = _run("--help")
    assert r.exit_code == 0 and "calibration file is an input too" in " ".join(r.output.split())


def test_fits_and_writes_back_into_a_calibration_without_the_section(files):
    run, cal = files
    before = load_calibration(cal)
    r = _run("--run", run, "--calibration", cal)
    assert r.exit_code == 0, r.output
    after = load_calibration(cal)
    w = after.wheel_odometry
    assert w.effective_track_m == pytest.approx(0.525, rel=0.01) and w.wheel_scale == pytest.approx(0.97, rel=0.01)
    assert w.fit.reference == "icp" and w.fit.source == "hil case1 seed 2" and w.fit.windows == 114
    assert w.fit.window_s == 0.5
    # Everything else of the file is kept.
    assert after.camera == before.camera and after.lidar_to_camera == before.lidar_to_camera
    assert after.provenance == before.provenance and after.robot == "limo"
    out = r.stdout
    assert f"wheel_scale          {w.wheel_scale:.4f}" in out
    assert f"effective_track_m    {w.effective_track_m:.4f} m (yaw factor" in out
    assert "x the geometric 0.175 m; the description says 3" in out
    assert "windows of 0.5 s: 114 used, 6 standstill left out" in out
    assert "mm distance" in out and "deg yaw per window" in out and f"wheel_odometry -> {cal}" in out
    assert sorted(p.name for p in cal.parent.iterdir()) == ["cal.yaml", "run.npz"]  # no temporary file left


def test_an_existing_section_is_replaced_only_with_force(files):
    run, cal = files
    assert _run("--run", run, "--calibration", cal).exit_code == 0
    first = cal.read_bytes()
    _one_line_error(_run("--run", run, "--calibration", cal), "already has a wheel_odometry section", "--force")
    assert cal.read_bytes() == first
    r = _run("--run", run, "--calibration", cal, "--force", "--window-s", "1.0")
    assert r.exit_code == 0, r.output
    assert "(replaces the section fitted" in r.stdout
    assert load_calibration(cal).wheel_odometry.fit.window_s == 1.0


def test_output_leaves_the_calibration_alone(files, tmp_path):
    run, cal = files
    before = cal.read_bytes()
    out = tmp_path / "new.yaml"
    r = _run("--run", run, "--calibration", cal, "--output", out)
    assert r.exit_code == 0, r.output
    assert cal.read_bytes() == before and load_calibration(out).wheel_odometry is not None
    _one_line_error(_run("--run", run, "--calibration", cal, "--output", out), "already exists", "--force")
    assert _run("--run", run, "--calibration", cal, "--output", out, "--force").exit_code == 0
    _one_line_error(_run("--run", run, "--calibration", cal, "--output", cal), "is also an input")
    _one_line_error(_run("--run", run, "--calibration", cal, "--output", run, "--force"), "is also an input")
    _one_line_error(_run("--run", run, "--calibration", cal, "--output", tmp_path / "no" / "x.yaml"), "does not exist")
    assert cal.read_bytes() == before


def test_a_run_that_cannot_determine_the_values_writes_nothing(files, tmp_path):
    _, cal = files
    before = cal.read_bytes()
    straight = tmp_path / "straight.npz"
    simulate_run(schedule=((0.4, 0.0, 5.0), (-0.4, 0.0, 5.0))).save(straight)
    _one_line_error(_run("--run", straight, "--calibration", cal), f"odometry run {straight}", "too little motion",
                    "deg of turning (at least 90 deg)")
    implausible = tmp_path / "implausible.npz"
    simulate_run(0.12, 1.0).save(implausible)
    _one_line_error(_run("--run", implausible, "--calibration", cal), "implausible fit", "effective track 0.1")
    assert cal.read_bytes() == before


def test_bad_inputs_are_one_line_and_exit_2(files, tmp_path):
    run, cal = files
    junk = tmp_path / "junk.npz"
    junk.write_bytes(b"PK\x03\x04 not really a zip")
    _one_line_error(_run("--run", junk, "--calibration", cal), f"odometry run {junk}: cannot be read")
    other = tmp_path / "other.npz"
    simulate_run(robot="scout").save(other)
    _one_line_error(_run("--run", other, "--calibration", cal), "of robot 'scout'", "of 'limo'")
    bad_cal = tmp_path / "bad.yaml"
    bad_cal.write_text("robot: limo\ncamera: {fx: -1}\n")
    _one_line_error(_run("--run", run, "--calibration", bad_cal), f"calibration file {bad_cal}", "camera.fx")
    _one_line_error(_run("--run", run, "--calibration", cal, "--window-s", "-1"), "--window-s", "positive duration")
    _one_line_error(_run("--calibration", cal), "Missing option '--run'")
    _one_line_error(_run("--run", tmp_path / "missing.npz", "--calibration", cal), "does not exist")
    bad_desc = tmp_path / "desc.yaml"
    bad_desc.write_text("name: x\n")
    _one_line_error(_run("--run", run, "--calibration", cal, "--robot-description", bad_desc), "robot description")


def test_the_robot_description_sets_the_geometric_track(files, tmp_path):
    """A description with a 0.12 m track makes the 0.525 m fit implausible (more than 5x)."""
    import yaml

    from calibration.robot_description import load_robot_description

    run, cal = files
    desc = load_robot_description().model_dump(mode="json")
    desc["drive"]["track_m"] = 0.10
    path = tmp_path / "narrow.yaml"
    path.write_text(yaml.safe_dump(desc))
    _one_line_error(_run("--run", run, "--calibration", cal, "--robot-description", path),
                    "outside [0.100, 0.500] m")


def test_dct_entry_point_end_to_end(files):
    run, cal = files
    dct = [sys.executable, "-c", "from runtime.app.cli import main; main()"]
    p = subprocess.run([*dct, "calibrate", "wheels", "--run", str(run), "--calibration", str(cal)],
                       capture_output=True, text=True)
    assert p.returncode == 0, p.stderr
    assert "effective_track_m" in p.stdout and load_calibration(cal).wheel_odometry is not None
    p = subprocess.run([*dct, "calibrate", "wheels", "--run", str(run), "--calibration", str(cal)],
                       capture_output=True, text=True)
    assert p.returncode == 2 and p.stderr.count("\n") == 1 and "already has" in p.stderr
