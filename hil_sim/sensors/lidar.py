"""Simulated Livox Mid-360 class lidar: a non-repetitive pattern cast with `mujoco.mj_multiRay`.

The pattern is a 2-D low-discrepancy sequence (Roberts' R2 sequence) over the field of view,
360 deg in azimuth and, by default, -7..+52 deg in elevation, uniform in solid angle. Taken in
time order it covers the whole field of view sparsely in every few milliseconds and densely over
several frames, like the Livox rosette: it is not a set of fixed rings. Directions are
precomputed for `pattern_frames` frames; each later pass over the table is turned about the
lidar's z axis by the golden angle, so no two frames are the same.

A frame (default 100 ms, 20,000 rays) is cut into `slices_per_frame` slices. `step(t_s)` casts
every slice due up to t_s from the lidar pose in `data` at that moment, so a frame taken while
the robot moves is distorted exactly as a real one (deskewing matters). Each point is given in
the lidar frame *at the time its ray was cast*, with that time as its offset within the frame.

The rays are cast by hil_sim.sensors.lidar_cast: in this process, or with `cast_in_process` in a
child process of their own, from a copy of the state of each slice's instant, with the same
frames bit for bit.

Robustness: nothing in the physics state makes `step` raise (only a bad call: time not finite
or going backwards). A non-finite distance is a no-return like a miss; a non-finite body pose
makes its slice all no-returns (counted in `invalid_pose_slices`); ranges outside
[min_range_m, max_range_m] (noise included) are dropped.

Pose convention: `step(t_s)` uses `data.xpos`/`data.xmat` of the robot body as MuJoCo last
computed them; pass the time those correspond to (after `mj_step`, the state at the start of
that step; after `mj_forward`/`mj_kinematics`, `data.time`). Call `step` at least once per slice
period (e.g. every physics step); slices cast more than one slice period late are counted in
`late_slices`.
"""
from __future__ import annotations

import math
from collections import deque
from typing import Any

import mujoco
import numpy as np
from numba import njit
from pydantic import BaseModel, ConfigDict, Field, model_validator

from runtime.common.sensor_data import LidarScan

_PLASTIC = 1.324717957244746025960908854  # g for Roberts' R2 sequence: g^3 = g + 1
GOLDEN_ANGLE_RAD = math.pi * (3.0 - math.sqrt(5.0))


