"""The MPC QP's fixed sparsity pattern: where each variable and constraint row lies, the
constraint matrix's entries in a fixed order (the groups rewritten each solve named by slices),
the map from that order to the CSC data order OSQP keeps, and the cost matrix.

Variables z = [s_0..s_H (3(H+1)), u_0..u_{H-1} (2H), e_{1,1}..e_{H,K} (HK)].
Rows: initial state (3), dynamics (3H), input bounds (2H), rate bounds (2H),
collision (HK), slack >= 0 (HK). All H*K collision rows are always present (unused ones have
zero coefficients, kept as explicit entries), so OSQP is set up once and each solve only
rewrites the numbers (runtime.planning.mpc_qp).
"""
from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from runtime.planning.mpc_config import MpcConfig


class _EntryList:
    """The constraint matrix's entries in the order they are added; named groups keep a slice."""

    def __init__(self) -> None:
        self.rows: list[np.ndarray] = []
        self.cols: list[np.ndarray] = []
        self.vals: list[np.ndarray] = []
        self.slices: dict[str, slice] = {}
        self.nnz = 0

    def add(self, name: str | None, r, c, v) -> None:
        r = np.asarray(r, dtype=np.int64).ravel()
        c = np.asarray(c, dtype=np.int64).ravel()
        v = np.broadcast_to(np.asarray(v, dtype=np.float64), r.shape).ravel()
        self.rows.append(r)
        self.cols.append(c)
        self.vals.append(v.copy())
        if name is not None:
            self.slices[name] = slice(self.nnz, self.nnz + r.size)
        self.nnz += r.size


class QpLayout:
    """Sizes, row offsets and the constraint matrix's pattern of the MPC QP (module docstring).

    `values` holds the entries in our order (the groups named in `slices` rewritten each solve);
    `perm` maps CSC data position -> our entry index; `A` is the matrix OSQP is set up with."""

    def __init__(self, config: MpcConfig) -> None:
        H = config.horizon_steps
        K = config.points.points_per_pose
        self.H, self.K = H, K
        self.n_s, self.n_u, self.n_e = 3 * (H + 1), 2 * H, H * K
        self.n = self.n_s + self.n_u + self.n_e
        entries = _EntryList()
        self._dynamics_and_input_rows(entries, config.step_s)
        self._collision_and_slack_rows(entries, config.linearize_heading)
        self.slices = entries.slices
        self.nnz = entries.nnz
        r_all, c_all, v_all = np.concatenate(entries.rows), np.concatenate(entries.cols), np.concatenate(entries.vals)
        # CSC with a known map from our entry order to OSQP's data order: build it from entry ids.
        nnz = self.nnz
        ids = sp.csc_matrix((np.arange(1, nnz + 1, dtype=np.float64), (r_all, c_all)), shape=(self.m, self.n))
        ids.sort_indices()
        if ids.nnz != nnz:
            raise AssertionError("OsqpMpcBackend: duplicate entries in the constraint pattern")
        self.perm = ids.data.astype(np.int64) - 1  # csc position -> our entry index
        self.values = v_all  # our order; varying groups rewritten each solve
        self.A = sp.csc_matrix((self.values[self.perm], ids.indices.copy(), ids.indptr.copy()), shape=(self.m, self.n))

    def _state_col(self, h):
        return 3 * h

    def _input_col(self, h):
        return self.n_s + 2 * h

    def _dynamics_and_input_rows(self, entries: _EntryList, dt: float) -> None:
        """Initial state, the linearized unicycle (12b), input and rate bounds (12c)."""
        H, add, sx, uv = self.H, entries.add, self._state_col, self._input_col
        hs = np.arange(H)
        add(None, [0, 1, 2], [0, 1, 2], 1.0)
        r_dyn = 3
        rx, ry, rt = r_dyn + 3 * hs, r_dyn + 3 * hs + 1, r_dyn + 3 * hs + 2
        add(None, rx, sx(hs), 1.0)
        add("a02", rx, sx(hs) + 2, 0.0)
        add("b0", rx, uv(hs), 0.0)
        add(None, rx, sx(hs + 1), -1.0)
        add(None, ry, sx(hs) + 1, 1.0)
        add("a12", ry, sx(hs) + 2, 0.0)
        add("b1", ry, uv(hs), 0.0)
        add(None, ry, sx(hs + 1) + 1, -1.0)
        add(None, rt, sx(hs) + 2, 1.0)
        add(None, rt, uv(hs) + 1, dt)
        add(None, rt, sx(hs + 1) + 2, -1.0)
        self.r_box = r_dyn + 3 * H
        add(None, self.r_box + np.arange(2 * H), self.n_s + np.arange(2 * H), 1.0)
        self.r_rate = self.r_box + 2 * H
        add(None, self.r_rate + np.arange(2 * H), self.n_s + np.arange(2 * H), 1.0)
        add(None, self.r_rate + 2 + np.arange(2 * H - 2), self.n_s + np.arange(2 * H - 2), -1.0)

    def _collision_and_slack_rows(self, entries: _EntryList, linearize_heading: bool) -> None:
        """Collision rows (12d) with their slack, then slack >= 0."""
        H, K, add, sx = self.H, self.K, entries.add, self._state_col
        hs = np.arange(H)
        self.r_coll = self.r_rate + 2 * H
        hk_h = np.repeat(hs + 1, K)  # pose index 1..H of each collision row
        r_c = self.r_coll + np.arange(H * K)
        add("cx", r_c, sx(hk_h), 0.0)
        add("cy", r_c, sx(hk_h) + 1, 0.0)
        if linearize_heading:  # else the rows do not touch theta: no entries to factorize
            add("cth", r_c, sx(hk_h) + 2, 0.0)
        e_cols = self.n_s + self.n_u + np.arange(H * K)
        add(None, r_c, e_cols, 1.0)
        self.r_slack = self.r_coll + H * K
        add(None, self.r_slack + np.arange(H * K), e_cols, 1.0)
        self.m = self.r_slack + H * K

    def cost_matrix(self, config: MpcConfig) -> sp.csc_matrix:
        """P of the cost (13), upper triangle: tracking, input size and change, slack."""
        w = config.weights
        H, n_s = self.H, self.n_s
        diag = np.zeros(self.n)
        pos_w = np.full(H, w.position)
        pos_w[-1] = w.terminal_position
        diag[3 * np.arange(1, H + 1)] = 2 * pos_w
        diag[3 * np.arange(1, H + 1) + 1] = 2 * pos_w
        diag[3 * np.arange(1, H + 1) + 2] = 2 * w.heading
        dv, dw = w.speed_change, w.angular_speed_change
        # Input changes: (u_0 - u_prev)^2 + sum_h (u_h - u_{h-1})^2.
        cnt = np.full(H, 2.0)
        cnt[-1] = 1.0
        diag[n_s + 2 * np.arange(H)] = 2 * w.speed + 2 * dv * cnt
        diag[n_s + 2 * np.arange(H) + 1] = 2 * w.angular_speed + 2 * dw * cnt
        diag[n_s + self.n_u :] = 2 * w.slack_quadratic + 1e-6
        r = [np.arange(self.n), n_s + 2 * np.arange(H - 1), n_s + 2 * np.arange(H - 1) + 1]
        c = [np.arange(self.n), n_s + 2 * np.arange(1, H), n_s + 2 * np.arange(1, H) + 1]
        v = [diag, np.full(H - 1, -2 * dv), np.full(H - 1, -2 * dw)]
        P = sp.csc_matrix((np.concatenate(v), (np.concatenate(r), np.concatenate(c))), shape=(self.n, self.n))
        return sp.triu(P, format="csc")
