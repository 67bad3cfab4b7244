"""Does a scan constrain the robot's planar motion, and along which direction does it not?

The registration's Hessian tells (Zhang, Kaess and Singh, "On degeneracy of optimization-based
state estimation problems", ICRA 2016). We use the point-to-plane form, because point-to-point
ICP's translational Hessian is the identity times the point count whatever the geometry: it
cannot see a corridor. For every point p with a surface normal n, a planar motion (x, y, yaw)
moves the point-to-plane residual by

    J = [n_x, n_y, (p_x n_y - p_y n_x) / r]         (r: the scan's median planar range)

and H = sum J^T J over the points (the yaw column scaled by r so that the three directions are
comparable). The floor's normals are vertical: their rows are zero, and they do not count.

Normalised by the number of points, H's translational block has eigenvalues that sum to the
mean n_xy^2 (<= 1): about 0.5 each in a room, one of them near 0 in a straight corridor (every
wall normal is across it). A scan is degenerate along the eigenvector whose eigenvalue falls below
`min_eigenvalue` (or when fewer than `min_points` points have a horizontal normal: a scan that
sees too little); yaw is degenerate when its Schur complement (what yaw adds once x and y are
known) falls below the same bound. The fusion then trusts wheels and IMU along that direction.

The normals: the points are binned into cubic cells (`cell_m`); a cell's points share the normal
of the cell's PCA (the covariance's smallest eigenvector) when the cell holds enough points and is
flat. The covariances come from per-cell sums (np.bincount) and the eigenpairs from the closed
form for symmetric 3x3 matrices: about a millisecond for a frame, where a k-d tree's 8 nearest
neighbours and a batched np.linalg.eigh per point took 12-15 ms on the reference machine
(docs/decisions/odometry-icp-speed.md).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from pydantic import BaseModel, ConfigDict, Field


class DegeneracyConfig(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)

    #: The cells the points are binned into for their normals (m, cubes).
    cell_m: float = Field(0.4, gt=0.05, le=5.0)
    #: A cell with fewer points than this gives its points no normal.
    min_cell_points: int = Field(5, ge=4, le=1000)
    #: A cell is a surface when its smallest PCA eigenvalue is below this share of the sum
    #: (0 = a perfect plane, 1/3 = an isotropic blob): corners, edges and clutter give no normal.
    max_surface_variation: float = Field(0.05, gt=0.0, le=0.34)
    #: A direction is constrained when its normalised eigenvalue is at least this. Measured on the
    #: simulator: 0.15-0.45 in rooms and clutter, below 0.01 in the 2 m corridor (docs in
    #: runtime/config/default.yaml).
    min_eigenvalue: float = Field(0.03, gt=0.0, le=1.0)
    #: Fewer points with a horizontal normal than this: the scan sees too little.
    min_points: int = Field(50, ge=1, le=100_000)
    #: The deskewed frame is thinned to one point per voxel of this size (m) for the analysis
    #: (KISS-ICP's registration points, at 1.5 x its voxel, are too sparse for normals).
    voxel_m: float = Field(0.1, gt=0.01, le=1.0)
    #: At most this many points are analysed (the rest is subsampled evenly): a bound for
    #: pathological frames. A subsampled frame leaves fewer points per cell, so the bound sits
    #: above the thinned frames of a 40k-ray lidar (about 6k points).
    max_points: int = Field(20_000, ge=100, le=200_000)


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


def smallest_eigen(cov: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The smallest eigenvalue, its unit eigenvector and the eigenvalue sum of each symmetric
    3x3 matrix in cov (M, 3, 3), in closed form (the trigonometric solution of the characteristic
    cubic; the eigenvector is the longest cross product of two rows of cov - lambda I)."""
    # Solved on cov / its largest entry (the roots scale with it): no under- or overflow in the
    # squares and cubes below, whatever the matrix's own scale.
    size = np.abs(cov).reshape(len(cov), 9).max(axis=1)
    size = np.where(size > 0.0, size, 1.0)
    cov = cov / size[:, None, None]
    a, b, c = cov[:, 0, 0], cov[:, 1, 1], cov[:, 2, 2]
    d, e, f = cov[:, 0, 1], cov[:, 1, 2], cov[:, 0, 2]
    q = (a + b + c) / 3.0
    aq, bq, cq = a - q, b - q, c - q
    p = np.sqrt((aq * aq + bq * bq + cq * cq + 2.0 * (d * d + e * e + f * f)) / 6.0)
    det = aq * (bq * cq - e * e) - d * (d * cq - e * f) + f * (d * e - bq * f)
    # Three equal roots (p negligible beside the matrix's scale, where p ** 3 would underflow):
    # every root is q.
    p = np.where(p > 1e-9 * np.maximum(np.abs(q), p), p, 0.0)
    with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
        r = np.where(p > 0.0, det / (2.0 * p ** 3), 0.0)
    lam = q + 2.0 * p * np.cos(np.arccos(np.clip(r, -1.0, 1.0)) / 3.0 + 2.0 * np.pi / 3.0)
    a, b, c = a - lam, b - lam, c - lam   # the rows of cov - lambda I: (a d f), (d b e), (f e c)
    cands = np.stack([np.stack([d * e - f * b, f * d - a * e, a * b - d * d], axis=1),    # row 0 x row 1
                      np.stack([d * c - f * e, f * f - a * c, a * e - d * f], axis=1),    # row 0 x row 2
                      np.stack([b * c - e * e, e * f - d * c, d * e - b * f], axis=1)],   # row 1 x row 2
                     axis=1)                                                          # (M, 3, 3)
    norm2 = (cands * cands).sum(axis=2)
    best = norm2.argmax(axis=1)
    pick = np.arange(len(cov))
    vec = cands[pick, best]
    # Scaled by its largest component first, so that a tiny (subnormal) cross product normalises.
    big = np.abs(vec).max(axis=1)
    with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
        unit = vec / big[:, None]
        unit = unit / np.sqrt((unit * unit).sum(axis=1))[:, None]
    ok = (big > 0.0) & np.isfinite(unit).all(axis=1)
    vec = np.where(ok[:, None], unit, np.array([0.0, 0.0, 1.0]))
    return lam * size, vec, 3.0 * q * size


