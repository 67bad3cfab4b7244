"""What `dct odom eval --scans` says about the ICP settings it used and the points its range gate
dropped (JSON and stdout, a warning line on stderr above a quarter)."""
import json

import pytest
from click.testing import CliRunner

from runtime.odometry.cli import odom_group
from tests.runtime.odometry.synthetic_sequence import make_sequence


@pytest.fixture(scope="module")
def sequence(tmp_path_factory):
    return make_sequence(tmp_path_factory.mktemp("seq"), n_scans=12, points=3000)


def _eval(sequence, tmp_path, *extra):
    scans, poses, _ = sequence
    out = tmp_path / "eval.json"
    r = CliRunner().invoke(odom_group, ["eval", "--scans", str(scans), "--poses", str(poses), "--json", str(out),
                                        *map(str, extra)])
    assert r.exit_code == 0, r.output
    return r, json.loads(out.read_text())


def test_the_defaults_are_derived_from_the_first_scan_and_said(sequence, tmp_path):
    r, report = _eval(sequence, tmp_path)
    config, gate = report["config"], report["range_gate"]
    assert report["config_given"]["voxel_size_m"] == "auto" and config["voxel_size_m"] == 0.3
    assert config["max_range_m"] == 12.0 and report["settings_derivation"]["derived"]["max_range_m"] == 12.0
    assert config["max_iterations"] == "auto" and 20 <= report["iteration_caps"][0] <= report["iteration_caps"][1]
    assert gate["frames"] == 12 and gate["dropped_fraction"] < 0.05 and gate["warning"] is None
    assert "ICP settings: voxel 0.3 m, range 0.3-12 m, iteration cap auto (" in r.stdout
    assert f"ICP {gate['summary']}" in r.stdout and "warning" not in r.stderr


def test_a_gate_that_drops_more_than_a_quarter_is_warned_about_on_one_line(sequence, tmp_path):
    r, report = _eval(sequence, tmp_path, "--max-range", 4, "--max-iterations", 30)
    gate = report["range_gate"]
    assert gate["dropped_fraction"] > 0.25 and gate["beyond_max"] > gate["below_min"]
    assert report["config"]["max_iterations"] == 30 and report["iteration_caps"] == [30, 30]
    warnings = [ln for ln in r.stderr.splitlines() if ln.startswith("warning:")]
    assert warnings == [gate["warning"]]
    assert f"dropped {gate['dropped_fraction']:.0%} of the finite points (max range 4 m" in warnings[0]
