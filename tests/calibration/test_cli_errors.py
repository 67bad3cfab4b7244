"""`dct calibrate`: input errors are one line and a non-zero exit; outputs are checked first, written
atomically, never over an input, and not at all when the calibration misses its quality target."""
import json
import shutil
import subprocess
import sys

import cv2
import numpy as np
import pytest
import yaml
from click.testing import CliRunner

from calibration import extrinsics as extrinsics_module
from calibration import intrinsics as intrinsics_module
from calibration.calibration_file import load_calibration, make_calibration, save_calibration
from calibration.cli import calibrate_group
from calibration.pointcloud_write import write_pcd

from .conftest import (CAPTURE_BORDER_M, CAPTURE_SQUARE_M, PANDAR, capture_calibration, capture_T_cam_lidar,
                       render_board_view, write_synthetic_capture)
from .test_intrinsics_extrinsics import DIST_TRUE, K_TRUE, PATTERN, SQUARE, _poses


def _run(args):
    return CliRunner().invoke(calibrate_group, [str(a) for a in args])


def _one_line_error(r, *fragments, exit_code=None) -> str:
    """The command failed with exactly one line on stderr and no traceback; returns that line."""
    assert r.exit_code != 0, r.output
    if exit_code is not None:
        assert r.exit_code == exit_code, r.output
    assert isinstance(r.exception, SystemExit), repr(r.exception)
    assert "Traceback" not in r.output
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("Error: "), r.stderr
    for f in fragments:
        assert str(f) in lines[0], lines[0]
    return lines[0]


def _files(folder):
    return sorted(p.name for p in folder.iterdir())


@pytest.fixture(scope="module")
def board_images(tmp_path_factory):
    """Ten OpenCV-rendered checkerboard views with a known K (the intrinsics test's setup)."""
    folder = tmp_path_factory.mktemp("imgs")
    rng = np.random.default_rng(5)
    for i, (rv, t) in enumerate(_poses(10, rng)):
        cv2.imwrite(str(folder / f"{i:02d}.png"), render_board_view(K_TRUE, DIST_TRUE, rv, t, PATTERN, SQUARE))
    return folder


@pytest.fixture(scope="module")
def capture(tmp_path_factory):
    """Eight PNG + PCD board views with a known T_camera<-lidar, and a calibration with a rough guess."""
    root = tmp_path_factory.mktemp("capture")
    write_synthetic_capture(root / "views", n_poses=8, seed=3)
    capture_calibration(root / "intrinsics.yaml")
    return root


def _extrinsics_args(capture, out, *extra):
    return ["extrinsics", capture / "views", "--calibration", capture / "intrinsics.yaml", "--out", out,
            "--square-m", CAPTURE_SQUARE_M, "--border-m", CAPTURE_BORDER_M, *extra]


def _intrinsics_args(folder, out, *extra):
    return ["intrinsics", folder, "--pattern", "9x6", "--square-m", SQUARE, "--out", out, *extra]


# ---------------------------------------------------------------------------- input errors
def test_missing_folder_and_bad_options_are_one_line(tmp_path, board_images):
    _one_line_error(_run(["intrinsics", tmp_path / "nope", "--out", tmp_path / "c.yaml"]), "nope", exit_code=2)
    _one_line_error(_run(["intrinsics", board_images]), "--out", exit_code=2)
    _one_line_error(_run(["intrinsics", board_images, "--square-m", "nan", "--out", tmp_path / "c.yaml"]),
                    "square-m", "positive", exit_code=2)
    _one_line_error(_run(["intrinsics", board_images, "--pattern", "9by6", "--out", tmp_path / "c.yaml"]), "9x6",
                    exit_code=2)
    _one_line_error(_run(["nosuch"]), "No such command", exit_code=2)
    assert _files(tmp_path) == []


