"""The distance net (paper IV-C-1, NeuPAN's DUNE): point in the robot frame -> dual variables mu.

For a point p in the robot frame and the footprint {x : G x <= g}, the net predicts mu >= 0
(one per edge). The exported TorchScript module scales mu so that ||G^T mu|| <= 1 (divides
by max(1, ||G^T mu||)); the numpy wrapper repeats that scaling in float64. Then by weak
duality the net's distance mu^T (G p - g) never exceeds the true distance outside the
footprint: it errs only on the safe side, wherever the point is, even outside the training
domain. Inside, mu^T (G p - g) is negative: a signed distance (beyond NeuPAN's 0).

For the MPC, at robot pose (R, t) and a world point p_w:
    distance = mu^T (G R^T (p_w - t) - g) = lambda^T (t - p_w) - mu^T g,  lambda = -R G^T mu,
so lambda is the gradient of the distance with respect to the robot position t (paper
eq. 11: mu^T G + lambda^T R = 0) and -lambda the gradient with respect to the point.
`dual()` returns lam_robot = -G^T mu (R = I, robot frame); rotate it with R for the world frame.

The net exploits the rectangle's symmetry: it sees the point folded into the first quadrant
(|x|, |y|), predicts the two dual variables of the front and left edges there, and the module
unfolds them onto (front, left, rear, right) by the signs of x and y.
"""
from __future__ import annotations

import io
import json
import warnings
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn

from calibration.outputs import atomic_write_bytes
from models.distance_integrity import (
    IntegrityError,
    build_record,
    nonfinite_weights,
    verify_probes,
    verify_weights,
    weight_tensors,
)
from models.errors import DistanceNetFileError, FootprintMismatchError, UnsupportedFootprintError
from models.footprint_dual import validate_points

ARTIFACT_FORMAT = "dct-distance-net"
# Version 2 added the integrity record (weight checksum, probe set, error bound).
ARTIFACT_VERSION = 2
# Older versions this code recognises (to say how to upgrade them) but does not load.
LEGACY_VERSIONS = (1,)
METADATA_FILE = "dct_metadata.json"
SHIPPED_ARTIFACT = "limo_distance_net.pt"
# Footprints are compared to this tolerance (m) when an artifact is loaded.
FOOTPRINT_TOLERANCE_M = 1e-6
# Rows of G for a centred, axis-aligned rectangle, as the robot description orders them.
RECTANGLE_NORMALS = np.array([[1.0, 0.0], [0.0, 1.0], [-1.0, 0.0], [0.0, -1.0]])


def rectangle_half_extents(G: np.ndarray, g: np.ndarray) -> tuple[float, float]:
    """(half_length_m, half_width_m) of a centred axis-aligned rectangle given as (G, g)."""
    G = np.asarray(G, dtype=np.float64)
    g = np.asarray(g, dtype=np.float64)
    if G.shape != (4, 2) or g.shape != (4,) or not np.allclose(G, RECTANGLE_NORMALS, atol=1e-12):
        raise UnsupportedFootprintError(
            "the distance net supports a centred, axis-aligned rectangular footprint with rows "
            f"(front, left, rear, right) = {RECTANGLE_NORMALS.tolist()}; got G = {G.tolist()}"
        )
    if not (np.isclose(g[0], g[2]) and np.isclose(g[1], g[3]) and np.all(g > 0)):
        raise UnsupportedFootprintError(f"the footprint rectangle must be centred on base_link; got g = {g.tolist()}")
    return float(g[0]), float(g[1])


