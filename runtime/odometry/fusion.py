"""One pose stream in the odom frame, with a covariance, from wheels + gyro and KISS-ICP.

Which filter, and why: an extended Kalman filter on pose *increments* (information form), not a
complementary filter. KISS-ICP is odometry too: it measures the motion between two frames, not
an absolute pose, so fusing its increments (rather than its drifting pose) counts every
measurement once. And its certainty depends on the direction: in a corridor it knows the
across-axis motion to a few millimetres and the along-axis motion not at all (the Hessian,
runtime.odometry.degeneracy). A complementary filter blends with one fixed gain per axis; the
EKF weighs each direction by its information, so a degenerate direction falls back to the wheels
by itself while the constrained ones follow the lidar.

The state:
- the dead-reckoning pose D(t) from wheels and gyro (runtime.odometry.wheels), every tick, kept
  in a short history so that an ICP result stamped in the past can be placed;
- the anchor: the fused pose F_a at the time t_a of the newest ICP result, with its covariance.

Output at any time t: F(t) = F_a (+) (D(t_a)^-1 (+) D(t)): the newest ICP-corrected pose,
predicted forward with the wheels and the gyro. Between scans, when ICP is late and when ICP is
degenerate, wheels and gyro carry the pose.

An ICP result for the frame ending at t_b (its increment since the previous result at t_a):
the wheel increment over the same interval d_w (covariance Q from the wheel noise model: a
share of the distance along the track, a larger share across it and per radian turned, as a
skid-steer base slips sideways when it turns), the ICP increment d_i (covariance R from the scan's
constraint: `icp_sigma` along constrained directions, `degenerate_variance` along a degenerate
one), fused: P = (Q^-1 + R^-1)^-1, d = P (Q^-1 d_w + R^-1 d_i); F_b = F_a (+) d. An ICP increment
that no robot could have made (farther from the wheels' than `gate_m` + `gate_fraction` of the
distance, or `gate_rad` in yaw) is refused and the wheels' is used (counted, named). Over an
interval in which the base said nothing of its motion (no wheel distances, no speed: a bus-off,
a rebooting base) the wheels' translation is unknown, not zero: ICP's translation is taken (its
rotation is still judged against the gyro's).

The gyro's bias is estimated online from the same ICP frames (runtime.odometry.gyro_bias), over
blocks of consecutive fused frames whose rotation ICP constrains; a block over which the gyro and
ICP disagree beyond the estimate's gate has its heading given back to ICP (the anchor's yaw),
and the gyro's rotation is weighed by the bias's uncertainty, so that while a bias step is being
learnt ICP leads the heading. The stage applies the estimate to the dead reckoning
(runtime.odometry.stage).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from runtime.odometry.gyro_bias import GyroBiasConfig, GyroBiasEstimator
from runtime.odometry.icp import IcpResult
from runtime.odometry.se2 import compose_jacobians, se2_between, se2_compose, wrap


class FusionConfig(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)

    # Increment noise (1 sigma), per ICP frame (0.1 s): wheels + gyro from their measured errors;
    # the ICP sigmas a choice between its drift and its jitter: translation 2 mm (ICP leads where
    # the scan constrains it), yaw 2 mrad (the gyro leads); wheels and gyro lead along a
    # degenerate direction in any case. See docs/decisions/odometry-fusion-noise.md.
    wheel_along_fraction: float = Field(0.03, gt=0.0, le=1.0)  # of the distance (skid, scale)
    wheel_across_fraction: float = Field(0.02, gt=0.0, le=1.0)  # of the distance (sideways slip)
    wheel_across_per_rad_m: float = Field(0.01, ge=0.0, le=1.0)  # sideways slip per radian turned
    gyro_fraction: float = Field(0.005, ge=0.0, le=1.0)  # of the angle turned (gyro scale)
    gyro_rate_sigma_radps: float = Field(0.003, ge=0.0, le=1.0)  # bias walk, as a rate
    wheel_floor_m: float = Field(0.001, gt=0.0, le=1.0)  # per increment: nothing is exact
    wheel_floor_rad: float = Field(0.0003, gt=0.0, le=1.0)
    # ICP increment noise along well-constrained directions (see above).
    icp_sigma_m: float = Field(0.002, gt=0.0, le=1.0)
    icp_sigma_rad: float = Field(0.002, gt=0.0, le=1.0)
    #: A constrained direction with a normalised eigenvalue of `reference_eigenvalue` gets
    #: icp_sigma; a weaker one proportionally more variance.
    reference_eigenvalue: float = Field(0.4, gt=0.0, le=1.0)
    #: Variance along a degenerate direction (m^2 or rad^2): the wheels decide there.
    degenerate_variance: float = Field(1e4, gt=0.0)
    # Plausibility gate of an ICP increment against the wheels'.
    gate_m: float = Field(0.10, gt=0.0, le=10.0)
    gate_fraction: float = Field(0.5, ge=0.0, le=10.0)
    gate_rad: float = Field(0.15, gt=0.0, le=3.2)
    #: How far back (s) the dead-reckoning history reaches (ICP results older are dropped).
    history_s: float = Field(3.0, gt=0.2, le=60.0)
    #: The online estimate of the gyro's bias from ICP's rotation (runtime.odometry.gyro_bias).
    gyro_bias: GyroBiasConfig = GyroBiasConfig()


@dataclass
class FusionStats:
    results: int = 0
    fused: int = 0
    refused: int = 0
    too_old: int = 0
    degenerate: int = 0
    wheels_blind: int = 0  # fused with the translation from ICP alone (the base said nothing of it)


class PoseFusion:
    """EKF on increments: wheels + gyro predict, KISS-ICP increments correct (module docstring)."""

    def __init__(self, config: FusionConfig, capacity: int = 1024, gyro_bias: GyroBiasEstimator | None = None) -> None:
        """capacity: dead-reckoning samples kept (one per tick; 1024 = 51 s at 20 Hz, more than
        history_s can ask for). gyro_bias: the estimate to go on with (a fusion started afresh
        keeps what was learnt of the gyro); None: a new one, at zero."""
        self.config = config
        self._cap = capacity
        self._t = np.full(capacity, -np.inf)
        self._d = np.zeros((capacity, 3))
        #: With each D(t): the raw gyro's integral and the time it covers (add_dead_reckoning).
        self._g = np.full((capacity, 2), np.nan)
        self.gyro_bias = gyro_bias if gyro_bias is not None else GyroBiasEstimator(config.gyro_bias)
        self._n = 0  # samples written (ring index = n % cap)
        self.anchor_t: float | None = None
        self.anchor_pose = np.zeros(3)
        self.anchor_cov = np.zeros((3, 3))
        self._anchor_d = np.zeros(3)
        self._blind_t: float | None = None  # the last tick at which the wheels knew no translation
        self.stats = FusionStats()
        #: Time of the newest ICP result that was fused (None: none yet): the age of the correction.
        self.last_fused_t: float | None = None

    def start_at(self, pose) -> None:
        """Begin the fused pose at `pose` (an earlier run's frame continued) instead of the origin;
        only before the first dead-reckoning sample, whose pose it then stands for."""
        if self._n:
            raise RuntimeError("start_at after dead reckoning began")
        self.anchor_pose = np.array([pose.x_m, pose.y_m, pose.yaw_rad], dtype=float)

    # -- dead reckoning ------------------------------------------------------------------------
    def add_dead_reckoning(self, t_s: float, pose: np.ndarray, translation_known: bool = True,
                           gyro: tuple[float, float] | None = None) -> None:
        """The wheel + gyro pose D(t) (call every tick, times increasing). translation_known False:
        the base said nothing of its motion since the call before (no wheel distances, no speed):
        D did not move, which is not "the robot stood still"; an ICP increment over that time is
        then judged and fused on its rotation only and gives the translation (icp_update).
        gyro: the raw gyro's yaw integral (rad) and the time it has covered (s) so far
        (runtime.odometry.wheels), for the bias estimate; None: no gyro."""
        if not translation_known:
            self._blind_t = t_s
        i = self._n % self._cap
        self._t[i] = t_s
        self._d[i] = pose
        self._g[i] = gyro if gyro is not None else (np.nan, np.nan)
        self._n += 1
        if self.anchor_t is None:
            self.anchor_t = t_s
            self._anchor_d = np.array(pose, dtype=float)

    def _locate(self, t_s: float) -> tuple[np.ndarray, int, float] | None:
        """Where t_s falls in the history: (ring indices in time order, j, w) for the samples
        j-1 and j weighted 1-w and w (j = 0: the oldest alone; w = 1 past the newest); None
        when t_s is outside it."""
        n = min(self._n, self._cap)
        if n == 0:
            return None
        order = np.argsort(self._t[:n]) if self._n > self._cap else np.arange(n)
        ts = self._t[:n][order]
        if t_s < ts[-1] - self.config.history_s:
            return None
        if t_s < ts[0] - 1e-9 or t_s > ts[-1] + 1e-9:
            # A little past the newest sample (the frame ended after the last tick): hold it.
            if ts[-1] < t_s <= ts[-1] + 0.06:
                return order, n - 1, 1.0
            return None
        j = int(np.searchsorted(ts, t_s))
        if j == 0:
            return order, 1 if n > 1 else 0, 0.0 if n > 1 else 1.0
        if j >= n:
            return order, n - 1, 1.0
        t0, t1 = ts[j - 1], ts[j]
        return order, j, 0.0 if t1 <= t0 else (t_s - t0) / (t1 - t0)

    def dead_reckoning_at(self, t_s: float) -> np.ndarray | None:
        """D(t) interpolated from the history (None when t is outside it)."""
        where = self._locate(t_s)
        if where is None:
            return None
        order, j, w = where
        b = self._d[order[j]]
        if j == 0 or w >= 1.0:
            return b.copy()
        a = self._d[order[j - 1]]
        return np.array([a[0] + w * (b[0] - a[0]), a[1] + w * (b[1] - a[1]), wrap(a[2] + w * wrap(b[2] - a[2]))])

    def gyro_at(self, t_s: float) -> np.ndarray | None:
        """The raw gyro's (yaw integral, covered time) at t_s, interpolated (None: outside the
        history, or no gyro there)."""
        where = self._locate(t_s)
        if where is None:
            return None
        order, j, w = where
        b = self._g[order[j]]
        g = b.copy() if j == 0 or w >= 1.0 else self._g[order[j - 1]] + w * (b - self._g[order[j - 1]])
        return None if np.isnan(g).any() else g

    def motion_samples(self, t0_s: float, t1_s: float) -> np.ndarray:
        """Dead-reckoning samples (K, 4: t, x, y, yaw) covering [t0, t1] (for deskew)."""
        n = min(self._n, self._cap)
        ts = self._t[:n]
        sel = (ts >= t0_s - 0.06) & (ts <= t1_s + 0.06)
        out = np.column_stack([ts[sel], self._d[:n][sel]])
        return out[np.argsort(out[:, 0])]

    # -- output --------------------------------------------------------------------------------
    def pose_now(self, d_now: np.ndarray, now_s: float) -> tuple[np.ndarray, np.ndarray]:
        """The fused pose for the dead-reckoning pose now, and its covariance."""
        inc = se2_between(self._anchor_d, d_now)
        pose = se2_compose(self.anchor_pose, inc)
        ja, jb = compose_jacobians(self.anchor_pose, inc)
        dt = max(0.0, now_s - self.anchor_t) if self.anchor_t is not None else 0.0
        cov = ja @ self.anchor_cov @ ja.T + jb @ self.wheel_covariance(inc, dt) @ jb.T
        return pose, cov

    # -- noise models --------------------------------------------------------------------------
    def wheel_covariance(self, inc: np.ndarray, dt_s: float, bias_sigma_radps: float | None = None) -> np.ndarray:
        """bias_sigma_radps: the uncertainty of the gyro bias applied over the increment, when
        it exceeds the configured rate noise (a bias step being learnt); None: the estimate's now."""
        c = self.config
        dist = math.hypot(inc[0], inc[1])
        turn = abs(inc[2])
        along = c.wheel_along_fraction * dist + c.wheel_floor_m
        across = c.wheel_across_fraction * dist + c.wheel_across_per_rad_m * turn + c.wheel_floor_m
        heading = math.atan2(inc[1], inc[0]) if dist > 1e-6 else 0.0
        ch, sh = math.cos(heading), math.sin(heading)
        rot = np.array([[ch, -sh], [sh, ch]])
        cov = np.zeros((3, 3))
        cov[:2, :2] = rot @ np.diag([along**2, across**2]) @ rot.T
        if bias_sigma_radps is None:
            bias_sigma_radps = self.gyro_bias.sigma_radps
        rate_sigma = max(c.gyro_rate_sigma_radps, bias_sigma_radps)
        yaw = c.gyro_fraction * turn + rate_sigma * dt_s + c.wheel_floor_rad
        cov[2, 2] = yaw**2
        return cov

    def icp_covariance(self, result: IcpResult) -> np.ndarray:
        """R of the ICP increment, in the base frame at the previous frame (where the increment is
        expressed; the scan's constraint directions are in the base frame at this frame's end)."""
        c = self.config
        con = result.constraint
        cov = np.zeros((3, 3))
        if con is None:
            cov[:2, :2] = np.eye(2) * c.degenerate_variance
            cov[2, 2] = c.degenerate_variance
            return cov
        # Along each eigenvector: icp_sigma scaled by how much weaker than the reference it is;
        # the weakest one not at all when it is degenerate (the eigenvalues are ascending).
        var = [c.icp_sigma_m**2 * c.reference_eigenvalue / max(float(lam), 1e-6) for lam in con.eigenvalues_xy]
        if con.degenerate_xy:
            var[0] = c.degenerate_variance
        if con.too_few_points:
            var = [c.degenerate_variance, c.degenerate_variance]
        turn = float(result.delta_base[2]) if result.delta_base is not None else 0.0
        ct, st = math.cos(turn), math.sin(turn)
        v = np.array([[ct, -st], [st, ct]]) @ con.eigenvectors_xy
        cov[:2, :2] = v @ np.diag(var) @ v.T
        cov[2, 2] = c.degenerate_variance if con.degenerate_yaw else (
            c.icp_sigma_rad**2 * c.reference_eigenvalue / max(con.yaw_eigenvalue, 1e-6))
        return cov

    # -- ICP update ----------------------------------------------------------------------------
    def icp_update(self, result: IcpResult) -> str | None:
        """Fuse one ICP result; returns None when fused, else why it was not."""
        self.stats.results += 1
        if result.constraint is not None and result.constraint.degenerate:
            self.stats.degenerate += 1
        t_b = result.end_s
        if self.anchor_t is None:
            return self._refuse("no wheel odometry yet")
        d_b = self.dead_reckoning_at(t_b)
        if d_b is None:
            self.stats.too_old += 1
            return self._refuse(f"frame end {t_b:.3f} s is outside the {self.config.history_s:.1f} s odometry history")
        d_w = se2_between(self._anchor_d, d_b)   # wheels from the anchor to t_b
        if result.delta_base is None or result.prev_end_s is None or result.error is not None:
            # The first frame (or one ICP could not register): move the anchor with the wheels.
            self._move_anchor(t_b, d_b, d_w, self.wheel_covariance(d_w, t_b - self.anchor_t))
            if result.error is not None:
                return self._refuse(f"ICP could not register the frame: {result.error}")
            return None
        if abs(result.prev_end_s - self.anchor_t) > 1e-6:
            # The anchor is not at ICP's previous frame (a result was lost): wheels up to it.
            self._move_anchor(t_b, d_b, d_w, self.wheel_covariance(d_w, t_b - self.anchor_t))
            return self._refuse("previous ICP frame missing: wheels and gyro carried the pose")
        d_i = np.asarray(result.delta_base, dtype=float)
        c = self.config
        dist = math.hypot(d_w[0], d_w[1])
        off = math.hypot(d_i[0] - d_w[0], d_i[1] - d_w[1])
        off_yaw = abs(wrap(d_i[2] - d_w[2]))
        bias_sigma, bias_back = self._observe_gyro_bias(result, d_i) if off_yaw <= c.gate_rad else (None, None)
        q = self.wheel_covariance(d_w, t_b - self.anchor_t, bias_sigma)
        if self._blind_t is not None and self._blind_t > self.anchor_t - 1e-9:
            # the wheels knew nothing of the translation over part of this interval: ICP's counts
            self.stats.wheels_blind += 1
            q[:2, :] = 0.0
            q[:, :2] = 0.0
            q[0, 0] = q[1, 1] = c.degenerate_variance
            off = 0.0
        if off > c.gate_m + c.gate_fraction * dist or off_yaw > c.gate_rad:
            self.gyro_bias.break_run()
            self._move_anchor(t_b, d_b, d_w, q)
            return self._refuse(f"ICP increment {off * 100:.1f} cm / {math.degrees(off_yaw):.1f} deg from the "
                                f"wheels' over {t_b - result.prev_end_s:.2f} s: implausible, wheels used")
        r = self.icp_covariance(result)
        q_inf, r_inf = np.linalg.inv(q), np.linalg.inv(r)
        p = np.linalg.inv(q_inf + r_inf)
        innov = d_i - d_w
        innov[2] = wrap(innov[2])
        d = d_w + p @ (r_inf @ innov)   # = P (Q^-1 d_w + R^-1 d_i), angles wrapped
        d[2] = wrap(d[2])
        self._move_anchor(t_b, d_b, d, p)
        if bias_back is not None:
            # a block in which the gyro and ICP disagree beyond the bias's gate: its heading is
            # ICP's (runtime.odometry.gyro_bias)
            self.anchor_pose[2] = wrap(self.anchor_pose[2] - bias_back)
        self.stats.fused += 1
        self.last_fused_t = t_b
        return None

    def _observe_gyro_bias(self, result: IcpResult, d_i: np.ndarray) -> tuple[float | None, float | None]:
        """ICP's rotation over the frame into the gyro bias's estimate (runtime.odometry.gyro_bias).
        Returns (the bias's uncertainty before this frame, which the dead reckoning's rotation
        over it carried; None when the frame is no observation: ICP does not constrain the
        rotation, or no gyro over it), and (when this frame completed a block over which the gyro
        and ICP disagree beyond the estimate's gate) the rotation the gyro put into the block's
        heading beyond ICP's, else None."""
        con = result.constraint
        est = self.gyro_bias
        if con is None or con.degenerate_yaw or con.too_few_points:
            est.break_run()
            return None, None
        g_a, g_b = self.gyro_at(result.prev_end_s), self.gyro_at(result.end_s)
        if g_a is None or g_b is None:
            est.break_run()
            return None, None
        prior = est.sigma_radps
        back = est.add_frame(result.end_s, float(g_b[0] - g_a[0]), float(d_i[2]), result.end_s - result.prev_end_s,
                             float(g_b[1] - g_a[1]))
        return prior, back

    def _move_anchor(self, t_b: float, d_b: np.ndarray, inc: np.ndarray, inc_cov: np.ndarray) -> None:
        ja, jb = compose_jacobians(self.anchor_pose, inc)
        self.anchor_cov = ja @ self.anchor_cov @ ja.T + jb @ inc_cov @ jb.T
        self.anchor_pose = se2_compose(self.anchor_pose, inc)
        self.anchor_t = t_b
        self._anchor_d = d_b

    def _refuse(self, why: str) -> str:
        self.stats.refused += 1
        self.gyro_bias.break_run()
        return why


__all__ = ["FusionConfig", "PoseFusion", "FusionStats"]
