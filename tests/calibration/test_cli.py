"""`dct calibrate` sub-commands on folders of files, end to end."""
import json
import subprocess
import sys

import cv2
import numpy as np
import yaml
from click.testing import CliRunner

from calibration.calibration_file import load_calibration
from calibration.cli import calibrate_group

from .conftest import PANDAR, render_board_view
from .test_intrinsics_extrinsics import DIST_TRUE, K_TRUE, PATTERN, SQUARE, _poses


def test_cli_module_imports_no_heavy_packages():
    code = ("import sys, calibration.cli; bad = [m for m in ('cv2', 'mujoco', 'torch', 'hil_sim', 'runtime') "
            "if m in sys.modules]; print(bad); sys.exit(1 if bad else 0)")
    assert subprocess.run([sys.executable, "-c", code]).returncode == 0


def test_hil_check_is_listed_lazily():
    result = CliRunner().invoke(calibrate_group, ["--help"])
    assert result.exit_code == 0
    for name in ("intrinsics", "extrinsics", "project", "report", "hil-check", "import-opencalib"):
        assert name in result.output


def test_intrinsics_then_report(tmp_path):
    rng = np.random.default_rng(5)
    folder = tmp_path / "imgs"
    folder.mkdir()
    for i, (rv, t) in enumerate(_poses(10, rng)):
        cv2.imwrite(str(folder / f"{i:02d}.png"), render_board_view(K_TRUE, DIST_TRUE, rv, t, PATTERN, SQUARE))
    cal = tmp_path / "cal.yaml"
    r = CliRunner().invoke(calibrate_group, ["intrinsics", str(folder), "--pattern", "9x6", "--square-m", str(SQUARE),
                                             "--out", str(cal)])
    assert r.exit_code == 0, r.output
    c = load_calibration(cal)
    assert abs(c.camera.fx / K_TRUE[0, 0] - 1) < 0.01 and c.provenance.intrinsics_rms_px < 0.3
    r = CliRunner().invoke(calibrate_group, ["report", str(cal), "--images", str(folder), "--square-m", str(SQUARE)])
    assert r.exit_code == 0, r.output
    assert "mean per-image RMS" in r.output and "not calibrated" in r.output


def test_bad_pattern_and_bad_calibration_file(tmp_path):
    r = CliRunner().invoke(calibrate_group, ["intrinsics", str(tmp_path), "--pattern", "9by6", "--out", "x.yaml"])
    assert r.exit_code != 0 and "9x6" in r.output
    bad = tmp_path / "bad.yaml"
    bad.write_text(yaml.safe_dump({"robot": "x", "camera": {"fx": -1}}))
    r = CliRunner().invoke(calibrate_group, ["report", str(bad)])
    assert r.exit_code != 0 and "camera.fx" in r.output


def test_import_opencalib_and_project_real_data(tmp_path):
    cal = tmp_path / "pandar.yaml"
    r = CliRunner().invoke(calibrate_group, [
        "import-opencalib", str(PANDAR / "center_camera-intrinsic.json"),
        str(PANDAR / "top_center_lidar-to-center_camera-extrinsic.json"), "--width", "1920", "--height", "1200",
        "--out", str(cal)])
    assert r.exit_code == 0, r.output
    out, stats = tmp_path / "overlay.png", tmp_path / "stats.json"
    r = CliRunner().invoke(calibrate_group, ["project", str(PANDAR / "0.pcd"), str(PANDAR / "0.png"), "--calibration",
                                             str(cal), "--out", str(out), "--json", str(stats)])
    assert r.exit_code == 0, r.output
    s = json.loads(stats.read_text())
    assert abs(s["in_image"] - 9954) <= 100
    assert cv2.imread(str(out)).shape == (1200, 1920, 3)
