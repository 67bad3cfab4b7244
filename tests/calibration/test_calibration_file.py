"""Calibration file: round trip, and errors that name the field and the reason."""
import numpy as np
import pytest
import yaml

from calibration.calibration_file import load_calibration, make_calibration, save_calibration
from calibration.errors import ConfigFileError

K = np.array([[336.0, 0.0, 319.5], [0.0, 337.0, 239.5], [0.0, 0.0, 1.0]])
T = np.eye(4)
T[:3, :3] = [[0, -1, 0], [0, 0, -1], [1, 0, 0]]
T[:3, 3] = [0.0, -0.05, -0.08]


def _write(tmp_path, cal_dict):
    p = tmp_path / "cal.yaml"
    p.write_text(yaml.safe_dump(cal_dict))
    return p


@pytest.fixture
def good(tmp_path):
    cal = make_calibration("limo", K, [0.01, -0.02, 0.0, 0.0, 0.0], 640, 480, T, method="test",
                           intrinsics_rms_px=0.2)
    save_calibration(cal, tmp_path / "good.yaml")
    return yaml.safe_load((tmp_path / "good.yaml").read_text())


def test_round_trip(tmp_path, good):
    cal = load_calibration(_write(tmp_path, good))
    np.testing.assert_allclose(cal.camera.K(), K)
    np.testing.assert_allclose(cal.T_cam_lidar(), T, atol=1e-9)
    uv, valid = cal.camera_model().project(np.array([[0.0, 0.0, 1.0]]))
    assert valid[0] and np.allclose(uv[0], [319.5, 239.5])


def test_quaternion_and_matrix_forms(tmp_path, good):
    from scipy.spatial.transform import Rotation

    q = Rotation.from_matrix(T[:3, :3]).as_quat().tolist()
    good["lidar_to_camera"] = {"xyz_m": [0.0, -0.05, -0.08], "quaternion_xyzw": q}
    np.testing.assert_allclose(load_calibration(_write(tmp_path, good)).T_cam_lidar(), T, atol=1e-9)
    good["lidar_to_camera"] = {"xyz_m": [0.0, -0.05, -0.08], "rotation_matrix": T[:3, :3].tolist()}
    np.testing.assert_allclose(load_calibration(_write(tmp_path, good)).T_cam_lidar(), T, atol=1e-12)


@pytest.mark.parametrize(
    "path,value,field,reason",
    [
        (("camera", "fx"), -336.0, "camera.fx", "greater than 0"),
        (("camera", "distortion"), [0.1, 0.2, 0.3], "camera.distortion", "coefficients"),
        (("camera", "cx"), 900.0, "camera", "principal point"),
        (("camera", "width_px"), 0, "camera.width_px", "greater than 0"),
        (("lidar_to_camera",), {"xyz_m": [0, 0, 0]}, "lidar_to_camera", "exactly one"),
        (("provenance", "method"), "", "provenance.method", "at least 1"),
        (("provenance", "date"), "yesterday", "provenance.date", "datetime"),
        (("camera", "focal"), 3.0, "camera.focal", "Extra inputs"),
    ],
)
def test_bad_values_name_field_and_reason(tmp_path, good, path, value, field, reason):
    node = good
    for k in path[:-1]:
        node = node[k]
    node[path[-1]] = value
    with pytest.raises(ConfigFileError) as e:
        load_calibration(_write(tmp_path, good))
    msg = str(e.value)
    assert "cal.yaml" in msg and field in msg and reason in msg, msg


def test_non_orthonormal_rotation(tmp_path, good):
    R = T[:3, :3].copy()
    R[0, 1] = -0.9
    good["lidar_to_camera"] = {"xyz_m": [0, 0, 0], "rotation_matrix": R.tolist()}
    with pytest.raises(ConfigFileError, match="lidar_to_camera.*orthonormal"):
        load_calibration(_write(tmp_path, good))
    good["lidar_to_camera"] = {"xyz_m": [0, 0, 0], "rotation_matrix": (-np.eye(3)).tolist()}
    with pytest.raises(ConfigFileError, match="reflection"):
        load_calibration(_write(tmp_path, good))
    good["lidar_to_camera"] = {"xyz_m": [0, 0, 0], "quaternion_xyzw": [0, 0, 0, 2]}
    with pytest.raises(ConfigFileError, match="unit norm"):
        load_calibration(_write(tmp_path, good))


def test_missing_extrinsic_is_explicit(tmp_path, good):
    del good["lidar_to_camera"]
    cal = load_calibration(_write(tmp_path, good))
    with pytest.raises(ConfigFileError, match="no lidar_to_camera"):
        cal.T_cam_lidar()