class FoldedDualMLP(nn.Module):
    """6 x 32 ReLU MLP on the folded point; forward returns scaled mu (N, 4) in row order
    (front, left, rear, right)."""

    def __init__(self, half_length_m: float, half_width_m: float, input_scale_m: float = 0.5,
                 hidden: int = 32, hidden_layers: int = 6) -> None:
        super().__init__()
        self.register_buffer("half_extent_m", torch.tensor([half_length_m, half_width_m], dtype=torch.float32))
        self.input_scale_m = float(input_scale_m)
        layers: list[nn.Module] = [nn.Linear(2, hidden), nn.ReLU()]
        for _ in range(hidden_layers - 1):
            layers += [nn.Linear(hidden, hidden), nn.ReLU()]
        layers.append(nn.Linear(hidden, 2))
        self.mlp = nn.Sequential(*layers)

    def folded_raw(self, folded_points: torch.Tensor) -> torch.Tensor:
        """Pre-activation output (N, 2) for points already folded into the first quadrant."""
        return self.mlp((folded_points - self.half_extent_m) / self.input_scale_m)

    def forward(self, points: torch.Tensor) -> torch.Tensor:
        folded = torch.abs(points)
        m = torch.relu(self.folded_raw(folded))
        norm = torch.sqrt((m * m).sum(dim=1, keepdim=True))
        m = m / torch.clamp(norm, min=1.0)
        zero = torch.zeros_like(m[:, 0])
        pos_x = points[:, 0] >= 0.0
        pos_y = points[:, 1] >= 0.0
        return torch.stack(
            [
                torch.where(pos_x, m[:, 0], zero),
                torch.where(pos_y, m[:, 1], zero),
                torch.where(pos_x, zero, m[:, 0]),
                torch.where(pos_y, zero, m[:, 1]),
            ],
            dim=1,
        )


def shipped_artifact_path() -> Path:
    """Path of the trained LIMO distance net shipped in models/artifacts/."""
    return Path(str(resources.files("models") / "artifacts" / SHIPPED_ARTIFACT))


def module_dual(module: Any, points: np.ndarray, G: np.ndarray,
                g: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(mu (N, 4), lam_robot (N, 2) = -G^T mu, signed distance (N,)) of `module` at validated points
    (N, 2) float64, N > 0; mu rescaled in float64 so that ||G^T mu|| <= 1 beyond float32 rounding."""
    with torch.inference_mode():
        mu = module(torch.from_numpy(points.astype(np.float32))).numpy().astype(np.float64)
    if mu.shape != (points.shape[0], G.shape[0]):
        raise ValueError(f"the module returned shape {mu.shape} for {points.shape[0]} points, expected "
                         f"({points.shape[0]}, {G.shape[0]})")
    gt_mu = mu @ G  # (N, 2) = G^T mu per point
    scale = 1.0 / np.maximum(np.sqrt(gt_mu[:, 0] * gt_mu[:, 0] + gt_mu[:, 1] * gt_mu[:, 1]), 1.0)
    mu *= scale[:, None]
    gt_mu *= scale[:, None]
    # mu^T (G p - g) = (G^T mu) . p - mu . g
    distance = gt_mu[:, 0] * points[:, 0] + gt_mu[:, 1] * points[:, 1] - mu @ g
    return mu, -gt_mu, distance


def _one_line(exc: BaseException) -> str:
    """The first sentence of an exception's first line (torch's may carry advice and a C++ trace)."""
    text = str(exc).strip()
    return text.splitlines()[0].split(". ")[0] if text else type(exc).__name__


def _frozen(module: nn.Module | torch.jit.ScriptModule) -> torch.jit.ScriptModule:
    """`module` as a frozen TorchScript module in eval mode, float32."""
    if isinstance(module, torch.jit.ScriptModule):
        if not list(module.parameters()):
            return module  # already frozen (a loaded artifact)
        return torch.jit.freeze(module.eval())
    return torch.jit.freeze(torch.jit.script(module.eval().to(torch.float32)))


def _torchscript_bytes(frozen: torch.jit.ScriptModule, meta: dict[str, Any]) -> bytes:
    buffer = io.BytesIO()
    torch.jit.save(frozen, buffer, _extra_files={METADATA_FILE: json.dumps(meta, indent=1, allow_nan=False)})
    return buffer.getvalue()


def _footprint_halfspaces(meta: dict[str, Any], where: str) -> tuple[np.ndarray, np.ndarray]:
    """(G, g) of the footprint in an artifact's metadata, checked to be a supported rectangle."""
    try:
        G = np.asarray(meta["footprint"]["G"], dtype=np.float64)
        g = np.asarray(meta["footprint"]["g"], dtype=np.float64)
    except (KeyError, TypeError, ValueError) as exc:
        raise DistanceNetFileError(f"{where}: metadata footprint has no valid 'G' and 'g'") from exc
    rectangle_half_extents(G, g)  # UnsupportedFootprintError (a DistanceNetError) names the problem
    return G, g