def _normals(points: np.ndarray, config: DegeneracyConfig) -> tuple[np.ndarray, np.ndarray]:
    """Unit normals of the points on surfaces (their cell's), and which points have one."""
    cell = config.cell_m
    ijk = np.floor(points / cell)
    idx = (ijk - ijk.min(axis=0)).astype(np.int64)
    span = idx.max(axis=0) + 1
    _, inv, counts = np.unique((idx[:, 0] * span[1] + idx[:, 1]) * span[2] + idx[:, 2],
                               return_inverse=True, return_counts=True)
    m = len(counts)
    local = points - ijk * cell          # within the cell: no cancellation in the sums
    mean = np.stack([np.bincount(inv, local[:, i], m) for i in range(3)], axis=1) / counts[:, None]
    cov = np.empty((m, 3, 3))
    for i, j in ((0, 0), (1, 1), (2, 2), (0, 1), (1, 2), (0, 2)):
        cov[:, i, j] = cov[:, j, i] = (np.bincount(inv, local[:, i] * local[:, j], m) / counts
                                       - mean[:, i] * mean[:, j])
    lam, normal, total = smallest_eigen(cov)
    with np.errstate(invalid="ignore", divide="ignore"):
        variation = np.where(total > 0.0, lam / total, 1.0)
    ok = (counts >= config.min_cell_points) & (variation <= config.max_surface_variation)
    return normal[inv], ok[inv]


def planar_constraint(points_base: np.ndarray, config: DegeneracyConfig = DegeneracyConfig()) -> PlanarConstraint:
    """Analyse the (thinned, deskewed) points of one scan, given in the base frame (N, 3)."""
    pts = np.asarray(points_base, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise ValueError(f"points must be (N, 3), got {pts.shape}")
    if not np.isfinite(pts).all():
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


__all__ = ["DegeneracyConfig", "PlanarConstraint", "planar_constraint", "smallest_eigen"]
