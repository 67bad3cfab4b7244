"""Integrity of a distance-net artifact at load: weight checksum, finite weights, probe set
(stored outputs and the exact distance within the stored bound), and the v1 -> v2 upgrade."""
from __future__ import annotations

import copy
import json
import warnings
import zipfile
from pathlib import Path

import numpy as np
import pytest
import torch

from calibration.robot_description import load_robot_description
from models.distance_integrity import (
    ERROR_BOUND_MARGIN_M,
    MIN_PROBE_POINTS,
    probe_points,
    weight_tensors,
    weights_checksum,
)
from models.distance_net import METADATA_FILE, DistanceNet, save_artifact, shipped_artifact_path, upgrade_artifact
from models.errors import DistanceNetFileError
from models.footprint_dual import exact_dual

ROBOT = load_robot_description()
HL, HW = ROBOT.footprint.length_m / 2, ROBOT.footprint.width_m / 2
pytestmark = pytest.mark.filterwarnings("ignore::DeprecationWarning")


@pytest.fixture(scope="module")
def net() -> DistanceNet:
    return DistanceNet.load()


def _load_module(path: Path) -> torch.jit.ScriptModule:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)
        return torch.jit.load(str(path))


def _save_with_metadata(module: torch.jit.ScriptModule, path: Path, meta: dict) -> Path:
    """Save a (modified) module with the given metadata as is, the way a hand edit would."""
    torch.jit.save(module, str(path), _extra_files={METADATA_FILE: json.dumps(meta)})
    return path


def _constants(module: torch.jit.ScriptModule) -> dict[str, torch.Tensor]:
    return module.code_with_constants[1].const_mapping


def _with_integrity(meta: dict, **changes) -> dict:
    out = copy.deepcopy(meta)
    out["integrity"].update(changes)
    return out


def test_shipped_artifact_loads_and_its_record_matches_its_weights(net: DistanceNet) -> None:
    record = net.metadata["integrity"]
    assert record["weights_sha256"] == weights_checksum(weight_tensors(net._module))
    assert record["n_weight_tensors"] == 15  # 7 linear layers (weight, bias) + the half extents
    assert MIN_PROBE_POINTS <= record["probe"]["n_points"] <= 1_000
    stats = net.metadata["error_statistics"]
    assert record["error_bound"]["outside_m"] >= stats["max_abs_error_m"] + ERROR_BOUND_MARGIN_M
    assert record["error_bound"]["inside_m"] >= stats["inside_max_abs_error_m"] + ERROR_BOUND_MARGIN_M
    assert record["error_bound"]["outside_m"] < 1e-3  # the bound is tight: it checks something


def test_probe_set_surrounds_and_fills_the_footprint() -> None:
    pts = probe_points(HL, HW)
    assert pts.shape[0] >= 300 and np.isfinite(pts).all()
    np.testing.assert_array_equal(pts, probe_points(HL, HW))  # a fixed rule
    G, g = ROBOT.footprint.halfspaces()
    _, d = exact_dual(pts, G, g)
    assert (d > 0).sum() >= 300 and (d < 0).sum() >= 100
    assert d.max() == pytest.approx(3.0) and (d[d > 0] <= 1e-2 + 1e-12).sum() >= 80  # near and far
    for sx, sy in ((1, 1), (-1, 1), (-1, -1), (1, -1)):  # every quadrant, corners included
        assert ((pts[:, 0] * sx > HL) & (pts[:, 1] * sy > HW)).sum() >= 16
    assert np.any(np.all(np.abs(pts) < 1e-12, axis=1))  # the centre


def _assert_same_record(a, b, what: str = "record") -> None:
    """Equal, except that recomputed floats (probe outputs, error figures) may differ in the last
    bits between CPUs (torch picks other kernels on another instruction set): within 1e-6."""
    if isinstance(a, dict):
        assert isinstance(b, dict) and a.keys() == b.keys(), what
        for k in a:
            _assert_same_record(a[k], b[k], f"{what}.{k}")
    elif isinstance(a, (list, tuple)) or isinstance(a, float):
        np.testing.assert_allclose(np.asarray(a, dtype=float), np.asarray(b, dtype=float), rtol=0, atol=1e-6,
                                   err_msg=what)
    else:
        assert a == b, what


