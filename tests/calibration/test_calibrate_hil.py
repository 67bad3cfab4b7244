"""`dct calibrate hil`: a simulated robot variant calibrated from its target views recovers its truth."""
import json
import tomllib
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

pytest.importorskip("mujoco")

from calibration.robot_description import load_robot_description  # noqa: E402
from hil_sim.world.robot_variant import resolve_variant  # noqa: E402

ROBOT = load_robot_description()
ROOT = Path(__file__).resolve().parents[2]


def _assert_recovers(cal, variant, targets) -> None:
    """The calibration file against the variant's truth (not the command's own verdict)."""
    from calibration.extrinsics import transform_error

    truth = variant.true_camera()
    K = cal.camera.K()
    assert abs(K[0, 0] / truth.fx - 1) <= targets["focal_rel"] and abs(K[1, 1] / truth.fy - 1) <= targets["focal_rel"]
    assert abs(K[0, 2] - truth.cx) <= targets["principal_px"] and abs(K[1, 2] - truth.cy) <= targets["principal_px"]
    for est, true in ((cal.T_base_lidar(ROBOT), variant.true_lidar_mount()),
                      (cal.T_base_lidar(ROBOT) @ np.linalg.inv(cal.T_cam_lidar()), variant.true_camera_mount()),
                      (cal.T_cam_lidar(), variant.true_T_cam_lidar())):
        t_err, r_err = transform_error(est, true)
        assert t_err <= targets["mount_m"] and r_err <= targets["mount_deg"], (t_err, r_err)
    # The lens over the whole image, corners included, within the controller's calibration check
    # (3 px: runtime config calibration_check): a fit from central views alone extrapolates its
    # distortion into the corners and fails it there.
    from calibration.consistency import _distortion_shift_px

    assert _distortion_shift_px(cal.camera_model(), truth.dist) <= 3.0


def test_calibrate_hil_variant_7_recovers_the_truth(tmp_path):
    """`dct calibrate hil --robot-variant 7` (20 views: the quick form of the default 30)."""
    from calibration.calibration_file import load_calibration
    from hil_sim.eval.calibration_hil import TARGETS, calibrate_hil_command

    out, fig = tmp_path / "cal7.yaml", tmp_path / "fig.json"
    r = CliRunner().invoke(calibrate_hil_command, ["--robot-variant", "7", "--out", str(out), "--json", str(fig),
                                                   "--poses", "20"])
    assert r.exit_code == 0, r.output
    assert "lidar_mount xyz [mm]" in r.output and "passed" in r.output
    cal = load_calibration(out)
    assert cal.lidar_mount is not None and len(cal.camera.distortion) == 5
    assert "robot variant seed 7" in cal.provenance.method
    variant = resolve_variant(7, ROBOT)
    _assert_recovers(cal, variant, TARGETS)
    figures = json.loads(fig.read_text())
    assert figures["passed"] is True and figures["robot_variant"] == variant.to_dict()
    # The recovered camera is the variant's, not the description's: the nominal K is further away.
    assert abs(cal.camera.fx - variant.true_camera().fx) < abs(ROBOT.sensors.camera.nominal_intrinsics()[0, 0]
                                                                - variant.true_camera().fx)


@pytest.mark.slow
@pytest.mark.parametrize("spec", ["7", "1", "2", str(ROOT / "hil_sim/scenarios/robot_variants/limo_edge.yaml")])
def test_calibrate_hil_recovers_the_truth_at_the_default_views(spec):
    from hil_sim.eval.calibration_hil import TARGETS, run_calibrate_hil

    variant = resolve_variant(spec, ROBOT)
    result = run_calibrate_hil(variant, seed=0)
    assert result["figures"]["passed"], result["figures"]["errors"]
    _assert_recovers(result["calibration"], variant, TARGETS)


def test_outputs_are_checked_before_the_work(tmp_path):
    from hil_sim.eval.calibration_hil import calibrate_hil_command

    out = tmp_path / "cal.yaml"
    out.write_text("kept\n")
    r = CliRunner().invoke(calibrate_hil_command, ["--robot-variant", "7", "--out", str(out)])
    assert r.exit_code != 0 and "--force" in r.output and len(r.output.strip().splitlines()) == 1
    assert out.read_text() == "kept\n"
    r = CliRunner().invoke(calibrate_hil_command, ["--robot-variant", "7", "--out", str(tmp_path / "no" / "c.yaml")])
    assert r.exit_code != 0 and len(r.output.strip().splitlines()) == 1


@pytest.mark.parametrize("spec", ["seven", "missing.yaml"])
def test_a_bad_variant_is_one_line(tmp_path, spec):
    from hil_sim.eval.calibration_hil import calibrate_hil_command

    r = CliRunner().invoke(calibrate_hil_command, ["--robot-variant", spec, "--out", str(tmp_path / "c.yaml")])
    assert r.exit_code == 1 and "robot variant" in r.output and len(r.output.strip().splitlines()) == 1
    assert not (tmp_path / "c.yaml").exists()


def test_the_fixture_boards_are_in_view_of_every_drawn_variant():
    """The end-of-line stations leave a margin around each board for any variant within the bounds."""
    from calibration.camera_model import CameraModel, transform_points
    from hil_sim.eval.calibration_check import BOARD_BORDER_M, BOARD_PATTERN, BOARD_SQUARE_M
    from hil_sim.eval.calibration_hil import fixture_board_poses
    from hil_sim.world.robot_variant import _camera_K, draw_departures

    cols, rows = BOARD_PATTERN
    sq, b = BOARD_SQUARE_M, BOARD_BORDER_M
    outline = np.array([[-sq - b, -sq - b, 0], [cols * sq + b, -sq - b, 0], [cols * sq + b, rows * sq + b, 0],
                        [-sq - b, rows * sq + b, 0]])
    for seed in range(100):
        d = draw_departures(seed, ROBOT)
        cam = CameraModel(_camera_K(d.camera, ROBOT), np.array(d.camera.distortion), 640, 480)
        T_base_cam = d.camera_mount.apply(ROBOT.sensors.camera.mount)
        for T_base_board in fixture_board_poses():
            uv, valid = cam.project(transform_points(np.linalg.inv(T_base_cam) @ T_base_board, outline))
            assert valid.all() and uv.min() > 15 and uv[:, 0].max() < 625 and uv[:, 1].max() < 465, (seed, uv)


def test_dct_calibrate_hil_is_registered_beside_hil_check():
    """`dct calibrate hil` comes from the dct.calibrate entry point group, like hil-check."""
    from importlib import import_module

    from hil_sim.eval.calibration_hil import calibrate_hil_command

    group = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["entry-points"]["dct.calibrate"]
    module, name = group["hil"].split(":")
    assert getattr(import_module(module), name) is calibrate_hil_command
    assert calibrate_hil_command.name == "hil" and "hil-check" in group
