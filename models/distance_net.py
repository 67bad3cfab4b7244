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

import json
import warnings
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn

from models.errors import DistanceNetFileError, FootprintMismatchError, UnsupportedFootprintError
from models.footprint_dual import validate_points

ARTIFACT_FORMAT = "dct-distance-net"
ARTIFACT_VERSION = 1
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


def save_artifact(module: FoldedDualMLP, path: Path, metadata: dict[str, Any]) -> Path:
    """Script, freeze and save `module` as TorchScript with our metadata as an extra file."""
    module = module.eval().to(torch.float32)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    meta = dict(metadata, format=ARTIFACT_FORMAT, version=ARTIFACT_VERSION)
    with warnings.catch_warnings():  # TorchScript is deprecated upstream but is our deployment format
        warnings.simplefilter("ignore", DeprecationWarning)
        frozen = torch.jit.freeze(torch.jit.script(module))
        torch.jit.save(frozen, str(path), _extra_files={METADATA_FILE: json.dumps(meta, indent=1)})
    return path


def _read_artifact(path: Path) -> tuple[torch.jit.ScriptModule, dict[str, Any]]:
    if not path.is_file():
        raise DistanceNetFileError(f"distance-net artifact {path}: no such file")
    extra = {METADATA_FILE: ""}
    try:
        with warnings.catch_warnings():  # TorchScript is deprecated upstream but is our deployment format
            warnings.simplefilter("ignore", DeprecationWarning)
            module = torch.jit.load(str(path), map_location="cpu", _extra_files=extra)
    except Exception as exc:  # torch raises RuntimeError/ValueError/zipfile errors alike
        raise DistanceNetFileError(f"distance-net artifact {path}: not a readable TorchScript file: {exc}") from exc
    raw = extra[METADATA_FILE]
    if not raw:
        raise DistanceNetFileError(
            f"distance-net artifact {path}: TorchScript without '{METADATA_FILE}' metadata "
            "(not exported by `dct models train-distance`)"
        )
    try:
        meta = json.loads(raw)
    except json.JSONDecodeError as exc:
        raise DistanceNetFileError(f"distance-net artifact {path}: metadata is not valid JSON: {exc}") from exc
    if not isinstance(meta, dict) or meta.get("format") != ARTIFACT_FORMAT:
        raise DistanceNetFileError(f"distance-net artifact {path}: metadata format is not '{ARTIFACT_FORMAT}'")
    if meta.get("version") != ARTIFACT_VERSION:
        raise DistanceNetFileError(
            f"distance-net artifact {path}: metadata version {meta.get('version')!r}, this code reads version "
            f"{ARTIFACT_VERSION}; retrain with `dct models train-distance`"
        )
    for key in ("footprint", "training_domain"):
        if key not in meta:
            raise DistanceNetFileError(f"distance-net artifact {path}: metadata lacks '{key}'")
    return module, meta


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

        Raises DistanceNetFileError for a missing/invalid file and FootprintMismatchError when the
        artifact's footprint differs from the robot description's.
        """
        if robot is None:
            from calibration.robot_description import load_robot_description

            robot = load_robot_description()
        path = shipped_artifact_path() if path is None else Path(path)
        module, meta = _read_artifact(path)
        G, g = robot.footprint.halfspaces()
        robot_vertices = np.asarray(robot.footprint.vertices(), dtype=np.float64)
        try:
            art_vertices = np.asarray(meta["footprint"]["vertices_m"], dtype=np.float64)
        except (KeyError, TypeError, ValueError) as exc:
            raise DistanceNetFileError(f"distance-net artifact {path}: metadata footprint has no valid 'vertices_m'") from exc
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
        torch.set_num_threads(1)
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
        with torch.inference_mode():
            mu = self._module(torch.from_numpy(p.astype(np.float32))).numpy().astype(np.float64)
        # Repeat the scaling in float64 so that the bound holds beyond float32 rounding.
        gt_mu = mu @ self.G  # (N, 2) = G^T mu per point
        scale = 1.0 / np.maximum(np.sqrt(gt_mu[:, 0] * gt_mu[:, 0] + gt_mu[:, 1] * gt_mu[:, 1]), 1.0)
        mu *= scale[:, None]
        gt_mu *= scale[:, None]
        # mu^T (G p - g) = (G^T mu) . p - mu . g
        distance = gt_mu[:, 0] * p[:, 0] + gt_mu[:, 1] * p[:, 1] - mu @ self.g
        return mu, -gt_mu, distance


__all__ = [
    "DistanceNet",
    "FoldedDualMLP",
    "save_artifact",
    "shipped_artifact_path",
    "rectangle_half_extents",
    "ARTIFACT_FORMAT",
    "ARTIFACT_VERSION",
]