def save_artifact(module: nn.Module | torch.jit.ScriptModule, path: str | Path, metadata: dict[str, Any]) -> Path:
    """Freeze `module` (a FoldedDualMLP, or an already frozen TorchScript net) and save it as TorchScript
    with our metadata and its integrity record (models.distance_integrity) as an extra file.

    metadata needs 'footprint' (with 'G' and 'g', as distance_training.footprint_metadata makes it) and
    'training_domain'; its 'error_statistics' (held-out check), when present, set the error bound.
    The artifact is checked as `DistanceNet.load` checks it before it is written, and written
    atomically (temporary file in the same folder, then rename): the folder must exist.
    """
    path = Path(path)
    where = f"distance-net artifact {path}"
    meta = {k: v for k, v in metadata.items() if k not in ("format", "version", "integrity")}
    G, g = _footprint_halfspaces(meta, where)
    with warnings.catch_warnings():  # TorchScript is deprecated upstream but is our deployment format
        warnings.simplefilter("ignore", DeprecationWarning)
        frozen = _frozen(module)
        try:
            record = build_record(weight_tensors(frozen), lambda p: module_dual(frozen, p, G, g), G, g,
                                  meta.get("error_statistics"))
        except IntegrityError as exc:
            raise DistanceNetFileError(f"{where}: not saved: {exc}") from exc
        meta.update(format=ARTIFACT_FORMAT, version=ARTIFACT_VERSION, integrity=record)
        data = _torchscript_bytes(frozen, meta)
        reloaded, reloaded_meta = _parse_artifact(data, where)
        _verify_weights(reloaded, reloaded_meta, where)
        _verify_probes(reloaded, reloaded_meta, G, g, where)
    atomic_write_bytes(path, data)
    return path


def _read_artifact(path: Path, accept_versions: tuple[int, ...] = (ARTIFACT_VERSION,)
                   ) -> tuple[torch.jit.ScriptModule, dict[str, Any]]:
    where = f"distance-net artifact {path}"
    if path.is_dir():
        raise DistanceNetFileError(f"{where}: is a folder, not a file")
    if not path.is_file():
        raise DistanceNetFileError(f"{where}: no such file")
    return _parse_artifact(str(path), where, accept_versions)


def _parse_artifact(source: str | bytes, where: str, accept_versions: tuple[int, ...] = (ARTIFACT_VERSION,)
                    ) -> tuple[torch.jit.ScriptModule, dict[str, Any]]:
    """Load TorchScript (a file name, or the bytes of one) and check our metadata's format, version
    and keys."""
    extra = {METADATA_FILE: ""}
    try:
        with warnings.catch_warnings():  # TorchScript is deprecated upstream but is our deployment format
            warnings.simplefilter("ignore", DeprecationWarning)
            # torch reads a named file itself: its errors say more than a stream's ("istream reader failed")
            stream = io.BytesIO(source) if isinstance(source, bytes) else source
            module = torch.jit.load(stream, map_location="cpu", _extra_files=extra)
    except Exception as exc:  # torch raises RuntimeError/ValueError/zipfile errors alike
        raise DistanceNetFileError(f"{where}: not a readable TorchScript file "
                                   f"(truncated, corrupted or another format): {_one_line(exc)}") from exc
    raw = extra[METADATA_FILE]
    if not raw:
        raise DistanceNetFileError(
            f"{where}: TorchScript without '{METADATA_FILE}' metadata (not exported by `dct models train-distance`)"
        )
    try:
        meta = json.loads(raw)
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise DistanceNetFileError(f"{where}: metadata is not valid JSON: {exc}") from exc
    if not isinstance(meta, dict) or meta.get("format") != ARTIFACT_FORMAT:
        raise DistanceNetFileError(f"{where}: metadata format is not '{ARTIFACT_FORMAT}'")
    version = meta.get("version")
    if isinstance(version, bool) or not isinstance(version, int):
        raise DistanceNetFileError(f"{where}: metadata version {version!r} is not an integer")
    if version in LEGACY_VERSIONS and version not in accept_versions:
        raise DistanceNetFileError(
            f"{where}: metadata version {version} is an older format without the integrity record (weight "
            f"checksum, probe set); this code reads version {ARTIFACT_VERSION}: re-save it with "
            "`dct models upgrade-distance` (same weights, re-checked) or retrain with `dct models train-distance`"
        )
    if version not in accept_versions:
        raise DistanceNetFileError(
            f"{where}: metadata version {version!r}, this code reads version {ARTIFACT_VERSION}; "
            "retrain with `dct models train-distance`"
        )
    required = ("footprint", "training_domain") + (("integrity",) if version == ARTIFACT_VERSION else ())
    for key in required:
        if key not in meta:
            raise DistanceNetFileError(f"{where}: metadata lacks '{key}'")
    return module, meta


