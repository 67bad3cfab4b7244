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
    assert res.exit_code != 0
    assert "trained for footprint" in res.output and "0.4" in res.output


def test_cli_train_distance_short(tmp_path: Path) -> None:
    out = tmp_path / "net.pt"
    res = CliRunner().invoke(models_group, ["train-distance", "--steps", "100", "--threads", "1",
                                            "--output", str(out), "--json", str(tmp_path / "meta.json")])
    assert res.exit_code == 0, res.output
    assert DistanceNet.load(out).metadata["training"]["steps_done"] == 100
    assert json.loads((tmp_path / "meta.json").read_text())["error_statistics"]["n_points"] >= 100_000
