"""Training/export round trip and the `dct models` commands (short runs)."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml
from click.testing import CliRunner

from calibration.robot_description import Footprint, load_robot_description
from models.cli import models_group
from models.distance_net import DistanceNet, FoldedDualMLP, rectangle_half_extents, save_artifact, shipped_artifact_path
from models.distance_training import TrainingConfig, footprint_metadata, sample_folded_points, train_and_export
from models.errors import FootprintMismatchError, UnsupportedFootprintError
from models.footprint_dual import exact_dual

ROBOT = load_robot_description()
QUICK = TrainingConfig(steps=300, dataset_size=20_000, batch_size=512, time_limit_s=60.0, threads=1)


def test_training_samples_cover_inside_outside_and_domain() -> None:
    hl, hw = ROBOT.footprint.length_m / 2, ROBOT.footprint.width_m / 2
    pts = sample_folded_points(np.random.default_rng(0), 50_000, hl, hw, 3.25)
    assert pts.shape == (50_000, 2) and (pts >= 0).all()
    G, g = ROBOT.footprint.halfspaces()
    _, d = exact_dual(pts, G, g)
    assert d.max() <= 3.25 + 1e-9
    assert 0.2 < (d < 0).mean() < 0.6
    assert (np.abs(d) < 1e-3).mean() > 0.05  # dense near the boundary


def test_export_round_trip_and_mismatch(tmp_path: Path) -> None:
    other = ROBOT.model_copy(update={"footprint": Footprint(length_m=0.5, width_m=0.3)})
    path = tmp_path / "other.pt"
    meta = train_and_export(other, path, QUICK, eval_points=2_000, log=lambda s: None)
    assert meta["training"]["steps_done"] == 300
    net = DistanceNet.load(path, other)
    assert net.metadata["footprint"]["length_m"] == 0.5
    assert set(meta["error_statistics"]) >= {"max_abs_error_m", "p99_abs_error_m", "inside_sign_errors"}
    # Even an under-trained net never overestimates outside (weak duality).
    rng = np.random.default_rng(5)
    pts = rng.uniform(-3, 3, size=(20_000, 2))
    _, true = exact_dual(pts, net.G, net.g)
    out = true > 0
    assert (net.distance(pts[out]) - true[out]).max() <= 1e-9
    with pytest.raises(FootprintMismatchError):
        DistanceNet.load(path, ROBOT)


def test_exported_torchscript_matches_the_eager_module(tmp_path: Path) -> None:
    """The frozen export computes the same scaled, unfolded mu as the eager module."""
    torch.manual_seed(3)
    model = FoldedDualMLP(0.161, 0.110).eval()
    path = save_artifact(model, tmp_path / "net.pt", {"footprint": footprint_metadata(ROBOT),
                                                      "training_domain": {"max_distance_outside_m": 3.25}})
    net = DistanceNet.load(path)
    pts = np.random.default_rng(8).uniform(-2.0, 2.0, size=(5_000, 2))
    with torch.no_grad():
        eager = model(torch.from_numpy(pts.astype(np.float32))).double().numpy()
    np.testing.assert_allclose(net.mu(pts), eager, atol=1e-6)
    assert np.linalg.norm(net.mu(pts) @ net.G, axis=1).max() <= 1.0 + 1e-12


def test_only_centred_rectangles_are_supported() -> None:
    G, g = ROBOT.footprint.halfspaces()
    assert rectangle_half_extents(G, g) == pytest.approx((0.161, 0.110))
    with pytest.raises(UnsupportedFootprintError):
        rectangle_half_extents(G[[1, 0, 2, 3]], g)
    with pytest.raises(UnsupportedFootprintError):
        rectangle_half_extents(G, g + [0.1, 0.0, 0.0, 0.0])


def test_cli_check_distance_writes_the_figures(tmp_path: Path) -> None:
    out = tmp_path / "check.json"
    res = CliRunner().invoke(models_group, ["check-distance", "--no-timing", "--json", str(out)])
    assert res.exit_code == 0, res.output
    report = json.loads(out.read_text())
    for key in ("n_points", "max_abs_error_m", "p99_abs_error_m", "max_overestimate_m", "inside_max_abs_error_m",
                "inside_sign_errors", "max_dual_norm"):
        assert key in report
    assert report["n_points"] >= 100_000 and report["targets_met"] is True


def test_cli_check_distance_refuses_other_footprint(tmp_path: Path) -> None:
    src = Path(str(shipped_artifact_path().parents[2] / "calibration" / "robots" / "limo.yaml"))
    data = yaml.safe_load(src.read_text())
    data["footprint"]["length_m"] = 0.4
    robot_file = tmp_path / "wide.yaml"
    robot_file.write_text(yaml.safe_dump(data))
    res = CliRunner().invoke(models_group, ["check-distance", "--no-timing", "--robot", str(robot_file)])
    line = _one_line_error(res)
    assert "trained for footprint" in line and "0.4" in line


def _one_line_error(res, exit_code: int = 1) -> str:
    """The command failed with exit_code and one 'Error:' line, the last on stderr (training logs
    may come before it), no traceback."""
    assert res.exit_code == exit_code, res.output
    assert isinstance(res.exception, SystemExit), res.exception
    assert "Traceback" not in res.output
    lines = [line for line in res.stderr.splitlines() if line.strip()]
    errors = [line for line in lines if line.startswith("Error")]
    assert len(errors) == 1 and lines[-1] == errors[0], res.stderr
    return errors[0]


QUICK_CLI = ["--steps", "100", "--dataset-size", "20000", "--eval-points", "2000", "--threads", "1"]


def test_cli_train_distance_writes_nothing_when_targets_are_missed(tmp_path: Path) -> None:
    out, meta = tmp_path / "net.pt", tmp_path / "meta.json"
    res = CliRunner().invoke(models_group, ["train-distance", *QUICK_CLI, "--output", str(out), "--json", str(meta)])
    line = _one_line_error(res)
    assert "accuracy targets missed" in line and "max_abs_error_m" in line and "--force" in line
    assert '"max_abs_error_m"' in res.stdout  # the figures are printed
    assert not out.exists() and not meta.exists() and list(tmp_path.iterdir()) == []


def test_cli_train_distance_force_writes_the_model_and_json(tmp_path: Path) -> None:
    out, meta = tmp_path / "net.pt", tmp_path / "meta.json"
    res = CliRunner().invoke(models_group, ["train-distance", *QUICK_CLI, "--force", "--output", str(out),
                                            "--json", str(meta)])
    assert res.exit_code == 0, res.output
    assert "WARNING: accuracy targets missed" in res.stderr
    loaded = DistanceNet.load(out)
    assert loaded.metadata["training"]["steps_done"] == 100
    assert json.loads(meta.read_text())["integrity"] == loaded.metadata["integrity"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["meta.json", "net.pt"]  # no temporary left


def test_cli_train_distance_writes_a_model_that_meets_the_targets(tmp_path: Path, monkeypatch) -> None:
    import models.cli

    monkeypatch.setattr(models.cli, "DISTANCE_TARGETS", {"max_abs_error_m": 10.0, "max_dual_norm": 1.0 + 1e-5})
    out = tmp_path / "net.pt"
    res = CliRunner().invoke(models_group, ["train-distance", *QUICK_CLI, "--output", str(out)])
    assert res.exit_code == 0, res.output
    assert "WARNING" not in res.output
    assert DistanceNet.load(out).metadata["training"]["config"]["dataset_size"] == 20_000


def test_cli_train_distance_needs_an_output_and_never_writes_the_package_by_default(tmp_path: Path) -> None:
    shipped = shipped_artifact_path()
    before = shipped.read_bytes()
    res = CliRunner().invoke(models_group, ["train-distance", *QUICK_CLI])
    assert res.exit_code == 2 and "Missing option '--output'" in res.output
    for target in (shipped, shipped.with_name("other_distance_net.pt")):
        res = CliRunner().invoke(models_group, ["train-distance", *QUICK_CLI, "--output", str(target)])
        line = _one_line_error(res)
        assert "inside the installed package" in line and "--replace-shipped" in line
        assert "step" not in res.stderr.replace(line, "")  # refused before training
    assert shipped.read_bytes() == before and not shipped.with_name("other_distance_net.pt").exists()


@pytest.mark.parametrize("json_name, message", [("nodir/meta.json", "does not exist"), (".", "is a folder")])
def test_cli_train_distance_checks_the_json_path_before_training(tmp_path: Path, json_name: str,
                                                                 message: str) -> None:
    res = CliRunner().invoke(models_group, ["train-distance", *QUICK_CLI, "--output", str(tmp_path / "net.pt"),
                                            "--json", str(tmp_path / json_name)])
    line = _one_line_error(res)
    assert "JSON output" in line and message in line
    assert "step" not in res.stderr.replace(line, "") and not (tmp_path / "net.pt").exists()


def _bad_models(tmp_path: Path) -> dict[str, tuple[Path, str]]:
    data = shipped_artifact_path().read_bytes()
    (tmp_path / "garbage.pt").write_bytes(b"\x00\xffnot a model")
    (tmp_path / "truncated.pt").write_bytes(data[: len(data) // 2])
    (tmp_path / "empty.pt").write_bytes(b"")
    plain = tmp_path / "plain.pt"
    torch.jit.save(torch.jit.script(torch.nn.Linear(2, 4)), str(plain))
    (tmp_path / "adir").mkdir()
    return {
        "missing": (tmp_path / "absent.pt", "no such file"),
        "folder": (tmp_path / "adir", "is a folder"),
        "garbage": (tmp_path / "garbage.pt", "not a readable TorchScript file"),
        "truncated": (tmp_path / "truncated.pt", "not a readable TorchScript file"),
        "empty": (tmp_path / "empty.pt", "not a readable TorchScript file"),
        "plain TorchScript": (plain, "without 'dct_metadata.json' metadata"),
    }


@pytest.mark.filterwarnings("ignore::DeprecationWarning")
def test_cli_check_distance_bad_model_files_are_one_line_errors(tmp_path: Path) -> None:
    out = tmp_path / "report.json"
    out.write_text("previous report\n")
    for name, (path, message) in _bad_models(tmp_path).items():
        res = CliRunner().invoke(models_group, ["check-distance", "--no-timing", "--model", str(path),
                                                "--json", str(out)])
        line = _one_line_error(res)
        assert str(path) in line and message in line, (name, line)
    assert out.read_text() == "previous report\n"  # nothing written by a failed command


def test_cli_check_distance_json_path_is_checked_before_the_work(tmp_path: Path) -> None:
    shipped = shipped_artifact_path()
    cases = [(tmp_path / "nodir" / "out.json", "does not exist"), (tmp_path, "is a folder"),
             (shipped.with_name("report.json"), "inside the installed package"),
             (shipped, "also an input")]
    for path, message in cases:
        res = CliRunner().invoke(models_group, ["check-distance", "--no-timing", "--model", str(shipped),
                                                "--json", str(path)])
        line = _one_line_error(res)
        assert message in line, line
        assert '"max_abs_error_m"' not in res.stdout  # refused before the evaluation
    assert not shipped.with_name("report.json").exists()


def test_cli_check_distance_bad_robot_file_is_one_line(tmp_path: Path) -> None:
    line = _one_line_error(CliRunner().invoke(models_group, ["check-distance", "--no-timing", "--robot",
                                                             str(tmp_path / "absent.yaml")]))
    assert "absent.yaml" in line
    binary = tmp_path / "binary.yaml"
    binary.write_bytes(b"\xff\xfe\x00\x01footprint")
    line = _one_line_error(CliRunner().invoke(models_group, ["check-distance", "--no-timing", "--robot", str(binary)]))
    assert str(binary) in line
    src = Path(str(shipped_artifact_path().parents[2] / "calibration" / "robots" / "limo.yaml"))
    data = yaml.safe_load(src.read_text())
    data["footprint"]["length_m"] = "long"
    data["footprint"]["width_m"] = -1
    invalid = tmp_path / "invalid.yaml"
    invalid.write_text(yaml.safe_dump(data))
    line = _one_line_error(CliRunner().invoke(models_group, ["check-distance", "--no-timing", "--robot", str(invalid)]))
    assert str(invalid) in line and "footprint.length_m" in line and "footprint.width_m" in line


@pytest.mark.filterwarnings("ignore::DeprecationWarning")
def test_cli_upgrade_distance(tmp_path: Path) -> None:
    net = DistanceNet.load()
    v1 = tmp_path / "v1.pt"
    meta = {k: v for k, v in net.metadata.items() if k != "integrity"}
    torch.jit.save(net._module, str(v1), _extra_files={"dct_metadata.json": json.dumps(dict(meta, version=1))})
    line = _one_line_error(CliRunner().invoke(models_group, ["check-distance", "--no-timing", "--model", str(v1)]))
    assert "older format" in line and "upgrade-distance" in line
    line = _one_line_error(CliRunner().invoke(models_group, ["upgrade-distance", str(v1), "--output",
                                                             str(shipped_artifact_path())]))
    assert "--replace-shipped" in line
    line = _one_line_error(CliRunner().invoke(models_group, ["upgrade-distance", str(v1), "--output", str(v1)]))
    assert "also an input" in line
    out = tmp_path / "v2.pt"
    res = CliRunner().invoke(models_group, ["upgrade-distance", str(v1), "--output", str(out)])
    assert res.exit_code == 0, res.output
    assert DistanceNet.load(out).metadata["integrity"]["weights_sha256"] == net.metadata["integrity"]["weights_sha256"]
