"""The shipped distance net: loading checks, safety (weak duality), accuracy, MPC-facing API."""
from __future__ import annotations

import json
import zipfile
from pathlib import Path

import numpy as np
import pytest
import torch

from calibration.robot_description import Footprint, load_robot_description
from models.distance_check import evaluate_mu_function, sample_inside_points, sample_outside_points
from models.distance_net import METADATA_FILE, DistanceNet, shipped_artifact_path
from models.errors import DistanceNetFileError, FootprintMismatchError, InvalidPointsError
from models.footprint_dual import exact_dual

ROBOT = load_robot_description()
HL, HW = ROBOT.footprint.length_m / 2, ROBOT.footprint.width_m / 2


@pytest.fixture(scope="module")
def net() -> DistanceNet:
    return DistanceNet.load()


def test_shipped_artifact_is_small_frozen_torchscript_with_metadata(net: DistanceNet) -> None:
    path = shipped_artifact_path()
    assert path.stat().st_size < 1_000_000
    meta = net.metadata
    assert meta["format"] == "dct-distance-net" and meta["version"] == 2
    assert len(meta["integrity"]["weights_sha256"]) == 64 and meta["integrity"]["probe"]["n_points"] >= 300
    np.testing.assert_allclose(meta["footprint"]["vertices_m"], ROBOT.footprint.vertices())
    assert meta["training_domain"]["max_distance_outside_m"] >= 3.0
    assert meta["error_statistics"]["n_points"] >= 100_000
    assert meta["architecture"]["hidden_layers"] == 6 and meta["architecture"]["hidden_units"] == 32
    # Frozen: no trainable parameters left as attributes, only constants in the graph.
    assert len(list(net._module.parameters())) == 0
    assert torch.get_num_threads() == 1


def test_no_overestimate_outside_anywhere(net: DistanceNet) -> None:
    """Weak duality: ||G^T mu|| <= 1 makes the net's distance a lower bound, even far outside
    the training domain."""
    rng = np.random.default_rng(11)
    pts = np.vstack([sample_outside_points(rng, 30_000, HL, HW, 3.0), rng.uniform(-20.0, 20.0, size=(5_000, 2))])
    _, true = exact_dual(pts, net.G, net.g)
    pts, true = pts[true > 0], true[true > 0]
    mu, _, dist = net.dual(pts)
    assert np.linalg.norm(mu @ net.G, axis=1).max() <= 1.0 + 1e-12
    assert (mu >= 0).all()
    assert (dist - true).max() <= 1e-9


def test_accuracy_on_held_out_points(net: DistanceNet) -> None:
    stats = evaluate_mu_function(net.mu, net.G, net.g, n_points=100_000, seed=99)
    assert stats["max_abs_error_m"] <= 5e-3
    assert stats["p99_abs_error_m"] <= 1e-3
    assert stats["max_overestimate_m"] <= 1e-5
    assert stats["inside_sign_errors"] == 0
    assert stats["inside_max_abs_error_m"] <= 2e-2
    assert stats["max_dual_norm"] <= 1.0 + 1e-5


def test_inside_is_negative_signed_distance(net: DistanceNet) -> None:
    rng = np.random.default_rng(12)
    pts = sample_inside_points(rng, 20_000, HL, HW)
    _, true = exact_dual(pts, net.G, net.g)
    d = net.distance(pts)
    assert (d < 0).all()
    assert np.abs(d - true).max() <= 2e-2
    centre = net.distance(np.zeros((1, 2)))[0]
    assert centre == pytest.approx(-HW, abs=5e-3)


def test_dual_gives_the_mpc_linear_constraint(net: DistanceNet) -> None:
    """distance = lambda^T (t - p_w) - mu^T g with lambda = -R G^T mu, checked at a rotated pose,
    and -lambda approximates the true gradient of the distance with respect to the point."""
    rng = np.random.default_rng(13)
    yaw, t = 0.7, np.array([1.0, -2.0])
    R = np.array([[np.cos(yaw), -np.sin(yaw)], [np.sin(yaw), np.cos(yaw)]])
    p_robot = sample_outside_points(rng, 2_000, HL, HW, 2.0)
    p_world = p_robot @ R.T + t
    mu, lam_robot, dist = net.dual(p_robot)
    np.testing.assert_allclose(lam_robot, -(mu @ net.G))
    lam_world = lam_robot @ R.T
    np.testing.assert_allclose(np.einsum("nk,nk->n", lam_world, t - p_world) - mu @ net.g, dist, atol=1e-12)
    true_mu, _ = exact_dual(p_robot, net.G, net.g)
    true_grad = true_mu @ net.G  # unit normal from the footprint to the point
    cos = np.einsum("nk,nk->n", -lam_robot, true_grad) / np.linalg.norm(lam_robot, axis=1)
    assert np.quantile(cos, 0.01) > 0.999


