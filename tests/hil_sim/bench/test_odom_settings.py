"""`dct bench odom-settings`: the default (auto) ICP settings beside the best of a grid, on a recorded
sequence and on a scenario's drive recorded as one."""
import json

import numpy as np
import pytest
from click.testing import CliRunner

from hil_sim.bench.cli import bench_group
from hil_sim.bench.odom_settings import grid_configs, record_scenario_sequence
from runtime.odometry.icp_config import IcpConfig
from runtime.odometry.sequence import evaluate_sequence, load_sequence
from tests.runtime.odometry.synthetic_sequence import make_sequence


@pytest.fixture(scope="module")
def sequence(tmp_path_factory):
    return make_sequence(tmp_path_factory.mktemp("seq"), n_scans=10, points=2500)


def test_the_table_puts_the_defaults_beside_the_best_grid_setting(sequence, tmp_path):
    scans, poses, _ = sequence
    out = tmp_path / "bench.json"
    r = CliRunner().invoke(bench_group, ["odom-settings", "--sequence", str(scans), "--poses", str(poses), "--voxel", "0.3",
                                         "--voxel", "1.0", "--max-range", "12", "--iterations", "50", "--json", str(out)])
    assert r.exit_code == 0, r.output
    result = json.loads(out.read_text())["results"][0]
    assert result["default"]["voxel_size_m"] == 0.3 and result["default"]["max_iterations"] == "auto"
    assert [(g["voxel_size_m"], g["max_range_m"], g["max_iterations"]) for g in result["grid"]] == [(0.3, 12.0, 50),
                                                                                                    (1.0, 12.0, 50)]
    assert result["best"] == min(result["grid"], key=lambda g: g["rpe_percent"])
    header = next(ln for ln in r.stdout.splitlines() if ln.startswith("input"))
    assert "auto settings" in header and "best grid setting" in header
    row = r.stdout.splitlines()[-1]
    assert row.startswith("seq") and "voxel 0.3 m, range 0.3-12 m, cap auto" in row


@pytest.mark.parametrize("args, message", [
    (["--sequence", "x"], "1 --sequence and 0 --poses"),
    ([], "nothing to run"),
    (["--scenario", "case1"], "case1 has no route"),
])
def test_input_errors_are_one_line(args, message):
    r = CliRunner().invoke(bench_group, ["odom-settings", *args])
    assert r.exit_code == 2 and message in r.stderr and len(r.stderr.strip().splitlines()) == 1


def test_grid_configs_leave_the_rest_auto():
    configs = grid_configs((0.3,), (12.0, 60.0), (50,))
    assert [c.max_range_m for c in configs] == [12.0, 60.0]
    assert all(c.min_range_m == "auto" and c.initial_threshold_m == "auto" for c in configs)


@pytest.mark.slow
def test_a_recorded_drive_is_a_sequence_whose_poses_are_the_lidars_truth(tmp_path):
    """case1's room, a 3.6 m route with a turn: KISS-ICP alone on the recorded frames follows the
    recorded poses (a wrong mount or pose convention would show as metres of error)."""
    from tests.hil_sim.eval.test_odometry import _short_route

    item = record_scenario_sequence(_short_route(), 0, tmp_path)
    seq = load_sequence(item.scans, item.poses)
    assert len(seq.indices) > 100 and np.allclose(seq.poses[0][2, 3], seq.poses[-1][2, 3])
    report, _ = evaluate_sequence(seq, IcpConfig())
    assert report["deskew"] and report["icp"]["length_m"] > 3.0
    assert report["icp"]["end_error_m"] < 0.10  # measured 6.6 cm over 3.6 m; a convention error is metres
