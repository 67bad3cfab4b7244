"""Does a scan constrain the robot's planar motion, and along which direction does it not?

The registration's Hessian tells (Zhang, Kaess and Singh, "On degeneracy of optimization-based
state estimation problems", ICRA 2016). We use the point-to-plane form, because point-to-point
ICP's translational Hessian is the identity times the point count whatever the geometry: it
cannot see a corridor. For every registration point p with a surface normal n (from a local PCA
of its neighbours), a planar motion (x, y, yaw) moves the point-to-plane residual by

    J = [n_x, n_y, (p_x n_y - p_y n_x) / r]         (r: the scan's median planar range)

and H = sum J^T J over the points (the yaw column scaled by r so that the three directions are
comparable). The floor's normals are vertical: their rows are zero, and they do not count.

Normalised by the number of points, H's translational block has eigenvalues that sum to the
mean n_xy^2 (<= 1): about 0.5 each in a room, one of them near 0 in a straight corridor (every
wall normal is across it). A scan is degenerate along the eigenvector whose eigenvalue falls below
`min_eigenvalue` (or when fewer than `min_points` points have a horizontal normal: a scan that
sees too little); yaw is degenerate when its Schur complement (what yaw adds once x and y are
known) falls below the same bound. The fusion then trusts wheels and IMU along that direction.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from pydantic import BaseModel, ConfigDict, Field
from scipy.spatial import cKDTree


class DegeneracyConfig(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)

    #: Neighbours of a point for its normal (PCA).
    neighbours: int = Field(8, ge=4, le=64)
    #: A neighbourhood is a surface when its smallest PCA eigenvalue is below this share of the
    #: sum (0 = a perfect plane, 1/3 = an isotropic blob): edges and scattered points give no normal.
    max_surface_variation: float = Field(0.05, gt=0.0, le=0.34)
    #: Neighbours farther than this (m) are not the same surface.
    max_neighbour_distance_m: float = Field(1.0, gt=0.0, le=10.0)
    #: A direction is constrained when its normalised eigenvalue is at least this. Measured on the
    #: simulator: 0.15-0.45 in rooms and clutter, below 0.01 in the 2 m corridor (docs in
    #: runtime/config/default.yaml).
    min_eigenvalue: float = Field(0.03, gt=0.0, le=1.0)
    #: Fewer points with a horizontal normal than this: the scan sees too little.
    min_points: int = Field(50, ge=1, le=100_000)
    #: The deskewed frame is thinned to one point per voxel of this size (m) for the analysis
    #: (KISS-ICP's registration points, at 1.5 x its voxel, are too sparse for normals).
    voxel_m: float = Field(0.1, gt=0.01, le=1.0)
    #: At most this many points are analysed (the rest is subsampled evenly).
    max_points: int = Field(4000, ge=100, le=200_000)


@dataclass(frozen=True)
class PlanarConstraint:
    """What one scan constrains of the planar motion (x, y, yaw), in the base frame."""

    #: Normalised information matrix (3x3) over (x, y, yaw * r).
    information: np.ndarray
    #: Translational eigenvalues (ascending) and their unit eigenvectors (columns, base frame).
    eigenvalues_xy: np.ndarray
    eigenvectors_xy: np.ndarray
    #: What yaw adds once x and y are known (Schur complement, normalised).
    yaw_eigenvalue: float
    points: int  # points with a horizontal normal (those that constrain x, y, yaw)
    scale_m: float  # r: the median planar range used to scale yaw
    degenerate_xy: bool
    degenerate_yaw: bool
    too_few_points: bool

    @property
    def degenerate(self) -> bool:
        return self.degenerate_xy or self.degenerate_yaw

    @property
    def weak_direction_xy(self) -> np.ndarray | None:
        """The unit direction (base frame) the scan does not constrain; None when it does."""
        return self.eigenvectors_xy[:, 0].copy() if self.degenerate_xy else None

    def describe(self) -> str:
        if self.too_few_points:
            return f"scan sees too little ({self.points} points on vertical surfaces)"
        parts = []
        if self.degenerate_xy:
            d = self.eigenvectors_xy[:, 0]
            heading = float(np.degrees(np.arctan2(d[1], d[0]))) % 180.0
            parts.append(f"translation unconstrained along {heading:.0f} deg in the base frame "
                         f"(eigenvalue {self.eigenvalues_xy[0]:.3f})")
        if self.degenerate_yaw:
            parts.append(f"yaw unconstrained (eigenvalue {self.yaw_eigenvalue:.3f})")
        return "; ".join(parts) or "well constrained"


def _normals(points: np.ndarray, config: DegeneracyConfig) -> tuple[np.ndarray, np.ndarray]:
    """Unit normals of the points on surfaces, and which points have one."""
    n = len(points)
    k = min(config.neighbours, n)
    if k < 4:
        return np.zeros((n, 3)), np.zeros(n, dtype=bool)
    tree = cKDTree(points)
    dist, idx = tree.query(points, k=k)
    near = dist[:, -1] <= config.max_neighbour_distance_m
    nb = points[idx]                                    # (n, k, 3)
    centred = nb - nb.mean(axis=1, keepdims=True)
    cov = np.einsum("nki,nkj->nij", centred, centred) / k
    evals, evecs = np.linalg.eigh(cov)                  # ascending
    total = evals.sum(axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        variation = np.where(total > 0, evals[:, 0] / total, 1.0)
    ok = near & (variation <= config.max_surface_variation)
    return evecs[:, :, 0], ok


def planar_constraint(points_base: np.ndarray, config: DegeneracyConfig = DegeneracyConfig()) -> PlanarConstraint:
    """Analyse the (thinned, deskewed) points of one scan, given in the base frame (N, 3)."""
    pts = np.asarray(points_base, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise ValueError(f"points must be (N, 3), got {pts.shape}")
    pts = pts[np.isfinite(pts).all(axis=1)]
    if len(pts) > config.max_points:
        pts = pts[np.linspace(0, len(pts) - 1, config.max_points).astype(np.int64)]
    normals, ok = _normals(pts, config) if len(pts) else (np.zeros((0, 3)), np.zeros(0, dtype=bool))
    nxy = normals[:, :2]
    horizontal = ok & (np.hypot(nxy[:, 0], nxy[:, 1]) > 0.5)   # a vertical surface's normal
    p, nrm = pts[horizontal], nxy[horizontal]
    count = int(len(p))
    r = float(np.median(np.hypot(p[:, 0], p[:, 1]))) if count else 1.0
    r = max(r, 0.1)
    if count:
        torque = (p[:, 0] * nrm[:, 1] - p[:, 1] * nrm[:, 0]) / r
        jac = np.column_stack([nrm[:, 0], nrm[:, 1], torque])
        info = jac.T @ jac / max(len(pts), 1) * (len(pts) / count)   # normalised by the surface points
    else:
        info = np.zeros((3, 3))
    h_tt = info[:2, :2]
    evals, evecs = np.linalg.eigh(h_tt)
    if abs(np.linalg.det(h_tt)) > 1e-12:
        yaw_eig = float(info[2, 2] - info[2, :2] @ np.linalg.solve(h_tt, info[:2, 2]))
    else:
        yaw_eig = float(info[2, 2])
    too_few = count < config.min_points
    return PlanarConstraint(
        information=info,
        eigenvalues_xy=evals,
        eigenvectors_xy=evecs,
        yaw_eigenvalue=yaw_eig,
        points=count,
        scale_m=r,
        degenerate_xy=bool(too_few or evals[0] < config.min_eigenvalue),
        degenerate_yaw=bool(too_few or yaw_eig < config.min_eigenvalue),
        too_few_points=too_few,
    )


__all__ = ["DegeneracyConfig", "PlanarConstraint", "planar_constraint"]