def test_symmetry_of_the_rectangle(net: DistanceNet) -> None:
    rng = np.random.default_rng(14)
    p = rng.uniform(0.01, 1.0, size=(500, 2))
    d = net.distance(p)
    for sx, sy in ((-1, 1), (1, -1), (-1, -1)):
        np.testing.assert_allclose(net.distance(p * [sx, sy]), d, atol=1e-7)


def test_empty_and_bad_inputs(net: DistanceNet) -> None:
    mu, lam, d = net.dual(np.zeros((0, 2)))
    assert mu.shape == (0, 4) and lam.shape == (0, 2) and d.shape == (0,)
    for bad in (np.zeros(2), np.zeros((4, 3)), [[np.nan, 1.0]], [[1.0, -np.inf]]):
        with pytest.raises(InvalidPointsError):
            net.distance(bad)


def test_footprint_mismatch_is_refused_with_both_footprints() -> None:
    other = ROBOT.model_copy(update={"footprint": Footprint(length_m=0.5, width_m=0.3)})
    with pytest.raises(FootprintMismatchError) as info:
        DistanceNet.load(None, other)
    msg = str(info.value)
    assert "0.322" in msg and "0.5" in msg and "0.3" in msg and "train-distance" in msg


@pytest.mark.filterwarnings("ignore::DeprecationWarning")
def test_missing_and_invalid_files(tmp_path: Path) -> None:
    with pytest.raises(DistanceNetFileError, match="no such file"):
        DistanceNet.load(tmp_path / "absent.pt")
    garbage = tmp_path / "garbage.pt"
    garbage.write_bytes(b"not a model")
    with pytest.raises(DistanceNetFileError, match="TorchScript"):
        DistanceNet.load(garbage)
    plain = tmp_path / "plain.pt"
    torch.jit.save(torch.jit.script(torch.nn.Linear(2, 4)), str(plain))
    with pytest.raises(DistanceNetFileError, match="metadata"):
        DistanceNet.load(plain)


def _with_metadata(src: Path, dst: Path, meta: dict) -> None:
    """Copy a TorchScript zip, replacing our metadata entry."""
    with zipfile.ZipFile(src) as zin, zipfile.ZipFile(dst, "w") as zout:
        for item in zin.infolist():
            data = zin.read(item.filename)
            if item.filename.endswith("extra/" + METADATA_FILE):
                data = json.dumps(meta).encode()
            zout.writestr(item, data)


def test_wrong_version_or_format_is_refused(tmp_path: Path, net: DistanceNet) -> None:
    bad_version = tmp_path / "v99.pt"
    _with_metadata(shipped_artifact_path(), bad_version, dict(net.metadata, version=99))
    with pytest.raises(DistanceNetFileError, match="version 99"):
        DistanceNet.load(bad_version)
    bad_format = tmp_path / "fmt.pt"
    _with_metadata(shipped_artifact_path(), bad_format, dict(net.metadata, format="other"))
    with pytest.raises(DistanceNetFileError, match="format"):
        DistanceNet.load(bad_format)
    ok = tmp_path / "same.pt"
    _with_metadata(shipped_artifact_path(), ok, net.metadata)
    assert DistanceNet.load(ok).metadata == net.metadata


def test_old_format_is_refused_with_the_way_to_upgrade(tmp_path: Path, net: DistanceNet) -> None:
    old = tmp_path / "v1.pt"
    v1_meta = {k: v for k, v in net.metadata.items() if k != "integrity"}
    _with_metadata(shipped_artifact_path(), old, dict(v1_meta, version=1))
    with pytest.raises(DistanceNetFileError, match=r"version 1 is an older format.*upgrade-distance"):
        DistanceNet.load(old)


def test_folder_and_truncated_archive_are_refused(tmp_path: Path) -> None:
    with pytest.raises(DistanceNetFileError, match="is a folder"):
        DistanceNet.load(tmp_path)
    data = shipped_artifact_path().read_bytes()
    for cut in (len(data) // 2, len(data) - 30, 100):
        truncated = tmp_path / f"cut{cut}.pt"
        truncated.write_bytes(data[:cut])
        with pytest.raises(DistanceNetFileError, match="not a readable TorchScript file") as info:
            DistanceNet.load(truncated)
        assert "\n" not in str(info.value) and str(truncated) in str(info.value)
