"""The MPC's collision rows (12d) from the distance model.

For the K P_fix points nearest to each predicted pose h = 1..H (runtime.planning.point_selection),
the model's dual (mu, lambda) at the nominal pose gives a row linear in the pose,

    d(s_h) ~ d_bar + lambda_w^T (t_h - t_bar) + dd/dtheta (theta_h - theta_bar) >= r_hk - e_hk,

with lambda_w = R(theta_bar) lam_robot = -R G^T mu (the gradient of the dual objective in t) and
an L1-penalized slack e_hk >= 0 so that the QP is always feasible. The required clearance r_hk is
d_min, or the point's distance to the footprint now where that is smaller ("never plan deeper":
such a row holds with standing still, and its slack costs `slack_linear_holding`).
"""
from __future__ import annotations

import math
import time

import numpy as np

from runtime.planning.distance_model import (
    DistanceModel,
    check_dual_output,
    footprint_distance_to_points,
    rectangle_signed_distance,
)
from runtime.planning.errors import check_points
from runtime.planning.mpc_config import MpcConfig
from runtime.planning.mpc_qp import MpcLinearization
from runtime.planning.point_selection import PointSelector


class CollisionRows:
    """Selects the constraint points at the nominal poses and writes the QP's collision rows."""

    def __init__(self, config: MpcConfig, distance_model: DistanceModel, half_length_m: float,
                 half_width_m: float) -> None:
        self.config = config
        self.distance_model = distance_model
        self.half_length_m = half_length_m
        self.half_width_m = half_width_m
        self.selector = PointSelector(config.points, half_length_m, half_width_m)
        H, K = config.horizon_steps, config.points.points_per_pose
        self._dummy_far = np.array([1.0e3, 0.0])
        self._local = np.empty((H, K, 2))  # robot-frame points of the net's batch
        self.last_selection = None
        # required_clearance and the slack weights of (selection, state0), the last fill's
        self._required_for = None
        self._required_at: tuple | None = None
        self._required: np.ndarray | None = None
        self._slack_weight: np.ndarray | None = None

    def select(self, nominal_states: np.ndarray, points_world: np.ndarray, timings: dict) -> None:
        """The K P_fix points nearest to each nominal pose; once per plan, kept for all alternations
        (NeuPAN's PAN iterations also keep the point set and re-run only the net and the QP)."""
        t0 = time.perf_counter()
        self.last_selection = self.selector.select(nominal_states[1:], points_world, points_checked=True)
        timings["select"] += (time.perf_counter() - t0) * 1e3

    def in_pose_frames(self, poses: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(cos, sin) of the poses' yaw (H, 1) and the selected points in pose h's frame, written
        into the preallocated (H, K, 2) buffer."""
        sel = self.last_selection
        c, s = np.cos(poses[:, 2])[:, None], np.sin(poses[:, 2])[:, None]
        dx = sel.points_world[..., 0] - poses[:, 0, None]
        dy = sel.points_world[..., 1] - poses[:, 1, None]
        local = self._local
        local[..., 0] = c * dx + s * dy
        local[..., 1] = -s * dx + c * dy
        return c, s, local

    def fill(self, lin: MpcLinearization, nominal_states: np.ndarray, timings: dict) -> int:
        """Run the distance model at the nominal poses on the selected points and fill the rows."""
        H, K = self.config.horizon_steps, self.config.points.points_per_pose
        sel = self.last_selection
        t1 = time.perf_counter()
        poses = nominal_states[1:]
        c, s, local = self.in_pose_frames(poses)
        local[~sel.valid] = self._dummy_far  # fixed-size batch for the net; rows inactive anyway
        n = H * K
        mu, lam_r, dist = check_dual_output(self.distance_model.dual(local.reshape(n, 2)), n)
        t2 = time.perf_counter()
        lam_r = lam_r.reshape(H, K, 2)
        dist = dist.reshape(H, K)
        lx = c * lam_r[..., 0] - s * lam_r[..., 1]  # lambda_w = R lam_robot
        ly = s * lam_r[..., 0] + c * lam_r[..., 1]
        coef = lin.coll_coef
        coef[..., 0] = lx
        coef[..., 1] = ly
        state0 = tuple(lin.state0.tolist())
        # once per plan: every alternation has the same selection and state0
        if self._required_for is not sel or self._required_at != state0:
            self._required_for, self._required_at = sel, state0
            self._required = required = self.required_clearance(lin, sel)
            w = self.config.weights
            self._slack_weight = np.where(required < self.config.d_min_m, w.slack_linear_holding, w.slack_linear)
        required = self._required
        rhs = required - dist + lx * poses[:, 0, None] + ly * poses[:, 1, None]
        if self.config.linearize_heading:
            lth = lam_r[..., 1] * local[..., 0] - lam_r[..., 0] * local[..., 1]
            coef[..., 2] = lth
            rhs += lth * poses[:, 2, None]
        lin.coll_rhs[:] = rhs
        lin.coll_active[:] = sel.valid
        lin.coll_slack_weight[:] = self._slack_weight
        timings["net"] += (t2 - t1) * 1e3
        timings["rows"] += (time.perf_counter() - t2) * 1e3
        return sel.count

    def required_clearance(self, lin: MpcLinearization, sel) -> np.ndarray:
        """(H, K) clearance each row demands: d_min, or, for a point the footprint at the current
        pose (lin.state0) is already nearer to than d_min, that current distance ("never plan
        deeper").

        A non-holonomic robot cannot step sideways out of d_min within 0.1 s, so a row demanding
        d_min of such a point is violated by every plan: its slack is paid anyway, and the QP
        would trade further millimetres of penetration for tracking at the slack's flat L1 price,
        which the safety supervisor (it stops any command that brings the footprint nearer than
        now inside d_stop) refuses tick after tick. Demanding the current distance keeps every
        row satisfiable (standing still meets it), so the exact L1 penalty holds it, and the plan
        slides along or away from the point, which the supervisor accepts
        (docs/decisions/planning-mpc-standstill.md)."""
        pts = sel.points_world
        d_now = footprint_distance_to_points(
            lin.state0[None], pts.reshape(-1, 2), self.half_length_m, self.half_width_m
        ).reshape(pts.shape[:2])
        return np.minimum(self.config.d_min_m, d_now)

    def linearize(self, lin: MpcLinearization, nominal_states: np.ndarray, points_world: np.ndarray,
                  timings: dict) -> int:
        """Select the points at the nominal poses, then fill the collision rows (both steps)."""
        points_world = check_points(points_world, "CollisionRows.linearize: points_world")
        self.select(nominal_states, points_world, timings)
        return self.fill(lin, nominal_states, timings)

    def min_predicted_distance(self, states: np.ndarray) -> float:
        """Exact distance of each predicted pose states[1:] to its own constraint points (the rows
        it saw), the least of them; inf without any."""
        sel = self.last_selection
        if sel is not None and sel.count:
            local = self.in_pose_frames(states[1:])[2]
            d = rectangle_signed_distance(local, self.half_length_m, self.half_width_m)
            return float(d[sel.valid].min())
        return math.inf