def test_folder_without_images_and_unreadable_image(tmp_path):
    empty = tmp_path / "empty"
    empty.mkdir()
    _one_line_error(_run(["intrinsics", empty, "--out", tmp_path / "c.yaml"]), "no images", exit_code=1)
    (empty / "broken.png").write_bytes(b"\x89PNG not really")
    _one_line_error(_run(["intrinsics", empty, "--out", tmp_path / "c.yaml"]), "broken.png", "cannot be read")
    assert not (tmp_path / "c.yaml").exists()


def test_too_few_views_for_any_calibration(tmp_path, board_images):
    few = tmp_path / "few"
    few.mkdir()
    for p in sorted(board_images.iterdir())[:3]:
        shutil.copy(p, few)
    _one_line_error(_run(_intrinsics_args(few, tmp_path / "c.yaml")), "usable views")
    assert not (tmp_path / "c.yaml").exists()


@pytest.mark.parametrize("content", [b"\x00\x01binary", b"camera: caf\xe9\n", b"", b"robot: a\nrobot: b\n"])
def test_bad_calibration_yaml_is_one_line_in_every_command(tmp_path, capture, content):
    bad = tmp_path / "bad.yaml"
    bad.write_bytes(content)
    _one_line_error(_run(["report", bad]), "calibration file", "bad.yaml")
    _one_line_error(_run(["project", PANDAR / "0.pcd", PANDAR / "0.png", "--calibration", bad, "--out",
                          tmp_path / "o.png"]), "bad.yaml")
    _one_line_error(_run(["extrinsics", capture / "views", "--calibration", bad, "--out", tmp_path / "o.yaml"]),
                    "bad.yaml")
    assert _files(tmp_path) == ["bad.yaml"]


def test_output_folder_checked_before_the_work(tmp_path, board_images, capture):
    _one_line_error(_run(_intrinsics_args(board_images, tmp_path / "nodir" / "c.yaml")), "does not exist")
    _one_line_error(_run(_extrinsics_args(capture, tmp_path / "nodir" / "c.yaml")), "does not exist")
    _one_line_error(_run(["project", PANDAR / "0.pcd", PANDAR / "0.png", "--calibration",
                          capture / "intrinsics.yaml", "--out", tmp_path / "o.png", "--json",
                          tmp_path / "nodir" / "s.json"]), "does not exist")
    _one_line_error(_run(["project", PANDAR / "0.pcd", PANDAR / "0.png", "--calibration",
                          capture / "intrinsics.yaml", "--out", tmp_path / "o.weird"]), "suffix")
    assert _files(tmp_path) == []


def test_never_over_a_shipped_artifact(tmp_path):
    """Refused before the work (the folder has no images: code that checks late fails differently)."""
    from importlib import resources

    shipped = resources.files("calibration") / "robots" / "limo.yaml"
    before = shipped.read_bytes()
    _one_line_error(_run(["intrinsics", tmp_path, "--out", shipped]), "shipped artifact")
    assert shipped.read_bytes() == before


# ---------------------------------------------------------------------------- intrinsics --out
def _calibration_with_extrinsic(path):
    T = capture_T_cam_lidar()
    cal = make_calibration("limo", K_TRUE * [[0.9], [0.9], [1]], np.zeros(5), 640, 480, T, method="previous",
                           extrinsic_rms_m=0.012, n_board_poses=9)
    save_calibration(cal, path)
    return path


def test_intrinsics_into_an_existing_calibration_keeps_its_extrinsic(tmp_path, board_images):
    out = _calibration_with_extrinsic(tmp_path / "cal.yaml")
    T_before = load_calibration(out).T_cam_lidar()
    r = _run(_intrinsics_args(board_images, out))
    assert r.exit_code == 0, r.output
    assert "kept the lidar_to_camera extrinsic" in r.output
    cal = load_calibration(out)
    np.testing.assert_allclose(cal.T_cam_lidar(), T_before, atol=1e-12)
    assert abs(cal.camera.fx / K_TRUE[0, 0] - 1) < 0.01  # the new intrinsics
    assert cal.provenance.extrinsic_rms_m == 0.012 and cal.provenance.n_board_poses == 9
    assert "kept from the previous file" in cal.provenance.method


