"""Lidar-camera extrinsic T_camera<-lidar from a planar checkerboard seen by both sensors.

Per board pose: the camera gives the board plane through solvePnP on the detected corners; the
lidar gives the board's points (region around the expected board, RANSAC plane). Across poses:
  1. rotation: Kabsch on the plane normals (n_cam = R n_lidar),
  2. translation: linear least squares on n_cam . (R p + t) = d_cam at the board centroids,
  3. refinement: point-to-plane residuals of all board points (scipy.optimize.least_squares).
The plane normals of the poses must span 3-D (tilt the board in several directions).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from calibration.camera_model import transform_points
from calibration.intrinsics import CalibrationError

#: Quality target of a lidar-camera extrinsic: `dct calibrate extrinsics` does not write a
#: result that misses it unless --force is given. The point-to-plane RMS of the board points is
#: about the lidar's range noise (2-3 cm for a Livox Mid-360 class sensor) when the transform is
#: right; above 4 cm a wrong segmentation or transform is likely. Fewer than 6 board poses leave
#: the translation weakly constrained (3 is the solver's hard minimum).
EXTRINSIC_MAX_RMS_M = 0.04
EXTRINSIC_MIN_POSES = 6


@dataclass(frozen=True)
class BoardGeometry:
    """A checkerboard: inner corners (cols, rows), square size, and its outer size (m)."""

    pattern_size: tuple[int, int]
    square_m: float
    border_m: float = 0.0  # white margin around the outer squares

    @property
    def width_m(self) -> float:
        return (self.pattern_size[0] + 1) * self.square_m + 2 * self.border_m

    @property
    def height_m(self) -> float:
        return (self.pattern_size[1] + 1) * self.square_m + 2 * self.border_m

    def centre_in_board(self) -> np.ndarray:
        """Board centre in the corner frame (origin at the first inner corner, z = 0)."""
        return np.array([(self.pattern_size[0] - 1) / 2 * self.square_m, (self.pattern_size[1] - 1) / 2 * self.square_m, 0.0])


@dataclass
class BoardObservation:
    """One board pose: T_camera<-board (from solvePnP) and the lidar points on the board."""

    T_cam_board: np.ndarray
    board_points_lidar: np.ndarray
    name: str = ""


@dataclass
class ExtrinsicsResult:
    T_cam_lidar: np.ndarray
    rms_point_to_plane_m: float
    per_pose_rms_m: dict[str, float]
    n_points: int
    T_closed_form: np.ndarray = field(repr=False, default_factory=lambda: np.eye(4))


def fit_plane(points: np.ndarray) -> tuple[np.ndarray, float]:
    """Least-squares plane n . p = d through (N,3) points (unit n)."""
    c = points.mean(axis=0)
    _, _, vt = np.linalg.svd(points - c, full_matrices=False)
    n = vt[2]
    return n, float(n @ c)


def ransac_plane(
    points: np.ndarray, threshold_m: float = 0.05, iterations: int = 200, rng: np.random.Generator | None = None
) -> tuple[np.ndarray, float, np.ndarray]:
    """RANSAC plane: (unit normal, d, inlier mask) of the plane with most points within threshold."""
    if len(points) < 3:
        raise CalibrationError(f"plane fit needs at least 3 points, got {len(points)}")
    rng = rng or np.random.default_rng(0)
    best = np.zeros(len(points), dtype=bool)
    for _ in range(iterations):
        a, b, c = points[rng.choice(len(points), 3, replace=False)]
        n = np.cross(b - a, c - a)
        norm = np.linalg.norm(n)
        if norm < 1e-9:
            continue
        n /= norm
        inl = np.abs(points @ n - n @ a) < threshold_m
        if inl.sum() > best.sum():
            best = inl
    if best.sum() < 3:
        raise CalibrationError("RANSAC found no plane")
    n, d = fit_plane(points[best])
    inl = np.abs(points @ n - d) < threshold_m
    n, d = fit_plane(points[inl])
    return n, d, inl


def segment_board(
    points_lidar: np.ndarray,
    board: BoardGeometry,
    T_cam_board: np.ndarray | None = None,
    T_cam_lidar_guess: np.ndarray | None = None,
    threshold_m: float = 0.05,
    margin_m: float = 0.15,
) -> np.ndarray:
    """Board points in a scan: near the expected board centre (if a guess is given), on the main plane.

    With a guess, keeps points within (half the board diagonal + margin) of the predicted centre;
    without, uses the whole scan. Returns the plane inliers (M,3).
    """
    pts = points_lidar[np.isfinite(points_lidar).all(axis=1)]
    if T_cam_board is not None and T_cam_lidar_guess is not None:
        centre_cam = transform_points(T_cam_board, board.centre_in_board()[None])[0]
        centre_lidar = transform_points(np.linalg.inv(T_cam_lidar_guess), centre_cam[None])[0]
        radius = 0.5 * np.hypot(board.width_m, board.height_m) + margin_m
        pts = pts[np.linalg.norm(pts - centre_lidar, axis=1) < radius]
    if len(pts) < 10:
        raise CalibrationError(f"only {len(pts)} lidar points near the expected board")
    _, _, inl = ransac_plane(pts, threshold_m)
    return pts[inl]


def _camera_plane(T_cam_board: np.ndarray) -> tuple[np.ndarray, float]:
    """Board plane in the camera frame, normal pointing towards the camera."""
    n = T_cam_board[:3, 2].copy()
    t = T_cam_board[:3, 3]
    if n @ t > 0:
        n = -n
    return n, float(n @ t)


def calibrate_lidar_camera(
    observations: list[BoardObservation], board: BoardGeometry | None = None, min_poses: int = 3
) -> ExtrinsicsResult:
    """Solve T_camera<-lidar from several board poses (see module docstring).

    With `board`, a second pass keeps only the points that fall inside the board's outline
    (in the board frame from the first solution) and within 3 sigma of its plane, and solves again:
    this drops clutter that happened to lie on the board's plane.
    """
    res = _solve(observations, min_poses)
    if board is None:
        return res
    cols, rows = board.pattern_size
    lo = np.array([-board.square_m - board.border_m] * 2) - 0.02
    hi = np.array([cols * board.square_m + board.border_m, rows * board.square_m + board.border_m]) + 0.02
    thr = max(3.0 * res.rms_point_to_plane_m, 0.01)
    kept = []
    for o in observations:
        T_board_lidar = np.linalg.inv(o.T_cam_board) @ res.T_cam_lidar
        q = transform_points(T_board_lidar, o.board_points_lidar)
        inside = np.all((q[:, :2] >= lo) & (q[:, :2] <= hi), axis=1) & (np.abs(q[:, 2]) < thr)
        kept.append(BoardObservation(o.T_cam_board, o.board_points_lidar[inside], o.name))
    return _solve(kept, min_poses)


def _solve(observations: list[BoardObservation], min_poses: int) -> ExtrinsicsResult:
    from scipy.optimize import least_squares
    from scipy.spatial.transform import Rotation

    obs = [o for o in observations if len(o.board_points_lidar) >= 10]
    if len(obs) < min_poses:
        raise CalibrationError(f"need at least {min_poses} board poses with lidar points, got {len(obs)}")
    n_cam, d_cam, n_lid, cen_lid = [], [], [], []
    for o in obs:
        nc, dc = _camera_plane(o.T_cam_board)
        nl, _ = fit_plane(o.board_points_lidar)
        centroid = o.board_points_lidar.mean(axis=0)
        if nl @ centroid > 0:  # towards the lidar
            nl = -nl
        n_cam.append(nc), d_cam.append(dc), n_lid.append(nl), cen_lid.append(centroid)
    n_cam, n_lid, d_cam, cen_lid = map(np.asarray, (n_cam, n_lid, d_cam, cen_lid))
    sv = np.linalg.svd(n_cam, compute_uv=False)
    if sv[-1] / sv[0] < 0.05:
        raise CalibrationError(
            f"board normals do not span 3-D (singular values {np.round(sv, 3).tolist()}): "
            "tilt the board left/right and up/down between poses"
        )
    # 1. rotation (Kabsch on normals)
    U, _, Vt = np.linalg.svd(n_cam.T @ n_lid)
    S = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
    R = U @ S @ Vt
    # 2. translation: n_c . t = d_c - n_c . R c_l
    b = d_cam - np.einsum("ij,ij->i", n_cam, cen_lid @ R.T)
    t, *_ = np.linalg.lstsq(n_cam, b, rcond=None)
    T0 = np.eye(4)
    T0[:3, :3], T0[:3, 3] = R, t
    # 3. point-to-plane refinement on all points
    pts = [o.board_points_lidar for o in obs]
    idx = np.concatenate([np.full(len(p), i) for i, p in enumerate(pts)])
    P = np.concatenate(pts)
    N = n_cam[idx]
    D = d_cam[idx]

    def residuals(x: np.ndarray) -> np.ndarray:
        Rx = Rotation.from_rotvec(x[:3]).as_matrix()
        return np.einsum("ij,ij->i", N, P @ Rx.T + x[3:]) - D

    x0 = np.concatenate([Rotation.from_matrix(R).as_rotvec(), t])
    sol = least_squares(residuals, x0, loss="soft_l1", f_scale=0.05, x_scale="jac")
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(sol.x[:3]).as_matrix()
    T[:3, 3] = sol.x[3:]
    r = residuals(sol.x)
    per_pose = {(o.name or f"pose_{i}"): float(np.sqrt(np.mean(r[idx == i] ** 2))) for i, o in enumerate(obs)}
    return ExtrinsicsResult(T_cam_lidar=T, rms_point_to_plane_m=float(np.sqrt(np.mean(r**2))),
                            per_pose_rms_m=per_pose, n_points=len(P), T_closed_form=T0)


def extrinsics_quality_problems(
    res: ExtrinsicsResult, max_rms_m: float | None = None, min_poses: int | None = None
) -> list[str]:
    """Why `res` misses the quality target (EXTRINSIC_MAX_RMS_M, EXTRINSIC_MIN_POSES); [] when it meets it."""
    max_rms_m = EXTRINSIC_MAX_RMS_M if max_rms_m is None else max_rms_m
    min_poses = EXTRINSIC_MIN_POSES if min_poses is None else min_poses
    problems = []
    if not np.isfinite(res.rms_point_to_plane_m) or res.rms_point_to_plane_m > max_rms_m:
        problems.append(f"point-to-plane RMS {res.rms_point_to_plane_m * 100:.2f} cm > {max_rms_m * 100:.2f} cm")
    n_poses = len(res.per_pose_rms_m)
    if n_poses < min_poses:
        problems.append(f"{n_poses} board poses < {min_poses}")
    return problems


def transform_error(T_est: np.ndarray, T_true: np.ndarray) -> tuple[float, float]:
    """(translation error m, rotation error deg) between two 4x4 transforms."""
    from scipy.spatial.transform import Rotation

    dT = np.linalg.inv(T_true) @ T_est
    ang = np.degrees(np.linalg.norm(Rotation.from_matrix(dT[:3, :3]).as_rotvec()))
    return float(np.linalg.norm(T_est[:3, 3] - T_true[:3, 3])), float(ang)


# ---------------------------------------------------------------------------- alignment checks
def image_edge_map(image: np.ndarray, blur_px: float = 2.0, decay: float = 0.9, reach_px: int = 20) -> np.ndarray:
    """Levinson-Thrun edge map: normalized gradient magnitude spread with a decay per pixel of distance."""
    import cv2

    gray = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    g = cv2.GaussianBlur(gray.astype(np.float32), (0, 0), blur_px)
    E = np.hypot(cv2.Sobel(g, cv2.CV_32F, 1, 0, ksize=3), cv2.Sobel(g, cv2.CV_32F, 0, 1, ksize=3))
    E = np.clip(E / max(float(np.percentile(E, 99.5)), 1e-6), 0.0, 1.0)
    D, cur, kernel = E.copy(), E.copy(), np.ones((3, 3), np.uint8)
    for _ in range(reach_px):
        cur = cv2.dilate(cur, kernel) * decay
        np.maximum(D, cur, out=D)
    return D


def depth_edge_mask(uv: np.ndarray, depth_m: np.ndarray, radius_px: float = 8.0, rel_jump: float = 0.3) -> np.ndarray:
    """Foreground depth-edge points: a neighbour within radius_px in the image is > rel_jump*depth farther."""
    from scipy.spatial import cKDTree

    if len(uv) == 0:
        return np.zeros(0, dtype=bool)
    _, idx = cKDTree(uv).query(uv, k=12, distance_upper_bound=radius_px)
    far = np.concatenate([depth_m, [-np.inf]])[idx].max(axis=1)
    return far - depth_m > rel_jump * depth_m


def edge_alignment_score(camera, points_lidar: np.ndarray, T_cam_lidar: np.ndarray, edge_map: np.ndarray) -> float:
    """Mean image-edge strength (from image_edge_map) at the projected lidar depth edges, in [0, 1]."""
    uv, valid, z = camera.depths_and_project_lidar(points_lidar, T_cam_lidar)
    uv, z = uv[valid], z[valid]
    edges = depth_edge_mask(uv, z)
    if not edges.any():
        return 0.0
    ij = np.clip(np.round(uv[edges]).astype(int), 0, [edge_map.shape[1] - 1, edge_map.shape[0] - 1])
    return float(edge_map[ij[:, 1], ij[:, 0]].mean())


def intensity_mutual_information(
    camera, points_lidar: np.ndarray, intensity: np.ndarray, T_cam_lidar: np.ndarray, image: np.ndarray, bins: int = 32
) -> float:
    """Mutual information (nats) between lidar intensity and image grey level at the projected points."""
    import cv2

    gray = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    gray = cv2.GaussianBlur(gray, (0, 0), 1.5)
    uv, valid = camera.project_lidar(points_lidar, T_cam_lidar)
    ok = valid & np.isfinite(intensity)
    if ok.sum() < bins:
        return 0.0
    ij = np.clip(np.round(uv[ok]).astype(int), 0, [gray.shape[1] - 1, gray.shape[0] - 1])
    a = intensity[ok].astype(float)
    b = gray[ij[:, 1], ij[:, 0]].astype(float)
    H, _, _ = np.histogram2d(a, b, bins=bins, range=[[a.min(), np.percentile(a, 99) + 1e-6], [0, 256]])
    P = H / H.sum()
    pa, pb = P.sum(axis=1, keepdims=True), P.sum(axis=0, keepdims=True)
    nz = P > 0
    return float((P[nz] * np.log(P[nz] / (pa @ pb)[nz])).sum())


def perturb_transform(T: np.ndarray, dxyz_m=(0.0, 0.0, 0.0), drpy_deg=(0.0, 0.0, 0.0)) -> np.ndarray:
    """Apply a small rotation (about the camera axes) and shift (in the camera frame) to T_cam_lidar."""
    from scipy.spatial.transform import Rotation

    P = np.eye(4)
    P[:3, :3] = Rotation.from_euler("xyz", drpy_deg, degrees=True).as_matrix()
    P[:3, 3] = dxyz_m
    return P @ np.asarray(T, dtype=float)


__all__ = ["BoardGeometry", "BoardObservation", "ExtrinsicsResult", "calibrate_lidar_camera", "segment_board",
           "extrinsics_quality_problems", "EXTRINSIC_MAX_RMS_M", "EXTRINSIC_MIN_POSES",
           "ransac_plane", "fit_plane", "transform_error", "image_edge_map", "depth_edge_mask",
           "edge_alignment_score", "intensity_mutual_information", "perturb_transform"]
