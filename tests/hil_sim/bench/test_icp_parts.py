"""`dct bench icp-parts`: ICP time per frame by part. No timing is asserted (the machine is slow
and noisy): that every part is there, that no part exceeds its frame, and the command's inputs."""
import json

import numpy as np
from click.testing import CliRunner

from hil_sim.bench.cli import bench_group
from hil_sim.bench.icp_parts import PARTS, time_parts
from tests.runtime.odometry.test_fusion import _frames


def test_every_part_of_every_frame_is_timed_and_none_exceeds_its_frame():
    jobs = _frames(4)
    out = time_parts(jobs, repeats=2)
    assert out["frames"] == 3 and list(out["parts_ms_p50"]) == list(PARTS)
    parts = np.array(list(out["parts_ms_p50"].values()))
    assert np.all(parts >= 0.0)
    # Each frame's wall time holds all its parts, so its median is at least every part's median.
    assert out["wall_ms"]["p50"] >= parts.max() and out["wall_ms"]["p99"] >= out["wall_ms"]["p50"]
    # The job crosses with its arrays: at least the points (float32 x 3) and their times (float32).
    assert out["job_bytes_p50"] >= len(jobs[1].points) * 16 and out["job_pickle_ms_p50"] > 0.0


def test_the_command_prints_and_writes_one_row_per_density(tmp_path):
    out = tmp_path / "parts.json"
    r = CliRunner().invoke(bench_group, ["icp-parts", "--rays", "2000", "--seconds", "1.5", "--repeats", "1",
                                         "--json", str(out)])
    assert r.exit_code == 0, r.output
    assert "registration" in r.output and "inspect" in r.output
    (row,) = json.loads(out.read_text())["rows"]
    assert row["rays_per_frame"] == 2000 and row["frames"] >= 1 and 0 < row["returns_p50"] <= 2000


def test_an_existing_json_is_refused_without_force_and_bad_values_exit_2(tmp_path):
    out = tmp_path / "parts.json"
    out.write_text("{}")
    r = CliRunner().invoke(bench_group, ["icp-parts", "--json", str(out)])
    assert r.exit_code != 0 and "already exists" in r.output and out.read_text() == "{}"
    assert CliRunner().invoke(bench_group, ["icp-parts", "--rays", "10"]).exit_code == 2
    assert CliRunner().invoke(bench_group, ["icp-parts", "--repeats", "0"]).exit_code == 2