def test_checksum_is_stable_on_resave_and_changes_with_any_weight(tmp_path: Path, net: DistanceNet) -> None:
    resaved = save_artifact(net._module, tmp_path / "resaved.pt", net.metadata)
    again = save_artifact(DistanceNet.load(resaved)._module, tmp_path / "again.pt", net.metadata)
    again_record = DistanceNet.load(again).metadata["integrity"]
    assert again_record["weights_sha256"] == net.metadata["integrity"]["weights_sha256"]
    _assert_same_record(again_record, net.metadata["integrity"])
    module = _load_module(shipped_artifact_path())
    reference = weights_checksum(weight_tensors(module))
    seen = {reference}
    for tensor in _constants(module).values():
        flat = tensor.view(-1)
        old = float(flat[-1])
        flat[-1] = float(np.nextafter(np.float32(old), np.float32(np.inf)))  # one ulp of one weight
        seen.add(weights_checksum(weight_tensors(module)))
        flat[-1] = old
    assert len(seen) == 1 + len(_constants(module))
    assert weights_checksum(weight_tensors(module)) == reference
    # Two weight matrices of the same shape swapped: same set of numbers, another net.
    c = _constants(module)
    w3, w5 = c["c3"].clone(), c["c5"].clone()
    c["c3"].copy_(w5)
    c["c5"].copy_(w3)
    assert weights_checksum(weight_tensors(module)) != reference


def test_tampered_weight_is_refused_for_the_checksum(tmp_path: Path, net: DistanceNet) -> None:
    module = _load_module(shipped_artifact_path())
    _constants(module)["c5"][3, 7] += 1e-3
    path = _save_with_metadata(module, tmp_path / "tampered.pt", net.metadata)
    with pytest.raises(DistanceNetFileError, match="checksum mismatch") as info:
        DistanceNet.load(path)
    assert str(path) in str(info.value)


def test_flipped_bit_in_the_archive_is_refused(tmp_path: Path) -> None:
    """torch does not check the zip's CRC: only our checksum sees a flipped bit in a weight record."""
    data = bytearray(shipped_artifact_path().read_bytes())
    with zipfile.ZipFile(shipped_artifact_path()) as z:
        name = next(n for n in z.namelist() if n.endswith("constants/5"))
        record = z.read(name)
    offset = data.find(record)
    assert offset > 0 and data.find(record, offset + 1) < 0
    data[offset + 101] ^= 0x01
    path = tmp_path / "flipped.pt"
    path.write_bytes(bytes(data))
    with pytest.raises(DistanceNetFileError, match="checksum mismatch"):
        DistanceNet.load(path)


def test_nan_weight_is_refused(tmp_path: Path, net: DistanceNet) -> None:
    module = _load_module(shipped_artifact_path())
    _constants(module)["c7"][0, 0] = float("nan")
    # Old checksum: refused for the checksum already.
    path = _save_with_metadata(module, tmp_path / "nan_old.pt", net.metadata)
    with pytest.raises(DistanceNetFileError, match="checksum mismatch"):
        DistanceNet.load(path)
    # Even with a checksum recomputed for the NaN weights, the finiteness check refuses it.
    meta = _with_integrity(net.metadata, weights_sha256=weights_checksum(weight_tensors(module)))
    path = _save_with_metadata(module, tmp_path / "nan_new.pt", meta)
    with pytest.raises(DistanceNetFileError, match=r"non-finite weights: constant:c7 \(32, 32\) has 1"):
        DistanceNet.load(path)
    with pytest.raises(DistanceNetFileError, match="non-finite weights"):
        save_artifact(module, tmp_path / "never.pt", net.metadata)
    assert not (tmp_path / "never.pt").exists()


def test_altered_probe_results_are_refused(tmp_path: Path, net: DistanceNet) -> None:
    module = _load_module(shipped_artifact_path())
    for key, row, delta, message in (("distance_m", 17, 1e-4, "distance by"), ("mu", 250, 1e-4, "mu by"),
                                     ("exact_distance_m", 3, 1e-6, "stored exact probe distances")):
        meta = copy.deepcopy(net.metadata)
        values = meta["integrity"]["probe"][key]
        if key == "mu":
            values[row][0] += delta
        else:
            values[row] += delta
        path = _save_with_metadata(module, tmp_path / f"{key}.pt", meta)
        with pytest.raises(DistanceNetFileError, match=message):
            DistanceNet.load(path)
    meta = copy.deepcopy(net.metadata)
    meta["integrity"]["probe"]["distance_m"] = meta["integrity"]["probe"]["distance_m"][:-1]
    with pytest.raises(DistanceNetFileError, match="distance_m' has shape"):
        DistanceNet.load(_save_with_metadata(module, tmp_path / "short.pt", meta))
    meta = copy.deepcopy(net.metadata)
    del meta["integrity"]["probe"]
    with pytest.raises(DistanceNetFileError, match="probe record rule None"):
        DistanceNet.load(_save_with_metadata(module, tmp_path / "noprobe.pt", meta))