def _verify_weights(module: torch.jit.ScriptModule, meta: dict[str, Any], where: str) -> None:
    """Checksum and finiteness of the weights against the integrity record."""
    try:
        verify_weights(meta["integrity"], weight_tensors(module))
    except IntegrityError as exc:
        raise DistanceNetFileError(f"{where}: integrity check failed: {exc}") from exc


def _verify_probes(module: torch.jit.ScriptModule, meta: dict[str, Any], G: np.ndarray, g: np.ndarray,
                   where: str) -> None:
    """The probe set against the stored outputs and the exact distance (within the stored bound)."""
    try:
        verify_probes(meta["integrity"], lambda p: module_dual(module, p, G, g), G, g)
    except IntegrityError as exc:
        raise DistanceNetFileError(f"{where}: integrity check failed: {exc}") from exc


def _check_footprint(meta: dict[str, Any], robot: Any, path: Path) -> None:
    """Refuse an artifact trained for another footprint than the robot description's."""
    robot_vertices = np.asarray(robot.footprint.vertices(), dtype=np.float64)
    try:
        art_vertices = np.asarray(meta["footprint"]["vertices_m"], dtype=np.float64)
    except (KeyError, TypeError, ValueError) as exc:
        raise DistanceNetFileError(
            f"distance-net artifact {path}: metadata footprint has no valid 'vertices_m'"
        ) from exc
    if art_vertices.shape != robot_vertices.shape or not np.allclose(
        art_vertices, robot_vertices, atol=FOOTPRINT_TOLERANCE_M, rtol=0.0
    ):
        name = getattr(robot, "name", "?")
        raise FootprintMismatchError(
            f"distance-net artifact {path} was trained for footprint vertices {art_vertices.tolist()} "
            f"(length x width {meta['footprint'].get('length_m')} x {meta['footprint'].get('width_m')} m), "
            f"but robot description '{name}' has footprint vertices {robot_vertices.tolist()} "
            f"(length x width {robot.footprint.length_m} x {robot.footprint.width_m} m); "
            "retrain with `dct models train-distance`"
        )


# Held-out figures recomputed by `upgrade_artifact` must match the stored ones to this (float32
# inference on another CPU may differ in the last bits; a changed weight moves them far more).
UPGRADE_FIGURE_TOLERANCE = 1e-6


