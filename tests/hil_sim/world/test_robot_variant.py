"""Robot variants: drawn within bounds and deterministic per seed, explicit files validated, the truth."""
import numpy as np
import pytest
import yaml
from click.testing import CliRunner
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from calibration.errors import ConfigFileError
from calibration.robot_description import load_robot_description
from hil_sim.world.robot_variant import BOUNDS, VariantDepartures, VariantError, draw_departures, resolve_variant

ROBOT = load_robot_description()


def _within(value: float, name: str) -> bool:
    low, high = BOUNDS[name]
    return low <= value <= high


def _assert_within_bounds(d: VariantDepartures) -> None:
    assert all(_within(s, "focal_scale") for s in d.camera.focal_scale)
    assert all(_within(p, "principal_offset_px") for p in d.camera.principal_offset_px)
    assert all(_within(k, name) for k, name in zip(d.camera.distortion, ("k1", "k2", "p1", "p2", "k3")))
    for mount in (d.lidar_mount, d.camera_mount):
        assert all(_within(x, "dxyz_m") for x in mount.dxyz_m)
        assert all(_within(a, "drpy_deg") for a in mount.drpy_deg)


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.integers(0, 2 ** 32 - 1))
def test_a_seed_draws_within_the_bounds_and_the_same_every_time(seed):
    from hil_sim.sensors.camera_lens import check_lens
    from hil_sim.world.robot_variant import _camera_K

    a, b = draw_departures(seed, ROBOT), draw_departures(seed, ROBOT)
    assert a == b
    _assert_within_bounds(a)
    check_lens(_camera_K(a.camera, ROBOT), np.array(a.camera.distortion), 640, 480)  # every drawn lens fits


def test_a_seed_names_the_same_variant_as_its_digits():
    a, b = resolve_variant(7, ROBOT), resolve_variant("7", ROBOT)
    assert a.to_dict() == b.to_dict() and a.source == "seed" and a.label == "seed 7"
    assert a.lens is not None and np.array_equal(a.lens.K, b.lens.K)


def test_seeds_draw_different_variants_that_span_the_bounds():
    draws = [draw_departures(s, ROBOT) for s in range(40)]
    assert len({d.camera.focal_scale for d in draws}) == 40
    k1 = [d.camera.distortion[0] for d in draws]
    dx = [d.lidar_mount.dxyz_m[0] for d in draws]
    assert min(k1) < -0.15 and max(k1) > 0.0  # barrel and pincushion lenses both occur
    assert min(dx) < -0.01 and max(dx) > 0.01


def test_nominal_is_the_robot_as_described():
    v = resolve_variant("nominal", ROBOT)
    assert v.is_nominal and v.lens is None and v.robot == ROBOT
    assert np.allclose(v.true_camera().K, ROBOT.sensors.camera.nominal_intrinsics())
    assert np.allclose(v.true_lidar_mount(), ROBOT.sensors.lidar.mount.transform())


def test_an_explicit_file_gives_the_truth_it_says(tmp_path):
    path = tmp_path / "v.yaml"
    path.write_text(yaml.safe_dump({
        "camera": {"focal_scale": [1.02, 1.01], "principal_offset_px": [5.0, -3.0],
                   "distortion": [-0.1, 0.02, 0.001, -0.001, 0.0]},
        "lidar_mount": {"dxyz_m": [0.01, 0.0, -0.02], "drpy_deg": [0.0, 0.0, 1.5]},
        "camera_mount": {"drpy_deg": [0.0, 2.0, 0.0]},
    }))
    v = resolve_variant(str(path), ROBOT)
    assert v.source == "file" and v.spec == str(path)
    K0 = ROBOT.sensors.camera.nominal_intrinsics()
    cam = v.true_camera()
    assert cam.fx == pytest.approx(1.02 * K0[0, 0]) and cam.fy == pytest.approx(1.01 * K0[0, 0])
    assert (cam.cx, cam.cy) == pytest.approx((K0[0, 2] + 5.0, K0[1, 2] - 3.0))
    assert cam.dist.tolist() == [-0.1, 0.02, 0.001, -0.001, 0.0]
    T = v.true_lidar_mount()
    assert T[:3, 3] == pytest.approx(np.array(ROBOT.sensors.lidar.mount.xyz_m) + [0.01, 0.0, -0.02])
    assert Rotation.from_matrix(T[:3, :3]).as_euler("xyz", degrees=True)[2] == pytest.approx(1.5)
    # The camera mount turns about base_link's y (its nose down by 2 deg), not about its own axes.
    Tc = v.true_camera_mount()
    R_nom = ROBOT.sensors.camera.mount.rotation()
    assert np.allclose(Tc[:3, :3], Rotation.from_euler("y", 2.0, degrees=True).as_matrix() @ R_nom)
    assert np.allclose(v.true_T_cam_lidar(), np.linalg.inv(Tc) @ T)