def test_intrinsics_out_that_is_not_a_calibration_is_left_alone(tmp_path, board_images):
    out = tmp_path / "notes.yaml"
    out.write_text("shopping: [milk]\n")
    _one_line_error(_run(_intrinsics_args(board_images, out)), "notes.yaml", "not a valid calibration")
    assert out.read_text() == "shopping: [milk]\n"
    other = _calibration_with_extrinsic(tmp_path / "other.yaml")
    before = other.read_bytes()
    _one_line_error(_run(_intrinsics_args(board_images, other, "--robot", "scout")), "robot 'limo', not 'scout'")
    assert other.read_bytes() == before


def test_intrinsics_missing_the_quality_target_are_not_written(tmp_path, board_images, monkeypatch):
    monkeypatch.setattr(intrinsics_module, "INTRINSICS_MAX_RMS_PX", 0.001)
    out = _calibration_with_extrinsic(tmp_path / "cal.yaml")
    before = out.read_bytes()
    r = _run(_intrinsics_args(board_images, out))
    _one_line_error(r, "quality target", "RMS reprojection error", "> 0.001 px", "not written", "--force")
    assert "RMS reprojection error" in r.stdout  # the figures are printed
    assert out.read_bytes() == before  # the existing output stays intact
    assert _files(tmp_path) == ["cal.yaml"]  # no temporary file left
    fresh = tmp_path / "fresh.yaml"
    _one_line_error(_run(_intrinsics_args(board_images, fresh)), "quality target")
    assert not fresh.exists()
    r = _run(_intrinsics_args(board_images, fresh, "--force"))
    assert r.exit_code == 0 and "written because of --force" in r.output, r.output
    assert load_calibration(fresh).provenance.intrinsics_rms_px > 0.001


def test_intrinsics_from_too_few_views_are_not_written(tmp_path, board_images):
    six = tmp_path / "six"
    six.mkdir()
    for p in sorted(board_images.iterdir())[:6]:
        shutil.copy(p, six)
    out = tmp_path / "c.yaml"
    _one_line_error(_run(_intrinsics_args(six, out)), "6 usable views < 8")
    assert not out.exists()
    assert _run(_intrinsics_args(six, out, "--force")).exit_code == 0
    assert load_calibration(out).provenance.n_images == 6


# ---------------------------------------------------------------------------- extrinsics
def test_extrinsics_writes_only_to_a_separate_out(tmp_path, capture):
    inp = capture / "intrinsics.yaml"
    before = inp.read_bytes()
    _one_line_error(_run(["extrinsics", capture / "views", "--calibration", inp]), "--out", exit_code=2)
    _one_line_error(_run(_extrinsics_args(capture, inp)), "also an input")
    _one_line_error(_run(_extrinsics_args(capture, capture / "views" / "pose_00.pcd")), "also an input")
    assert inp.read_bytes() == before
    out = tmp_path / "cal.yaml"
    r = _run(_extrinsics_args(capture, out))
    assert r.exit_code == 0, r.output
    assert inp.read_bytes() == before
    from calibration.extrinsics import transform_error

    t_err, r_err = transform_error(load_calibration(out).T_cam_lidar(), capture_T_cam_lidar())
    assert t_err < 0.01 and r_err < 0.5, (t_err, r_err)


def _views_with(tmp_path, capture, name, cloud=None, raw=None):
    views = tmp_path / "views"
    shutil.copytree(capture / "views", views)
    if raw is not None:
        (views / name).write_bytes(raw)
    else:
        write_pcd(views / name, cloud)
    return views


