"""Lidar odometry: one KISS-ICP pipeline on deskewed frames, and what the fusion needs of each.

`IcpEngine.process(job)` runs where the ICP worker runs (runtime.odometry.worker: a process on
the robot, because KISS-ICP's registration holds Python's GIL for its whole duration and would
stall the tick if it ran in a thread). It runs KISS-ICP's own pipeline steps
(runtime.odometry.kiss_pipeline: auto settings from the first frame, the range gate counted, the
iteration cap per frame from the time budget); what we add around it:

- The initial guess. Before each frame, KISS-ICP's `last_delta` (its constant-velocity
  prediction, used for the initial guess and for its deskew) is replaced by the motion the wheels
  and the gyro measured since the previous registered frame (from `IcpJob.dead_reckoning_end`).
- Deskew. "kiss": KISS-ICP's deskew (constant velocity over the sweep, from `last_delta`, i.e. from
  the wheels and gyro when a prior is given); "odometry": ours, every point moved by the wheel/gyro
  pose interpolated at its own time (`IcpJob.motion`), KISS-ICP's deskew off; "off". KISS-ICP
  deskews to the END of the sweep (it normalises the given times over [min, max] and moves every
  point to the time 1.0; measured: against ground truth, the pose matches the frame's end, not its
  middle), so every pose here is stamped with the time of the frame's last point.
- Degeneracy: `planar_constraint` on the deskewed frame (runtime.odometry.degeneracy), before the
  registration: with a prior, a direction the scan does not constrain keeps the prior's
  translation (solution remapping, applied to the registered pose before the map takes it), so
  ICP's slide along featureless walls reaches neither the map nor the next frame's guess, and the
  answer does not depend on where the iteration cap stopped the slide. Such a frame is registered
  with the lower cap `IcpConfig.degenerate_max_iterations`: past the constrained directions'
  convergence its iterations only slide.
- The planar increment since the previous frame in the base frame (the lidar's mount applied).

Frames must span their sweep in time for a deskew: a frame whose point times span less than half
its duration is registered without one (counted in the result), never with fake times.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import numpy as np

from runtime.odometry.degeneracy import DegeneracyConfig, PlanarConstraint, planar_constraint
from runtime.odometry.icp_config import IcpConfig, new_kiss_icp
from runtime.odometry.icp_settings import RangeGate
from runtime.odometry.se2 import se2_between, se2_matrix, se2_of_matrix


@dataclass(frozen=True)
class IcpJob:
    """One lidar frame for the ICP worker (picklable: it crosses a process boundary)."""

    seq: int
    stamp_s: float  # start of the frame
    end_s: float  # time of the frame's last point: the time the result's pose refers to
    points: np.ndarray  # (N, 3) float32, lidar frame, each at its own time
    offsets_s: np.ndarray  # (N,) float32, seconds since stamp_s
    duration_s: float
    #: The wheel + gyro (dead-reckoning) pose (x, y, yaw) at end_s; the engine's prior is the
    #: motion between the frame it registered last and this one. None: KISS-ICP's own prediction.
    dead_reckoning_end: np.ndarray | None = None
    #: Dead-reckoning poses (K, 4): t, x, y, yaw covering the sweep, for deskew="odometry".
    motion: np.ndarray | None = None
    #: Lockstep: the simulated time the result is delivered at (end_s + the fixed latency).
    ready_at_s: float = 0.0


@dataclass(frozen=True)
class IcpResult:
    seq: int
    stamp_s: float
    end_s: float
    ready_at_s: float
    #: The base's planar pose in ICP's own odom frame (the base at the first frame = origin).
    pose_base: np.ndarray
    #: (dx, dy, dyaw) since the previous result, in the base frame at prev_end_s (None: first).
    delta_base: np.ndarray | None
    prev_end_s: float | None
    constraint: PlanarConstraint | None
    points_in: int
    points_registered: int
    deskewed: bool
    compute_s: float  # wall-clock seconds in the worker (a measurement, never used for behaviour)
    error: str | None = None
    notes: tuple[str, ...] = field(default_factory=tuple)
    #: What the range gate dropped of this frame (None: not registered).
    gate: RangeGate | None = None
    #: The iteration cap this frame was registered with.
    iteration_cap: int | None = None
    #: The first result only: the settings in use (auto ones resolved) and their derivation.
    settings: dict | None = None
    #: Wall-clock ms by part (a measurement, never used for behaviour): "prepare" (the frame's
    #: conversion, the prior, a wheel/gyro deskew), then KissPipeline's TIMED_PARTS ("inspect":
    #: the degeneracy analysis).
    parts_ms: dict = field(default_factory=dict)


def _lidar_delta(prior_base: np.ndarray, mount: np.ndarray, mount_inv: np.ndarray) -> np.ndarray:
    """The base's planar motion as the lidar's 4x4 motion (what KISS-ICP's last_delta holds)."""
    return mount_inv @ se2_matrix(prior_base) @ mount


def deskew_with_motion(points: np.ndarray, times_s: np.ndarray, end_s: float, motion: np.ndarray,
                       mount: np.ndarray) -> np.ndarray:
    """Move every point (lidar frame, at its own time) to the lidar frame at end_s, with the
    dead-reckoning poses `motion` (K, 4: t, x, y, yaw; interpolated linearly, held at the ends)."""
    t, x, y, yaw = motion[:, 0], motion[:, 1], motion[:, 2], np.unwrap(motion[:, 3])
    px, py, pyaw = np.interp(times_s, t, x), np.interp(times_s, t, y), np.interp(times_s, t, yaw)
    ex, ey, eyaw = np.interp(end_s, t, x), np.interp(end_s, t, y), np.interp(end_s, t, yaw)
    # Relative planar pose of the base at each point's time, seen from the base at end_s.
    c, s = math.cos(eyaw), math.sin(eyaw)
    dx, dy = px - ex, py - ey
    rx, ry = c * dx + s * dy, -s * dx + c * dy
    ryaw = pyaw - eyaw
    r, tm = mount[:3, :3], mount[:3, 3]
    pb = points @ r.T + tm  # base frame at the point's own time
    cr, sr = np.cos(ryaw), np.sin(ryaw)
    out = np.empty_like(pb)
    out[:, 0] = cr * pb[:, 0] - sr * pb[:, 1] + rx
    out[:, 1] = sr * pb[:, 0] + cr * pb[:, 1] + ry
    out[:, 2] = pb[:, 2]
    return (out - tm) @ r  # back to the lidar frame (at end_s)


class IcpEngine:
    """One KISS-ICP pipeline and the bookkeeping around it; runs wherever the worker runs."""

    def __init__(self, icp: IcpConfig, degeneracy: DegeneracyConfig, mount: np.ndarray,
                 use_prior: bool = True) -> None:
        self.config = icp
        self.degeneracy = degeneracy
        self.mount = np.asarray(mount, dtype=np.float64)
        self.mount_inv = np.linalg.inv(self.mount)
        self.use_prior = use_prior
        #: KISS-ICP's steps (runtime.odometry.kiss_pipeline): auto settings resolved on the
        #: first frame, the range gate counted on every frame.
        self.kiss = new_kiss_icp(icp, deskew=icp.deskew == "kiss")
        self._settings_sent = False
        self._prev_pose: np.ndarray | None = None
        self._prev_end: float | None = None
        self._prev_dead_reckoning: np.ndarray | None = None

    def process(self, job: IcpJob) -> IcpResult:
        t0 = time.perf_counter()

        notes: list[str] = []
        pts = np.asarray(job.points, dtype=np.float64)
        offs = np.asarray(job.offsets_s, dtype=np.float64)
        span = float(offs.max() - offs.min()) if len(offs) else 0.0
        deskew = self.config.deskew != "off"
        if deskew and span < 0.5 * job.duration_s:
            deskew = False
            notes.append(f"point times span {span * 1e3:.0f} ms of a {job.duration_s * 1e3:.0f} ms frame: no deskew")
        prior = None
        if job.dead_reckoning_end is not None and self._prev_dead_reckoning is not None:
            prior = se2_between(self._prev_dead_reckoning, np.asarray(job.dead_reckoning_end, dtype=np.float64))
        if self._prev_pose is not None and prior is not None and self.use_prior:
            self.kiss.last_delta = _lidar_delta(prior, self.mount, self.mount_inv)
        mode = self.config.deskew
        if (mode == "kiss" and deskew and self._prev_end is not None and prior is not None
                and job.end_s - self._prev_end > 1.5 * job.duration_s):
            # KISS-ICP's deskew spreads last_delta over one sweep; after a gap (frames lost or
            # refused) the prior spans several, so this frame is deskewed with the wheels instead.
            mode = "odometry"
            notes.append(f"{(job.end_s - self._prev_end) * 1e3:.0f} ms since the previous frame: wheel/gyro deskew")
        if mode == "odometry" and deskew:
            if job.motion is not None and len(job.motion) >= 2:
                pts = deskew_with_motion(pts, job.stamp_s + offs, job.end_s, np.asarray(job.motion), self.mount)
            else:
                deskew = False
                notes.append("no wheel/gyro motion over the sweep: no deskew")
        kiss_deskews = deskew and mode == "kiss"
        analysis: list = []
        prepared = time.perf_counter()
        frame, source = self.kiss.register_frame(pts, offs, deskew=kiss_deskews,
                                                 inspect=lambda f: self._analyse(f, analysis),
                                                 correct=lambda f, g, p: self._remap(g, p, analysis))
        pose_base = se2_of_matrix(self.mount @ self.kiss.last_pose @ self.mount_inv)
        delta = None if self._prev_pose is None else se2_between(self._prev_pose, pose_base)
        prev_end = self._prev_end
        self._prev_pose, self._prev_end = pose_base, job.end_s
        self._prev_dead_reckoning = None if job.dead_reckoning_end is None else np.asarray(job.dead_reckoning_end)
        constraint = analysis[0] if analysis else None
        return IcpResult(
            seq=job.seq, stamp_s=job.stamp_s, end_s=job.end_s, ready_at_s=job.ready_at_s,
            pose_base=pose_base, delta_base=delta, prev_end_s=prev_end, constraint=constraint,
            points_in=len(pts), points_registered=len(source), deskewed=deskew,
            compute_s=time.perf_counter() - t0, notes=tuple(notes), gate=self.kiss.gate,
            iteration_cap=self.kiss.last_cap, settings=self._settings_once(),
            parts_ms={"prepare": (prepared - t0) * 1e3, **self.kiss.last_timings_ms},
        )

    def _analyse(self, frame: np.ndarray, out: list) -> int | None:
        """The degeneracy analysis of the deskewed frame (into out), before the registration; the
        iteration cap of a frame whose translation the remapping will put back along a direction
        (IcpConfig.degenerate_max_iterations: the iterations past it would only slide there)."""
        from kiss_icp.voxelization import voxel_down_sample

        if not len(frame):
            return None
        thin = voxel_down_sample(frame, self.degeneracy.voxel_m)
        con = planar_constraint(thin @ self.mount[:3, :3].T + self.mount[:3, 3], self.degeneracy)
        out.append(con)
        if con.degenerate_xy and self.use_prior:
            return self.config.degenerate_max_iterations
        return None

    def _remap(self, guess: np.ndarray, pose: np.ndarray, analysis: list) -> np.ndarray:
        """The registered pose with its translation along a direction the scan does not
        constrain put back to the prior's (solution remapping, Zhang, Kaess and Singh 2016):
        ICP's answer there is a slide along featureless walls, and the map must not take it."""
        weak = analysis[0].weak_direction_xy if analysis else None
        if weak is None or not self.use_prior:
            return pose
        step = self.mount @ np.linalg.inv(guess) @ pose @ self.mount_inv   # base frame, at the guess (a new array)
        step[:2, 3] -= weak * float(weak @ step[:2, 3])
        return guess @ self.mount_inv @ step @ self.mount

    def _settings_once(self) -> dict | None:
        """The settings in use and how the auto ones were derived: on the first result only."""
        if self._settings_sent or self.kiss.settings is None:
            return None
        self._settings_sent = True
        return {"icp": self.kiss.settings.model_dump(), "derivation": self.kiss.derivation}


def warm_up(engine_factory, frames: int = 3) -> float:
    """Register a few synthetic frames (a 4 m square room, the robot creeping forward) with a
    throwaway engine from engine_factory, so that the first real frame does not pay for loading
    the compiled kernels (about 40 ms, 5x a steady frame). The engines that register real frames
    are built apart: nothing of this one is kept. Returns the seconds it took."""
    t0 = time.perf_counter()
    engine = engine_factory()
    rng = np.random.default_rng(0)
    n = 4000
    offsets = np.linspace(0.0, 0.099, n, dtype=np.float32)
    for k in range(frames):
        az = rng.uniform(-math.pi, math.pi, n)
        r = 4.0 / np.maximum(np.abs(np.cos(az)), np.abs(np.sin(az)))
        z = rng.uniform(-0.2, 1.0, n)
        pts = np.column_stack([r * np.cos(az) - 0.02 * k, r * np.sin(az), z]).astype(np.float32)
        engine.process(IcpJob(seq=k, stamp_s=0.1 * k, end_s=0.1 * k + 0.099, points=pts, offsets_s=offsets,
                              duration_s=0.1, dead_reckoning_end=np.array([0.02 * k, 0.0, 0.0])))
    return time.perf_counter() - t0


__all__ = ["IcpEngine", "IcpJob", "IcpResult", "deskew_with_motion", "warm_up"]