def upgrade_artifact(source: str | Path, output: str | Path, robot: Any) -> dict[str, Any]:
    """Re-save an older-version artifact (same frozen weights) in the current format, adding the
    integrity record; returns the new metadata.

    The older format has no checksum, so the net is re-checked instead: its weights must be
    finite, its footprint the robot description's, and its held-out error figures, recomputed
    with the stored seed and point count, must equal the stored ones (UPGRADE_FIGURE_TOLERANCE).
    """
    from models.distance_check import evaluate_mu_function

    source = Path(source)
    where = f"distance-net artifact {source}"
    module, meta = _read_artifact(source, accept_versions=LEGACY_VERSIONS + (ARTIFACT_VERSION,))
    if meta["version"] == ARTIFACT_VERSION:
        raise DistanceNetFileError(f"{where}: already version {ARTIFACT_VERSION}; nothing to upgrade")
    bad = nonfinite_weights(weight_tensors(module))
    if bad:
        raise DistanceNetFileError(f"{where}: not upgraded: non-finite weights: " + "; ".join(bad))
    _check_footprint(meta, robot, source)
    G, g = (np.asarray(a, dtype=np.float64) for a in robot.footprint.halfspaces())
    torch.set_num_threads(1)
    stored = meta.get("error_statistics")
    try:
        n_points, seed = int(stored["n_points"]), int(stored["seed"])
    except (KeyError, TypeError, ValueError) as exc:
        raise DistanceNetFileError(f"{where}: not upgraded: metadata lacks error_statistics n_points and seed") from exc
    figures = evaluate_mu_function(lambda p: module_dual(module, p, G, g)[0], G, g, n_points=n_points, seed=seed)
    changed = [f"{k} stored {stored.get(k)!r}, now {v!r}" for k, v in figures.items()
               if not isinstance(stored.get(k), (int, float))
               or abs(float(stored[k]) - float(v)) > UPGRADE_FIGURE_TOLERANCE]
    if changed:
        raise DistanceNetFileError(f"{where}: not upgraded: held-out figures differ from the stored ones "
                                   f"(weights changed?): {'; '.join(changed)}")
    meta = dict(meta, upgraded_from_version=meta["version"])
    save_artifact(module, output, meta)
    return _read_artifact(Path(output))[1]


class DistanceNet:
    """Inference wrapper of the frozen TorchScript distance net (one torch thread).

    Attributes: G (4, 2), g (4,) of the robot description's footprint, metadata (dict), path.
    """

    def __init__(self, module: torch.jit.ScriptModule, G: np.ndarray, g: np.ndarray,
                 metadata: dict[str, Any], path: Path) -> None:
        self._module = module
        self.G = np.asarray(G, dtype=np.float64)
        self.g = np.asarray(g, dtype=np.float64)
        self.metadata = metadata
        self.path = path

    @classmethod
    def load(cls, path: str | Path | None = None, robot: Any = None) -> "DistanceNet":
        """Load an artifact (None: the shipped LIMO net) for a robot description (None: LIMO).

        Checks, in this order: the file is TorchScript with our metadata of the current version;
        the weights match the stored checksum and are finite; the footprint is the robot
        description's; on the stored probe set the net reproduces its stored outputs and stays
        within its stored error bound of the exact distance (models.distance_integrity).
        Raises DistanceNetFileError for a missing, invalid or failing file and
        FootprintMismatchError when the artifact's footprint differs from the robot description's.
        """
        if robot is None:
            from calibration.robot_description import load_robot_description

            robot = load_robot_description()
        path = shipped_artifact_path() if path is None else Path(path)
        module, meta = _read_artifact(path)
        where = f"distance-net artifact {path}"
        _verify_weights(module, meta, where)
        _check_footprint(meta, robot, path)
        G, g = (np.asarray(a, dtype=np.float64) for a in robot.footprint.halfspaces())
        torch.set_num_threads(1)
        _verify_probes(module, meta, G, g, where)
        return cls(module, G, g, meta, path)

    def mu(self, points_robot_frame: np.ndarray) -> np.ndarray:
        """Dual variables (N, 4) >= 0, rows (front, left, rear, right), with ||G^T mu|| <= 1."""
        return self.dual(points_robot_frame)[0]

    def distance(self, points_robot_frame: np.ndarray) -> np.ndarray:
        """Signed distance (N,) in m (negative inside): mu^T (G p - g)."""
        return self.dual(points_robot_frame)[2]

    def dual(self, points_robot_frame: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(mu (N, 4), lam_robot (N, 2) = -G^T mu, signed distance (N,)) in the robot frame."""
        p = validate_points(points_robot_frame, "DistanceNet points_robot_frame")
        if p.shape[0] == 0:
            return np.zeros((0, self.G.shape[0])), np.zeros((0, 2)), np.zeros(0)
        return module_dual(self._module, p, self.G, self.g)


__all__ = [
    "DistanceNet",
    "FoldedDualMLP",
    "save_artifact",
    "module_dual",
    "upgrade_artifact",
    "shipped_artifact_path",
    "rectangle_half_extents",
    "ARTIFACT_FORMAT",
    "ARTIFACT_VERSION",
]