@pytest.mark.parametrize(
    "cloud,raw,fragments",
    [
        ({k: np.zeros(0, np.float32) for k in "xyz"}, None, ("pose_03.pcd", "empty")),
        ({k: np.full(4, np.nan, np.float32) for k in "xyz"}, None, ("pose_03.pcd", "none of its 4 points")),
        (None, b"VERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nPOINTS 9\nDATA binary\n" + b"\0" * 12,
         ("pose_03.pcd", "12 bytes", "need 108")),
        (None, b"\xff\xfe garbage", ("pose_03.pcd",)),
    ],
)
def test_extrinsics_bad_scan_is_one_line_and_nothing_is_written(tmp_path, capture, cloud, raw, fragments):
    views = _views_with(tmp_path, capture, "pose_03.pcd", cloud, raw)
    out = tmp_path / "cal.yaml"
    out.write_text("precious: true\n")
    r = _run(["extrinsics", views, "--calibration", capture / "intrinsics.yaml", "--out", out,
              "--square-m", CAPTURE_SQUARE_M, "--border-m", CAPTURE_BORDER_M])
    _one_line_error(r, *fragments)
    assert out.read_text() == "precious: true\n"


def test_extrinsics_image_of_another_size(tmp_path, capture):
    views = tmp_path / "views"
    shutil.copytree(capture / "views", views)
    cv2.imwrite(str(views / "pose_01.png"), np.zeros((240, 320, 3), np.uint8))
    _one_line_error(_run(["extrinsics", views, "--calibration", capture / "intrinsics.yaml", "--out",
                          tmp_path / "o.yaml"]), "pose_01.png", "320x240", "640x480")
    assert not (tmp_path / "o.yaml").exists()


def test_extrinsics_missing_the_quality_target_are_not_written(tmp_path, capture, monkeypatch):
    out = tmp_path / "cal.yaml"
    shutil.copy(capture / "intrinsics.yaml", out)
    before = out.read_bytes()
    monkeypatch.setattr(extrinsics_module, "EXTRINSIC_MAX_RMS_M", 0.001)
    r = _run(_extrinsics_args(capture, out))
    _one_line_error(r, "extrinsics miss the quality target", "point-to-plane RMS", "> 0.10 cm", "--force")
    assert "point-to-plane RMS" in r.stdout
    assert out.read_bytes() == before
    r = _run(_extrinsics_args(capture, out, "--force"))
    assert r.exit_code == 0 and "written because of --force" in r.output, r.output
    assert load_calibration(out).provenance.extrinsic_rms_m > 0.001


def test_extrinsics_from_too_few_poses_are_not_written(tmp_path, capture):
    views = tmp_path / "views"
    views.mkdir()
    for p in sorted((capture / "views").iterdir()):
        if p.stem in ("pose_00", "pose_01", "pose_02", "pose_03"):
            shutil.copy(p, views)
    out = tmp_path / "o.yaml"
    r = _run(["extrinsics", views, "--calibration", capture / "intrinsics.yaml", "--out", out,
              "--square-m", CAPTURE_SQUARE_M, "--border-m", CAPTURE_BORDER_M])
    _one_line_error(r, "4 board poses < 6")
    assert not out.exists()


# ---------------------------------------------------------------------------- project, import, report
def test_project_empty_cloud_and_missing_extrinsic(tmp_path, pandar_calibration):
    cal = tmp_path / "pandar.yaml"
    save_calibration(pandar_calibration, cal)
    write_pcd(tmp_path / "empty.pcd", {k: np.zeros(0, np.float32) for k in "xyz"})
    _one_line_error(_run(["project", tmp_path / "empty.pcd", PANDAR / "0.png", "--calibration", cal, "--out",
                          tmp_path / "o.png"]), "empty.pcd", "empty")
    no_ext = tmp_path / "noext.yaml"
    data = yaml.safe_load(cal.read_text())
    del data["lidar_to_camera"]
    no_ext.write_text(yaml.safe_dump(data))
    _one_line_error(_run(["project", PANDAR / "0.pcd", PANDAR / "0.png", "--calibration", no_ext, "--out",
                          tmp_path / "o.png"]), "no lidar_to_camera")
    _one_line_error(_run(["project", PANDAR / "0.pcd", PANDAR / "0.png", "--calibration", cal, "--out",
                          PANDAR / "0.png"]), "also an input")
    assert sorted(_files(tmp_path)) == ["empty.pcd", "noext.yaml", "pandar.yaml"]


