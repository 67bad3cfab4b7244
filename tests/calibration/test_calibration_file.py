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