def test_not_yaml_and_missing_file(tmp_path):
    p = tmp_path / "x.yaml"
    p.write_text("camera: [unclosed")
    with pytest.raises(ConfigFileError, match="not valid YAML"):
        load_calibration(p)
    with pytest.raises(ConfigFileError, match="cannot read"):
        load_calibration(tmp_path / "missing.yaml")


@pytest.mark.parametrize(
    "extrinsic, field, reason",
    [
        ({"xyz_m": [2.5, 0.0, 0.0], "rpy_deg": [0, 0, 0]}, "lidar_to_camera.xyz_m", "implausible"),
        ({"xyz_m": [1.5, 1.5, 0.0], "rpy_deg": [0, 0, 0]}, "lidar_to_camera.xyz_m", "2.12 m long"),
        ({"xyz_m": [0.0, 0.0, 0.0], "rpy_deg": [0, 400, 0]}, "lidar_to_camera.rpy_deg.1", "less than or equal to 360"),
        ({"xyz_m": [0.0, 0.0, 0.0], "rotation_matrix": [[1, 0, 0], [0, 1, 0], [0, 0, 2]]}, "lidar_to_camera",
         "not orthonormal"),
        ({"xyz_m": [0.0, 0.0, 0.0], "rotation_matrix": [[1, 0, 0], [0, 1, 0], [0, 0, -1]]}, "lidar_to_camera",
         "reflection"),
        ({"xyz_m": [0.0, 0.0, 0.0], "quaternion_xyzw": [0.5, 0.5, 0.5, 0.6]}, "lidar_to_camera", "unit norm"),
    ],
)
def test_impossible_extrinsic_is_rejected_naming_the_field(tmp_path, good, extrinsic, field, reason):
    good["lidar_to_camera"] = extrinsic
    with pytest.raises(ConfigFileError) as e:
        load_calibration(_write(tmp_path, good))
    msg = str(e.value)
    assert "\n" not in msg and "cal.yaml" in msg and f"{field}" in msg and reason in msg, msg


@pytest.mark.parametrize(
    "text_old, text_new, shown",
    [
        ("fx: 336.0", "fx: .nan", "camera.fx: must be a finite number (got nan)"),
        ("fy: 337.0", "fy: -.inf", "camera.fy: must be a finite number (got -inf)"),
        ("fx: 336.0", "fx: 0.0", "camera.fx: Input should be greater than 0 (got 0.0)"),
        ("- 0.01\n", "- .nan\n", "camera.distortion.0: must be a finite number (got nan)"),
    ],
)
def test_non_finite_or_non_positive_intrinsics_are_rejected(tmp_path, good, text_old, text_new, shown):
    text = yaml.safe_dump(good, sort_keys=False)
    assert text_old in text, text
    p = tmp_path / "cal.yaml"
    p.write_text(text.replace(text_old, text_new, 1))
    with pytest.raises(ConfigFileError) as e:
        load_calibration(p)
    assert shown in str(e.value), str(e.value)


def test_non_finite_values_in_the_extrinsic_are_named(tmp_path, good):
    good["lidar_to_camera"] = {"xyz_m": [0.1, 0.2, 0.3], "rpy_deg": [1.5, 2.5, 3.5]}
    text = yaml.safe_dump(good, sort_keys=False)
    p = tmp_path / "cal.yaml"
    for key, first in (("xyz_m", "- 0.1\n"), ("rpy_deg", "- 1.5\n")):
        assert text.count(first) == 1, text
        p.write_text(text.replace(first, "- .nan\n"))
        with pytest.raises(ConfigFileError, match=rf"lidar_to_camera\.{key}\.0: must be a finite number \(got nan\)"):
            load_calibration(p)


def test_make_calibration_rejects_non_finite_and_far_extrinsic():
    bad_K = K.copy()
    bad_K[0, 0] = np.nan
    with pytest.raises(ConfigFileError, match="camera.fx"):
        make_calibration("limo", bad_K, np.zeros(5), 640, 480, None, method="test")
    far = T.copy()
    far[:3, 3] = [0.0, 0.0, 5.0]
    with pytest.raises(ConfigFileError, match="lidar_to_camera.xyz_m"):
        make_calibration("limo", K, np.zeros(5), 640, 480, far, method="test")


def test_save_calibration_is_atomic_and_keeps_the_old_file_on_error(tmp_path, good):
    p = _write(tmp_path, good)
    before = p.read_bytes()
    cal = load_calibration(p)
    cal.camera.fx = -1.0  # assignment is not validated; saving validates again
    with pytest.raises(ConfigFileError, match="camera.fx"):
        save_calibration(cal, p)
    assert p.read_bytes() == before
    assert [q.name for q in tmp_path.iterdir() if q.name.startswith(".")] == []  # no temporary left behind