def test_true_calibration_is_a_valid_calibration_file_of_the_truth(tmp_path):
    from calibration.calibration_file import load_calibration, save_calibration

    v = resolve_variant(7, ROBOT)
    save_calibration(v.true_calibration(), tmp_path / "truth.yaml")
    cal = load_calibration(tmp_path / "truth.yaml")
    assert np.allclose(cal.camera.K(), v.true_camera().K) and np.allclose(cal.camera.distortion, v.true_camera().dist)
    assert np.allclose(cal.T_base_lidar(ROBOT), v.true_lidar_mount(), atol=1e-9)
    assert np.allclose(cal.T_cam_lidar(), v.true_T_cam_lidar(), atol=1e-9)


@pytest.mark.parametrize("content, field", [
    ({"camera": {"focal_scale": [1.05, 1.0]}}, "camera.focal_scale.0"),
    ({"camera": {"principal_offset_px": [0.0, -12.0]}}, "camera.principal_offset_px.1"),
    ({"camera": {"distortion": [0.0, 0.0, 0.01, 0.0, 0.0]}}, "camera.distortion.2"),
    ({"camera": {"distortion": [0.0, 0.0]}}, "camera.distortion"),
    ({"lidar_mount": {"dxyz_m": [0.0, 0.0, 0.03]}}, "lidar_mount.dxyz_m.2"),
    ({"camera_mount": {"drpy_deg": [2.5, 0.0, 0.0]}}, "camera_mount.drpy_deg.0"),
    ({"camera_mount": {"rpy_deg": [0.0, 0.0, 0.0]}}, "camera_mount.rpy_deg"),
    ({"lidar": {}}, "lidar"),
    ({"camera": {"focal_scale": "1.0"}}, "camera.focal_scale"),
    ({"camera": {"distortion": [-0.3, -0.1, 0.0, 0.0, 0.0]}}, "camera.distortion"),  # folds over in the image
])
def test_a_bad_variant_file_is_one_line_naming_the_field(tmp_path, content, field):
    path = tmp_path / "bad.yaml"
    path.write_text(yaml.safe_dump(content))
    with pytest.raises(VariantError) as e:
        resolve_variant(str(path), ROBOT)
    msg = str(e.value)
    assert "\n" not in msg and field in msg and str(path) in msg, msg


@pytest.mark.parametrize("spec", ["seven", "-3", "", "nominal.yaml", str(2 ** 32)])
def test_a_bad_spec_is_one_line(spec):
    with pytest.raises(VariantError) as e:
        resolve_variant(spec, ROBOT)
    assert "\n" not in str(e.value) and "robot variant" in str(e.value)


_value = st.one_of(st.floats(-0.1, 0.1), st.integers(-3, 3), st.text(max_size=3), st.none(),
                   st.lists(st.floats(-3, 3), max_size=6))
_section = st.dictionaries(st.sampled_from(["focal_scale", "principal_offset_px", "distortion", "dxyz_m",
                                            "drpy_deg", "junk"]), _value, max_size=3)


@settings(max_examples=60, deadline=None)
@given(st.dictionaries(st.sampled_from(["camera", "lidar_mount", "camera_mount", "other"]), _section, max_size=3))
def test_any_variant_file_loads_or_fails_in_one_line(tmp_path_factory, data):
    """Fuzzed variant files: accepted only with every value inside its bounds, else one ConfigFileError line."""
    path = tmp_path_factory.mktemp("v") / "v.yaml"
    path.write_text(yaml.safe_dump(data) if data else "{}\n")
    try:
        v = resolve_variant(str(path), ROBOT)
    except ConfigFileError as e:
        assert "\n" not in str(e)
        return
    _assert_within_bounds(v.departures)


def test_a_scenario_names_its_variant_and_the_command_line_overrides_it(tmp_path):
    from hil_sim.cli import _load_variant
    from hil_sim.world.scenario import library_dir, load_scenario

    raw = yaml.safe_load((library_dir() / "case1.yaml").read_text())
    raw["robot_variant"] = {"lidar_mount": {"dxyz_m": [0.0, 0.01, 0.0]}}
    (tmp_path / "s.yaml").write_text(yaml.safe_dump(raw))
    sc = load_scenario(tmp_path / "s.yaml")
    from_scenario = _load_variant(None, sc, ROBOT)
    assert from_scenario.source == "scenario" and from_scenario.true_lidar_mount()[1, 3] == pytest.approx(0.01)
    assert _load_variant("3", sc, ROBOT).departures == draw_departures(3, ROBOT)
    assert _load_variant(None, load_scenario("case1"), ROBOT) is None


def test_hil_run_refuses_a_bad_variant_before_running(tmp_path):
    from hil_sim.cli import hil_group

    bad = tmp_path / "bad.yaml"
    bad.write_text("camera: {focal_scale: [2.0, 1.0]}\n")
    r = CliRunner().invoke(hil_group, ["run", "case1", "--robot-variant", str(bad), "--json", str(tmp_path / "o.json")])
    assert r.exit_code == 2, r.output
    assert "camera.focal_scale.0" in r.output and not (tmp_path / "o.json").exists()


def test_hil_serve_builds_the_variant_it_is_given_else_the_scenarios():
    from hil_sim.episode.serve import ServeOptions, _load

    *_, variant = _load(ServeOptions("case1", robot_variant="3"))
    assert variant.departures == draw_departures(3, ROBOT)
    *_, none = _load(ServeOptions("case1"))
    assert none is None