class LidarConfig(BaseModel):
    """Simulated lidar settings (defaults: Livox Mid-360 class)."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)

    frame_rate_hz: float = Field(10.0, gt=0.0, le=100.0)
    points_per_frame: int = Field(20_000, gt=0, le=200_000)
    slices_per_frame: int = Field(50, gt=0, le=10_000)
    elevation_min_deg: float = Field(-7.0, ge=-90.0, le=90.0)
    elevation_max_deg: float = Field(52.0, ge=-90.0, le=90.0)
    min_range_m: float = Field(0.1, ge=0.0)
    max_range_m: float = Field(40.0, gt=0.0, le=1000.0)
    range_noise_sigma_m: float = Field(0.02, ge=0.0, le=1.0)
    pattern_frames: int = Field(20, gt=0, le=1000)
    frame_id: str = Field("lidar", min_length=1)
    # Six 0/1 flags: which geom groups the rays can hit (None: all groups).
    geomgroup: tuple[int, int, int, int, int, int] | None = None
    max_queued_frames: int = Field(4, gt=0, le=1000)
    #: Evaluation only: keep the geom id each point hit for this many recent frames
    #: (SimLidar.ground_truth_geom_ids); 0 = none kept (the default: nothing extra is copied).
    ground_truth_frames: int = Field(0, ge=0, le=1000)

    @model_validator(mode="after")
    def _consistent(self) -> "LidarConfig":
        if self.elevation_max_deg <= self.elevation_min_deg:
            raise ValueError(f"elevation_max_deg ({self.elevation_max_deg}) must exceed elevation_min_deg "
                             f"({self.elevation_min_deg})")
        if self.min_range_m >= self.max_range_m:
            raise ValueError(f"min_range_m ({self.min_range_m}) must be below max_range_m ({self.max_range_m})")
        if self.slices_per_frame > self.points_per_frame:
            raise ValueError(f"slices_per_frame ({self.slices_per_frame}) exceeds points_per_frame "
                             f"({self.points_per_frame})")
        return self

    @property
    def frame_duration_s(self) -> float:
        return 1.0 / self.frame_rate_hz


def pattern_directions(n: int, elevation_min_deg: float, elevation_max_deg: float, start: int = 0) -> np.ndarray:
    """Unit directions (n, 3) of the R2 low-discrepancy pattern, uniform in solid angle.

    Point k (counted from `start`) has azimuth 2*pi*frac(0.5 + k/g) and sin(elevation) spread
    uniformly over [sin(el_min), sin(el_max)] by frac(0.5 + k/g^2).
    """
    k = np.arange(start, start + n, dtype=np.float64)
    u = np.mod(0.5 + k / _PLASTIC, 1.0)
    v = np.mod(0.5 + k / _PLASTIC**2, 1.0)
    s0, s1 = math.sin(math.radians(elevation_min_deg)), math.sin(math.radians(elevation_max_deg))
    sin_el = s0 + v * (s1 - s0)
    cos_el = np.sqrt(np.maximum(0.0, 1.0 - sin_el**2))
    az = 2.0 * math.pi * u
    return np.stack([cos_el * np.cos(az), cos_el * np.sin(az), sin_el], axis=1)


def ray_returns(geomid: np.ndarray, dist_m: np.ndarray, max_range_m: float) -> np.ndarray:
    """Which rays of mj_multiRay returned: a geom was hit at a finite distance in [0, max_range_m].
    A miss (-1), a non-finite distance or anything beyond the range is a no-return."""
    with np.errstate(invalid="ignore"):
        return (geomid >= 0) & np.isfinite(dist_m) & (dist_m >= 0.0) & (dist_m <= max_range_m)


@njit(cache=True, nogil=True)
def collect_returns(dl, geomid, dist, noise, sigma, min_range, max_range, offset_s, pts, offs, gids, keep_gids,
                     count):  # pragma: no cover - compiled (exercised through SimLidar)
    """Append the returns of one cast to the frame's buffers; the new point count.

    Per ray, as the numpy expressions it replaces (bit for bit: one IEEE operation each, no
    fused multiply-add): it returned (ray_returns: a geom hit at a distance in [0, max_range]),
    its noisy range r = dist + sigma * noise lies in [min_range, max_range]; the point is the
    lidar-frame direction times r, stored as float32, stamped offset_s.
    """
    k = count
    for i in range(dl.shape[0]):
        d = dist[i]
        if geomid[i] < 0 or not (d >= 0.0 and d <= max_range):  # NaN fails both comparisons
            continue
        r = d + sigma * noise[i] if sigma > 0 else d
        if not (r >= min_range and r <= max_range):
            continue
        pts[k, 0] = dl[i, 0] * r
        pts[k, 1] = dl[i, 1] * r
        pts[k, 2] = dl[i, 2] * r
        offs[k] = offset_s
        if keep_gids:
            gids[k] = geomid[i]
        k += 1
    return k


def _mount_transform(mount: Any) -> np.ndarray:
    """4x4 T_body<-sensor from a robot-description Mount (has .transform()) or a 4x4 array."""
    t = mount.transform() if hasattr(mount, "transform") else mount
    t = np.asarray(t, dtype=np.float64)
    if t.shape != (4, 4) or not np.isfinite(t).all():
        raise ValueError(f"mount must be a Mount or a finite 4x4 transform, got shape {t.shape}")
    r = t[:3, :3]
    if not np.allclose(r @ r.T, np.eye(3), atol=1e-6) or np.linalg.det(r) < 0:
        raise ValueError("mount rotation is not a proper rotation matrix")
    return t


class SimLidar:
    """Mid-360 class lidar on a MuJoCo body; see the module docstring for timing and pose rules.

    robot_body_id: the body carrying the lidar; its geoms are excluded from the rays (only that
    body's, not its children's: put wheels etc. in a geom group and leave it out of
    `config.geomgroup`). -1 or 0: `mount` is a world pose and nothing is excluded.
    mount: T_body<-lidar, a robot-description Mount or a 4x4 array.
    """

    def __init__(self, model: mujoco.MjModel, data: mujoco.MjData, robot_body_id: int, mount: Any,
                 config: LidarConfig | None = None, seed: int = 0, start_s: float = 0.0,
                 cast_in_process: bool = False) -> None:
        """cast_in_process: cast the rays in a child process of their own
        (hil_sim.sensors.lidar_cast.CastProcess: the same frames, the simulator's thread freed
        of the casts); `close` then ends it or leaves it for the next lidar."""
        self.config = config or LidarConfig()
        c = self.config
        if not (-1 <= robot_body_id < model.nbody):
            raise ValueError(f"robot_body_id {robot_body_id} not in [-1, {model.nbody})")
        self._m, self._d = model, data
        self._body = int(robot_body_id)
        t = _mount_transform(mount)
        self._mount_r = t[:3, :3].copy()
        self._mount_t = t[:3, 3].copy()
        from hil_sim.sensors.lidar_cast import CastProcess, RayCaster

        self._caster = (CastProcess if cast_in_process else RayCaster)(model, c, self._body, seed)

        n = c.points_per_frame
        self._period_s = c.frame_duration_s
        self._slice_s = self._period_s / c.slices_per_frame
        self._max_offset_s = float(np.nextafter(np.float32(self._period_s), np.float32(0)))  # < period in float32
        # Slice j of a frame holds rays [bounds[j], bounds[j+1]).
        self._bounds = np.linspace(0, n, c.slices_per_frame + 1).round().astype(np.int64)

        self._start_s = float(start_s)
        self._frame = 0                     # index of the frame being cast
        self._slice = 0                     # next slice to cast in that frame
        self._last_t: float | None = None
        self._truth: deque[tuple[float, np.ndarray]] = deque(maxlen=max(c.ground_truth_frames, 1))
        self._done: deque[LidarScan] = deque()
        self.late_slices = 0
        #: Slices cast while the body pose in data was not finite (all their rays: no return).
        self.invalid_pose_slices = 0
        self.dropped_frames = 0
        self.frames_completed = 0
        #: When the next slice is due: a step before it casts nothing (callers may skip it).
        self.next_due_s = self._due_s(0, 0)
        self._failure: Exception | None = None  # a cast that failed: every later step raises

    def wait_ready(self) -> None:
        """Until the caster can cast (a cast process has started); raises when it cannot."""
        self._caster.wait_ready()

    def close(self) -> None:
        """Release the caster (a cast process ends or waits for the next lidar); once."""
        caster, self._caster = self._caster, None
        if caster is not None:
            caster.close()

    # ------------------------------------------------------------------ pose

    def lidar_pose_world(self) -> tuple[np.ndarray, np.ndarray]:
        """(R_world<-lidar, origin_world) from the body pose currently in data."""
        if self._body <= 0:  # world body or none: the mount is a world pose
            return self._mount_r.copy(), self._mount_t.copy()
        rb = self._d.xmat[self._body].reshape(3, 3)
        pb = self._d.xpos[self._body]
        with np.errstate(invalid="ignore", over="ignore"):  # a diverged state: NaN out, checked by the caller
            return rb @ self._mount_r, pb + rb @ self._mount_t

    # ------------------------------------------------------------------ stepping

    def _due_s(self, frame: int, slice_: int) -> float:
        return self._start_s + frame * self._period_s + slice_ * self._slice_s

    def step(self, t_s: float) -> None:
        """Cast every slice due at or before t_s with the current body pose."""
        t_s = float(t_s)
        if not math.isfinite(t_s):
            raise ValueError(f"SimLidar.step: time {t_s} is not finite")
        if self._last_t is not None and t_s < self._last_t:
            raise ValueError(f"SimLidar.step: time went backwards ({t_s} < {self._last_t})")
        self._last_t = t_s
        if self._failure is not None:  # its frame is lost: no later frame is whole either
            raise RuntimeError(f"SimLidar failed earlier: {self._failure}") from self._failure
        eps = 1e-9
        if self.next_due_s > t_s + eps:
            return
        try:
            self._step_slices(t_s, eps)
        except Exception as exc:
            self._failure = exc
            raise

    def _step_slices(self, t_s: float, eps: float) -> None:
        c = self.config
        while self._due_s(self._frame, self._slice) <= t_s + eps:
            j0 = self._slice
            j1 = j0 + 1
            while j1 < c.slices_per_frame and self._due_s(self._frame, j1) <= t_s + eps:
                j1 += 1
            if t_s - self._due_s(self._frame, j0) > self._slice_s + eps:
                self.late_slices += j1 - j0
            frame_start = self._due_s(self._frame, 0)
            offset = min(max(t_s - frame_start, 0.0), self._max_offset_s)
            if not self._cast(int(self._bounds[j0]), int(self._bounds[j1]), offset):
                self.invalid_pose_slices += j1 - j0
            self._slice = j1
            if j1 == c.slices_per_frame:
                self._finish_frame()
        self.next_due_s = self._due_s(self._frame, self._slice)

    def _cast(self, i0: int, i1: int, offset_s: float) -> bool:
        """Cast rays [i0, i1) of this frame; False (and no returns) when the body pose is not finite."""
        if i1 <= i0:
            return True
        r_wl, origin = self.lidar_pose_world()
        if not (np.isfinite(r_wl).all() and np.isfinite(origin).all()):
            return False  # a diverged physics state: these rays return nothing
        self._caster.cast(self._d, self._frame, i0, i1, offset_s, r_wl, origin)
        return True

    def _finish_frame(self) -> None:
        pts, offs, gids = self._caster.take()
        k = len(pts)
        pts.flags.writeable = False       # hand over ownership: LidarScan keeps them without copying
        offs.flags.writeable = False
        stamp_s = self._due_s(self._frame, 0)
        if gids is not None:
            self._truth.append((stamp_s, gids))
        scan = LidarScan(stamp_s=stamp_s, points_m=pts, point_time_offsets_s=offs,
                         frame_duration_s=self._period_s, frame_id=self.config.frame_id, nothing_seen=(k == 0))
        if len(self._done) >= self.config.max_queued_frames:
            self._done.popleft()
            self.dropped_frames += 1
        self._done.append(scan)
        self.frames_completed += 1
        self._frame += 1
        self._slice = 0

    def ground_truth_geom_ids(self, stamp_s: float) -> np.ndarray | None:
        """(N,) int32: the MuJoCo geom id each point of the frame stamped stamp_s hit, in the
        frame's point order; None if that frame is not among the last `ground_truth_frames`."""
        for stamp, gids in reversed(self._truth):
            if stamp == stamp_s:
                return gids
        return None

    def pop_frame(self) -> LidarScan | None:
        """The oldest completed frame, or None."""
        return self._done.popleft() if self._done else None


__all__ = ["LidarConfig", "SimLidar", "pattern_directions", "ray_returns"]