def test_stored_outputs_are_checked_against_what_the_net_computes(tmp_path: Path, net: DistanceNet) -> None:
    """A weight change with a checksum recomputed to match (a hand 'fix') still fails: the net no
    longer reproduces its stored probe outputs."""
    module = _load_module(shipped_artifact_path())
    _constants(module)["c13"][0, 5] += 0.05  # output layer, front dual variable
    meta = _with_integrity(net.metadata, weights_sha256=weights_checksum(weight_tensors(module)))
    path = _save_with_metadata(module, tmp_path / "changed.pt", meta)
    with pytest.raises(DistanceNetFileError, match="probe outputs differ from the stored ones"):
        DistanceNet.load(path)


def test_violated_error_bound_is_refused(tmp_path: Path, net: DistanceNet) -> None:
    module = _load_module(shipped_artifact_path())
    for region in ("outside", "inside"):
        bound = dict(net.metadata["integrity"]["error_bound"], **{f"{region}_m": 1e-6})
        path = _save_with_metadata(module, tmp_path / f"{region}.pt", _with_integrity(net.metadata, error_bound=bound))
        message = f"exceeds its stored {region} error bound 1e-06 m at probe point"
        with pytest.raises(DistanceNetFileError, match=message):
            DistanceNet.load(path)
    bound = dict(net.metadata["integrity"]["error_bound"], outside_m="NaN")
    with pytest.raises(DistanceNetFileError, match="not finite and positive"):
        DistanceNet.load(_save_with_metadata(module, tmp_path / "nanbound.pt",
                                             _with_integrity(net.metadata, error_bound=bound)))


def test_a_module_that_is_not_the_net_is_refused(tmp_path: Path, net: DistanceNet) -> None:
    other = torch.jit.freeze(torch.jit.script(torch.nn.Linear(2, 3).eval()))
    meta = _with_integrity(net.metadata, weights_sha256=weights_checksum(weight_tensors(other)))
    path = _save_with_metadata(other, tmp_path / "linear.pt", meta)
    message = "module fails on the probe points: ValueError: the module returned shape"
    with pytest.raises(DistanceNetFileError, match=message):
        DistanceNet.load(path)


def _as_version_1(src: Path, dst: Path, module: torch.jit.ScriptModule | None = None) -> Path:
    meta = _load_metadata(src)
    v1 = {k: v for k, v in meta.items() if k != "integrity"}
    v1["version"] = 1
    return _save_with_metadata(module if module is not None else _load_module(src), dst, v1)


def _load_metadata(path: Path) -> dict:
    extra = {METADATA_FILE: ""}
    torch.jit.load(str(path), _extra_files=extra)
    return json.loads(extra[METADATA_FILE])


def test_upgrade_of_a_version_1_artifact_keeps_the_weights(tmp_path: Path, net: DistanceNet) -> None:
    old = _as_version_1(shipped_artifact_path(), tmp_path / "v1.pt")
    meta = upgrade_artifact(old, tmp_path / "v2.pt", ROBOT)
    assert meta["version"] == 2 and meta["upgraded_from_version"] == 1
    assert meta["integrity"]["weights_sha256"] == net.metadata["integrity"]["weights_sha256"]
    _assert_same_record(meta["integrity"], net.metadata["integrity"])
    _assert_same_record(meta["error_statistics"], net.metadata["error_statistics"])
    upgraded = DistanceNet.load(tmp_path / "v2.pt")
    pts = np.random.default_rng(3).uniform(-2, 2, size=(1_000, 2))
    np.testing.assert_array_equal(upgraded.dual(pts)[2], net.dual(pts)[2])
    with pytest.raises(DistanceNetFileError, match="already version 2"):
        upgrade_artifact(tmp_path / "v2.pt", tmp_path / "v3.pt", ROBOT)


def test_upgrade_refuses_a_version_1_artifact_whose_weights_changed(tmp_path: Path) -> None:
    module = _load_module(shipped_artifact_path())
    _constants(module)["c11"][4, 4] += 0.05
    old = _as_version_1(shipped_artifact_path(), tmp_path / "v1.pt", module)
    with pytest.raises(DistanceNetFileError, match="held-out figures differ from the stored ones"):
        upgrade_artifact(old, tmp_path / "v2.pt", ROBOT)
    assert not (tmp_path / "v2.pt").exists()