def test_project_writes_overlay_and_json_atomically(tmp_path, pandar_calibration):
    cal = tmp_path / "pandar.yaml"
    save_calibration(pandar_calibration, cal)
    out, stats = tmp_path / "overlay.jpg", tmp_path / "stats.json"
    r = _run(["project", PANDAR / "0.pcd", PANDAR / "0.png", "--calibration", cal, "--out", out, "--json", stats])
    assert r.exit_code == 0, r.output
    assert cv2.imread(str(out)).shape == (1200, 1920, 3)
    assert json.loads(stats.read_text())["points"] == 78238
    assert sorted(_files(tmp_path)) == ["overlay.jpg", "pandar.yaml", "stats.json"]


def test_import_opencalib_errors(tmp_path):
    intr, extr = PANDAR / "center_camera-intrinsic.json", PANDAR / "top_center_lidar-to-center_camera-extrinsic.json"
    _one_line_error(_run(["import-opencalib", intr, extr, "--width", "0", "--height", "1200", "--out",
                          tmp_path / "c.yaml"]), "--width", exit_code=2)
    _one_line_error(_run(["import-opencalib", intr, extr, "--width", "1920", "--height", "1200", "--out", intr]),
                    "also an input")
    doc = json.loads(extr.read_text())
    doc["top_center_lidar-to-center_camera-extrinsic"]["param"]["sensor_calib"]["data"][0][3] = float("nan")
    bad = tmp_path / "ext.json"
    bad.write_text(json.dumps(doc))
    _one_line_error(_run(["import-opencalib", intr, bad, "--width", "1920", "--height", "1200", "--out",
                          tmp_path / "c.yaml"]), "sensor_calib", "non-finite")
    bad.write_bytes(b"\xff\xfe\x00")
    _one_line_error(_run(["import-opencalib", intr, bad, "--width", "1920", "--height", "1200", "--out",
                          tmp_path / "c.yaml"]), "ext.json")
    assert not (tmp_path / "c.yaml").exists()


def test_report_with_unreadable_or_mismatched_images(tmp_path, capture):
    imgs = tmp_path / "imgs"
    imgs.mkdir()
    (imgs / "a.png").write_bytes(b"junk")
    _one_line_error(_run(["report", capture / "intrinsics.yaml", "--images", imgs]), "a.png", "cannot be read")
    cv2.imwrite(str(imgs / "a.png"), np.zeros((10, 20), np.uint8))
    _one_line_error(_run(["report", capture / "intrinsics.yaml", "--images", imgs]), "a.png", "20x10")


def test_through_the_dct_entry_point_stderr_is_one_line(tmp_path):
    bad = tmp_path / "bad.yaml"
    bad.write_bytes(b"robot: limo\ncamera: \xff\n")
    for args in (["calibrate", "report", str(bad)], ["calibrate", "intrinsics", str(tmp_path / "nope"), "--out", "x"]):
        p = subprocess.run([sys.executable, "-m", "runtime.app.cli", *args], capture_output=True, text=True, timeout=120)
        assert p.returncode != 0
        assert "Traceback" not in p.stderr
        assert len(p.stderr.strip().splitlines()) == 1, p.stderr


def test_hil_check_json_folder_checked_before_the_run(tmp_path):
    pytest.importorskip("mujoco")
    from runtime.app.cli import dct

    r = CliRunner().invoke(dct, ["calibrate", "hil-check", "--json", str(tmp_path / "nodir" / "out.json")])
    _one_line_error(r, "nodir", "does not exist")
