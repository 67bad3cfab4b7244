"""What the MPC needs from a distance model, the exact rectangle geometry, and a stand-in model.

The planner accepts any object with a `dual(points_robot_frame)` method (the `DistanceModel`
protocol): the distance net (models/distance_net.py) in the controller, the exact closed-form
dual below in tests and as a reference. Footprint = {x : G x <= g} in the robot frame.
"""
from __future__ import annotations

from typing import Protocol, runtime_checkable

import numpy as np

from runtime.planning.errors import DistanceModelError, PlannerInputError


@runtime_checkable
class DistanceModel(Protocol):
    """Dual distance of points (robot frame) to the footprint, as the distance net gives it."""

    G: np.ndarray  # (4, 2)
    g: np.ndarray  # (4,)

    def dual(self, points_robot_frame: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(mu (N,4) >= 0, lam_robot (N,2) = -G^T mu, signed distance (N,), negative inside)."""
        ...


def rectangle_signed_distance(points_local: np.ndarray, half_length_m: float, half_width_m: float) -> np.ndarray:
    """Exact signed distance (m) of points in the robot frame (..., 2) to the centred rectangle.

    Positive outside (Euclidean distance to the boundary), negative inside (minus the depth).
    """
    qx = np.abs(points_local[..., 0]) - half_length_m
    qy = np.abs(points_local[..., 1]) - half_width_m
    ox, oy = np.maximum(qx, 0.0), np.maximum(qy, 0.0)
    outside = np.sqrt(ox * ox + oy * oy)  # metres: no overflow to guard against (np.hypot is slower)
    inside = np.minimum(np.maximum(qx, qy), 0.0)
    return outside + inside


def points_in_pose_frames(poses: np.ndarray, points_world: np.ndarray) -> np.ndarray:
    """Points (M, 2) in the frames of poses (P, 3) = (x, y, yaw): returns (P, M, 2)."""
    c = np.cos(poses[:, 2])[:, None]
    s = np.sin(poses[:, 2])[:, None]
    dx = points_world[None, :, 0] - poses[:, 0, None]
    dy = points_world[None, :, 1] - poses[:, 1, None]
    out = np.empty((poses.shape[0], points_world.shape[0], 2))
    out[..., 0] = c * dx + s * dy
    out[..., 1] = -s * dx + c * dy
    return out


def footprint_distance_to_points(
    poses: np.ndarray, points_world: np.ndarray, half_length_m: float, half_width_m: float
) -> np.ndarray:
    """Exact signed distance (P, M) from the footprint at each pose (P, 3) to each point (M, 2)."""
    return rectangle_signed_distance(points_in_pose_frames(poses, points_world), half_length_m, half_width_m)


class ExactRectangleDual:
    """Closed-form solution of the dual problem (paper eq. 11) for a centred rectangle.

    The optimal mu puts weight only on the (at most two) edges the nearest boundary point lies
    on; outside a corner mu is the unit direction to the point. Same interface as the net.
    """

    def __init__(self, half_length_m: float, half_width_m: float) -> None:
        if not (half_length_m > 0 and half_width_m > 0):
            raise PlannerInputError(
                f"ExactRectangleDual: half sizes must be positive, got {half_length_m}, {half_width_m}"
            )
        self.half_length_m = float(half_length_m)
        self.half_width_m = float(half_width_m)
        # Rows: front, left, rear, right (as Footprint.halfspaces()).
        self.G = np.array([[1.0, 0.0], [0.0, 1.0], [-1.0, 0.0], [0.0, -1.0]])
        self.g = np.array([half_length_m, half_width_m, half_length_m, half_width_m])

    @classmethod
    def for_robot(cls, robot) -> "ExactRectangleDual":
        """Build from a RobotDescription's footprint."""
        return cls(robot.footprint.length_m / 2.0, robot.footprint.width_m / 2.0)

    def dual(self, points_robot_frame: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        p = np.asarray(points_robot_frame, dtype=np.float64)
        if p.ndim != 2 or p.shape[1] != 2:
            raise PlannerInputError(f"ExactRectangleDual.dual: expected (N, 2) points, got {p.shape}")
        qx = np.abs(p[:, 0]) - self.half_length_m
        qy = np.abs(p[:, 1]) - self.half_width_m
        px_pos = p[:, 0] >= 0.0
        py_pos = p[:, 1] >= 0.0
        wx = np.maximum(qx, 0.0)
        wy = np.maximum(qy, 0.0)
        norm = np.hypot(wx, wy)
        outside = norm > 0.0
        inside_x = ~outside & (qx >= qy)  # inside: the nearest edge is the x edge
        mx = np.where(outside, wx / np.where(outside, norm, 1.0), inside_x.astype(np.float64))
        my = np.where(outside, wy / np.where(outside, norm, 1.0), (~outside & ~inside_x).astype(np.float64))
        mu = np.zeros((p.shape[0], 4))
        mu[:, 0] = np.where(px_pos, mx, 0.0)
        mu[:, 2] = np.where(px_pos, 0.0, mx)
        mu[:, 1] = np.where(py_pos, my, 0.0)
        mu[:, 3] = np.where(py_pos, 0.0, my)
        lam = -(mu @ self.G)
        distance = norm + np.minimum(np.maximum(qx, qy), 0.0)
        return mu, lam, distance


def check_dual_output(
    out: tuple[np.ndarray, np.ndarray, np.ndarray], n_points: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Validate a distance model's (mu, lam, distance) for n_points; raise DistanceModelError."""
    try:
        mu, lam, dist = (np.asarray(a, dtype=np.float64) for a in out)
    except (TypeError, ValueError) as exc:
        raise DistanceModelError(f"distance model dual() must return (mu, lam, distance): {exc}") from exc
    if mu.shape != (n_points, 4) or lam.shape != (n_points, 2) or dist.shape != (n_points,):
        raise DistanceModelError(
            f"distance model dual() returned shapes mu {mu.shape}, lam {lam.shape}, distance {dist.shape}; "
            f"expected ({n_points}, 4), ({n_points}, 2), ({n_points},)"
        )
    if not (np.isfinite(mu).all() and np.isfinite(lam).all() and np.isfinite(dist).all()):
        raise DistanceModelError("distance model dual() returned NaN or infinite values")
    return mu, lam, dist
