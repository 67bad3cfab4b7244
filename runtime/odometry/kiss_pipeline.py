"""KISS-ICP's registration pipeline, step by step, with our settings around it.

`KissPipeline.register_frame` runs the steps of kiss_icp.kiss_icp.KissICP.register_frame (kiss-icp
1.3.0) with the package's own parts (its preprocessor, voxel downsampling, adaptive threshold,
registration and voxel map), in the same order, so that with the same settings it gives the same
poses (test: against KissICP). Its deskew is KISS-ICP's formula vectorised
(runtime.odometry.kiss_deskew: the same points to 1e-9 m, 40-50% of the time). What it adds:

- "auto" settings (runtime.odometry.icp_settings) are resolved from the first frame it is given;
  `settings` holds the numbers, `derivation` what they came from;
- the range gate is counted on every frame (`gate`, `gate_total`: points below the min range and
  beyond the max range among the finite ones), from the squared ranges it computes once;
- the iteration cap: a number given in the config, or (auto) per frame from the iteration
  budget and the frame's source points (icp_settings.iteration_cap): a count from the data,
  never a clock, so lockstep runs stay deterministic;
- the deskew can be switched per frame (`register_frame(..., deskew=False)`) for frames whose
  point times do not span the sweep.
- two hooks around the registration (runtime.odometry.icp): `inspect` sees the deskewed frame
  before it and may lower the frame's iteration cap; `correct` may change the registered pose
  before the adaptive threshold and the map take it.

The attributes KissICP's users touch are kept: `last_pose`, `last_delta` (the constant-velocity
prediction, replaced by the wheel/gyro motion in runtime.odometry.icp), `local_map`.
"""
from __future__ import annotations

import time

import numpy as np

from runtime.odometry.icp_config import AUTO, IcpConfig, make_kiss_config
from runtime.odometry.kiss_deskew import deskew_constant_velocity
from runtime.odometry.icp_settings import RangeGate, count_range_gate, iteration_cap, resolve_settings


#: The parts of register_frame timed in `last_timings_ms` (wall clock, ms; a measurement, never
#: used for behaviour): preprocess (range gate count, deskew, range filter), KISS-ICP's two voxel
#: downsamples, the `inspect` hook (the degeneracy analysis), the registration, and the rest (the
#: `correct` hook, the adaptive threshold and the map update).
TIMED_PARTS = ("preprocess", "downsample", "inspect", "registration", "map_update")


class KissPipeline:
    def __init__(self, config: IcpConfig, deskew: bool | None = None) -> None:
        self.config = config
        #: KISS-ICP's deskew for frames that do not say otherwise.
        self.deskew = (config.deskew == "kiss") if deskew is None else bool(deskew)
        self.last_pose = np.eye(4)
        self.last_delta = np.eye(4)
        #: The settings in use (numbers; max_iterations may stay auto: a cap per frame). None
        #: until the first frame when some are auto.
        self.settings: IcpConfig | None = None
        #: How the auto settings were derived (icp_settings.resolve_settings), None if none was.
        self.derivation: dict | None = None
        self.gate: RangeGate | None = None  # the last frame's
        self.gate_total = RangeGate.empty()
        self.last_cap: int | None = None  # the last frame's iteration cap
        self.cap_range: tuple[int, int] | None = None  # (min, max) over the frames
        self.last_timings_ms: dict[str, float] = {}  # the last frame's, by TIMED_PARTS
        self._registrations: dict[int, object] = {}
        if config.resolved:
            self._build(config, None)

    def _build(self, settings: IcpConfig, derivation: dict | None) -> None:
        from kiss_icp.mapping import get_voxel_hash_map
        from kiss_icp.preprocess import get_preprocessor
        from kiss_icp.threshold import get_threshold_estimator

        self.settings, self.derivation = settings, derivation
        cap = settings.max_iterations if settings.max_iterations != AUTO else 500
        self.kiss_config = make_kiss_config(settings, deskew=True, max_iterations=cap)
        # KISS-ICP's range filter; the deskew before it is kiss_deskew's.
        self._range_filter = get_preprocessor(make_kiss_config(settings, deskew=False, max_iterations=cap))
        self.adaptive_threshold = get_threshold_estimator(self.kiss_config)
        self.local_map = get_voxel_hash_map(self.kiss_config)

    def _registration(self, cap: int):
        reg = self._registrations.get(cap)
        if reg is None:
            from kiss_icp.registration import Registration

            s = self.settings
            reg = self._registrations[cap] = Registration(max_num_iterations=cap,
                                                          convergence_criterion=s.convergence_criterion,
                                                          max_num_threads=s.threads)
        return reg

    def register_frame(self, frame, timestamps, deskew: bool | None = None, correct=None, inspect=None):
        """KISS-ICP's register_frame (module doc); returns (the deskewed frame within the range
        gate, the source points registered), as KissICP does.

        inspect: None, or inspect(points) -> int | None, called with the deskewed frame before the
        registration: a number lowers the frame's iteration cap to it (a count, from the data).
        correct: None, or correct(points, initial_guess, pose) -> pose, called with the deskewed
        frame, the initial guess and the registered pose (4x4, lidar odom frame) before the
        adaptive threshold and the map take the pose: what it returns is the frame's pose."""
        from kiss_icp.voxelization import voxel_down_sample

        marks = [time.perf_counter()]
        points = np.ascontiguousarray(frame, dtype=np.float64)
        r2 = np.einsum("ij,ij->i", points, points)
        if self.settings is None:
            self._build(*resolve_settings(self.config, points, r2))
        s = self.settings
        self.gate = count_range_gate(r2, s.min_range_m, s.max_range_m)
        self.gate_total = self.gate_total + self.gate
        use_deskew = self.deskew if deskew is None else bool(deskew)
        if use_deskew:
            points = deskew_constant_velocity(points, timestamps, self.last_delta)
        points = self._range_filter.preprocess(points, np.zeros(0), self.last_delta)
        marks.append(time.perf_counter())
        frame_downsample = voxel_down_sample(points, s.voxel_size_m * 0.5)
        source = voxel_down_sample(frame_downsample, s.voxel_size_m * 1.5)
        cap = s.max_iterations if s.max_iterations != AUTO else iteration_cap(len(source), s.iteration_budget_ms)
        marks.append(time.perf_counter())
        limit = inspect(points) if inspect is not None else None
        marks.append(time.perf_counter())
        if limit is not None:
            cap = max(1, min(cap, int(limit)))
        self.last_cap = cap
        self.cap_range = (cap, cap) if self.cap_range is None else (min(self.cap_range[0], cap),
                                                                    max(self.cap_range[1], cap))
        sigma = self.adaptive_threshold.get_threshold()
        initial_guess = self.last_pose @ self.last_delta
        new_pose = self._registration(cap).align_points_to_map(
            points=source, voxel_map=self.local_map, initial_guess=initial_guess,
            max_correspondance_distance=3 * sigma, kernel=sigma)
        marks.append(time.perf_counter())
        if correct is not None:
            new_pose = correct(points, initial_guess, new_pose)
        self.adaptive_threshold.update_model_deviation(np.linalg.inv(initial_guess) @ new_pose)
        self.local_map.update(frame_downsample, new_pose)
        self.last_delta = np.linalg.inv(self.last_pose) @ new_pose
        self.last_pose = new_pose
        marks.append(time.perf_counter())
        self.last_timings_ms = {name: (b - a) * 1e3 for name, a, b in zip(TIMED_PARTS, marks, marks[1:])}
        return points, source


__all__ = ["KissPipeline", "TIMED_PARTS"]
