"""The "auto" KISS-ICP settings, the iteration cap from the time budget, and the range gate's count.

`resolve_settings(config, r2)` turns every "auto" field of an IcpConfig into a number derived
from one frame's squared ranges (the first frame the pipeline registers), deterministically
(docs/decisions/odometry-auto-settings.md has the measurements behind every constant):

- max range: the AUTO_RANGE_QUANTILE quantile of the frame's ranges, rounded up to a metre, at
  least AUTO_MIN_MAX_RANGE_M (a small room must not shrink the gate below the indoor robot's 12 m)
  and at most AUTO_MAX_MAX_RANGE_M: the far gate keeps almost every return of the sensor;
- min range: ROBOT_BODY_RANGE_M (the near gate is for the robot's own body, which one frame
  cannot tell from a wall), lowered to the AUTO_NEAR_QUANTILE quantile when it would drop more
  than that share of the frame (a sensor close to a surface);
- voxel: KISS-ICP's rule max_range / 100 where it holds, within [AUTO_MIN_VOXEL_M,
  AUTO_MAX_VOXEL_M]: finer costs much more for no accuracy indoors, and coarser loses sparse
  and narrow-FOV scans (a Livox Avia's 4-5k points: 1.0 m at 100 m lost the track where 0.5 m
  held); then raised, step by step, while the first frame's source points (the frame
  downsampled at 1.5 voxels, as KISS-ICP does) are so many that the iteration budget pays for
  fewer than MIN_AFFORDED_ITERATIONS iterations (dense spinning lidars);
- KISS-ICP's adaptive threshold: initial threshold max_range / 50 (KISS-ICP: 2.0 m at its 100 m
  range, where its voxel rule gives 1.0 m), at least 0.5 m; min motion 0.1 voxel (KISS-ICP: 0.1 m at
  1.0 m), at least 0.05 m. The initial threshold follows the range, not the voxel: indoors the voxel
  is held at 0.3 m (not 12/100), and 2 voxels (0.6 m) there let the first frames take wrong
  correspondences (the gap_offset approach stalled and odom_loop's fused end error grew 6 mm).

`iteration_cap(n_source, budget_ms)`: how many ICP iterations a frame may take so that its
iterations cost at most the budget, at COST_MS_PER_POINT_ITERATION (measured on the 2-core
reference machine, one thread, with a full voxel map): a count from the frame's data.

`count_range_gate(r2, min, max)`: how many finite points the gate drops below the min range
and beyond the max range (a count on the squared ranges the pipeline computes anyway).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from runtime.odometry.icp_config import AUTO, IcpConfig

#: The far gate: this quantile of the first frame's ranges (rounded up to a metre).
AUTO_RANGE_QUANTILE = 0.99
#: The far gate is at least this (m): the indoor robot's rooms measured best at 12 m.
AUTO_MIN_MAX_RANGE_M = 12.0
#: ... and at most KISS-ICP's own default (m): its adaptive threshold scales rotation errors by
#: the max range, so a farther gate widens the kernel and slows the convergence.
AUTO_MAX_MAX_RANGE_M = 100.0
#: The near gate: the robot's own body (m).
ROBOT_BODY_RANGE_M = 0.3
#: The near gate never drops more than this share of the first frame.
AUTO_NEAR_QUANTILE = 0.05
#: KISS-ICP's rule (voxel = max range / 100) holds between these (m): below 0.3 m the cost rises
#: steeply for no accuracy indoors; above 0.5 m sparse and narrow-FOV scans lose the track.
AUTO_MIN_VOXEL_M = 0.3
AUTO_MAX_VOXEL_M = 0.5
#: KISS-ICP's voxel rule: max range / this.
KISS_RANGE_PER_VOXEL = 100.0
#: The voxel steps (m); past AUTO_MAX_VOXEL_M only when the budget needs it (dense frames).
VOXEL_STEPS_M = (0.3, 0.35, 0.4, 0.5, 0.6, 0.75, 1.0)
#: The voxel of a dense frame is raised until the budget pays for this many iterations on it.
MIN_AFFORDED_ITERATIONS = 20
#: A frame is dense when its points per source voxel reach this: a coarser voxel then still
#: samples its surfaces; a sparse frame keeps its voxel (coarser loses its structure).
DENSE_POINTS_PER_SOURCE = 8.0
#: What one ICP iteration costs per source point (ms), a full voxel map, one thread.
COST_MS_PER_POINT_ITERATION = 0.0025
#: The auto cap's bounds: at least this many iterations whatever the budget, at most KISS-ICP's own.
MIN_ITERATIONS = 20
MAX_ITERATIONS = 500
#: The range gate warns when it drops more than this share of the finite points.
GATE_WARN_FRACTION = 0.25


@dataclass(frozen=True)
class RangeGate:
    """How many finite points the range gate saw and dropped (sums over frames with +)."""

    finite: int
    below_min: int
    beyond_max: int
    frames: int = 1
    min_range_m: float | None = None
    max_range_m: float | None = None

    @classmethod
    def empty(cls) -> "RangeGate":
        return cls(0, 0, 0, frames=0)

    def __add__(self, other: "RangeGate") -> "RangeGate":
        return RangeGate(self.finite + other.finite, self.below_min + other.below_min,
                         self.beyond_max + other.beyond_max, self.frames + other.frames,
                         other.min_range_m if other.min_range_m is not None else self.min_range_m,
                         other.max_range_m if other.max_range_m is not None else self.max_range_m)

    @property
    def dropped_fraction(self) -> float:
        return (self.below_min + self.beyond_max) / self.finite if self.finite else 0.0

    def to_dict(self) -> dict:
        f = self.finite
        return {"frames": self.frames, "finite_points": self.finite, "below_min": self.below_min,
                "beyond_max": self.beyond_max,
                "below_min_fraction": self.below_min / f if f else 0.0,
                "beyond_max_fraction": self.beyond_max / f if f else 0.0,
                "dropped_fraction": self.dropped_fraction,
                "min_range_m": self.min_range_m, "max_range_m": self.max_range_m,
                "summary": self.describe(), "warning": self.warning()}

    def describe(self) -> str:
        """One line: what the gate dropped."""
        if not self.finite:
            return "range gate: no points yet"
        f = self.finite
        return (f"range gate {_m(self.min_range_m)}-{_m(self.max_range_m)} m dropped {self.dropped_fraction:.1%} of "
                f"{f} finite points ({self.below_min / f:.1%} below the min range, {self.beyond_max / f:.1%} beyond "
                f"the max range) over {self.frames} frames")

    def warning(self) -> str | None:
        """The one-line warning when the gate dropped more than GATE_WARN_FRACTION, else None."""
        if self.dropped_fraction <= GATE_WARN_FRACTION:
            return None
        return (f"warning: the ICP range gate dropped {self.dropped_fraction:.0%} of the finite points "
                f"(max range {_m(self.max_range_m)} m: {self.beyond_max / self.finite:.0%} beyond it, min range "
                f"{_m(self.min_range_m)} m: {self.below_min / self.finite:.0%} below it); "
                f"odometry.icp.max_range_m / min_range_m: 'auto' derives them from the data")


def gate_lines(gate: dict | None) -> list[str]:
    """The lines a command prints about a RangeGate.to_dict() (none before the first frame)."""
    if not gate or not gate.get("frames"):
        return []
    return [f"ICP {gate['summary']}"] + ([gate["warning"]] if gate.get("warning") else [])


def _m(v: float | None) -> str:
    return "?" if v is None else f"{v:g}"


def count_range_gate(r2: np.ndarray, min_range_m: float, max_range_m: float) -> RangeGate:
    """The gate's counts on one frame's squared ranges (KISS-ICP keeps min < range < max)."""
    finite = np.isfinite(r2)
    n = int(np.count_nonzero(finite))
    below = int(np.count_nonzero(r2 <= min_range_m * min_range_m))  # NaN compares False
    beyond = int(np.count_nonzero(finite & (r2 >= max_range_m * max_range_m)))
    return RangeGate(n, below, beyond, 1, float(min_range_m), float(max_range_m))


def iteration_cap(n_source: int, budget_ms: float) -> int:
    """The iterations budget_ms pays for with n_source source points (module doc)."""
    per_iteration = COST_MS_PER_POINT_ITERATION * max(int(n_source), 1)
    return int(min(MAX_ITERATIONS, max(MIN_ITERATIONS, math.floor(budget_ms / per_iteration))))


def source_points(points_in_gate: np.ndarray, voxel_m: float) -> int:
    """How many source points KISS-ICP registers of this frame at voxel_m (0.5 then 1.5 voxels)."""
    from kiss_icp.voxelization import voxel_down_sample

    if not len(points_in_gate):
        return 0
    return len(voxel_down_sample(voxel_down_sample(points_in_gate, voxel_m * 0.5), voxel_m * 1.5))


def auto_voxel(max_range_m: float, points_in_gate: np.ndarray | None, budget_ms: float) -> tuple[float, str]:
    """The voxel (KISS-ICP's rule within [AUTO_MIN_VOXEL_M, AUTO_MAX_VOXEL_M], raised until the
    iteration budget affords MIN_AFFORDED_ITERATIONS on this frame) and why, in words."""
    kiss = max_range_m / KISS_RANGE_PER_VOXEL
    bounded = min(max(kiss, AUTO_MIN_VOXEL_M), AUTO_MAX_VOXEL_M)
    voxel = max(v for v in VOXEL_STEPS_M if v <= bounded + 1e-9)
    why = f"KISS-ICP's max_range/100 = {kiss:.2f} m"
    if voxel != kiss:
        why += f", within [{AUTO_MIN_VOXEL_M:g}, {AUTO_MAX_VOXEL_M:g}] m: {voxel:g} m"
    if points_in_gate is None:
        return voxel, why
    n = source_points(points_in_gate, voxel)
    density = len(points_in_gate) / max(n, 1)
    if density < DENSE_POINTS_PER_SOURCE:
        return voxel, why + f" ({n} source points, {density:.1f} points each: a sparse frame keeps its voxel)"
    first, n_first = voxel, n
    for v in [step for step in VOXEL_STEPS_M if step > voxel]:
        if _affords(n, budget_ms):
            break
        voxel, n = v, source_points(points_in_gate, v)
    if voxel != first:
        why += (f"; raised to {voxel:g} m: at {first:g} m the frame's {n_first} source points let {budget_ms:g} ms pay "
                f"for fewer than {MIN_AFFORDED_ITERATIONS} iterations")
    return voxel, why + f" ({n} source points)"


def _affords(n_source: int, budget_ms: float) -> bool:
    return budget_ms / (COST_MS_PER_POINT_ITERATION * max(n_source, 1)) >= MIN_AFFORDED_ITERATIONS


def resolve_settings(config: IcpConfig, points: np.ndarray, r2: np.ndarray | None = None
                     ) -> tuple[IcpConfig, dict | None]:
    """config with every auto field but max_iterations derived from one frame (N, 3) (r2: its
    squared ranges, when already computed) (module doc); and what they came from (None when
    nothing was auto)."""
    auto = set(config.auto_fields()) - {"max_iterations"}
    if not auto:
        return config, None
    points = np.asarray(points, dtype=np.float64)
    r2 = np.einsum("ij,ij->i", points, points) if r2 is None else np.asarray(r2, dtype=np.float64)
    valid = np.isfinite(r2) & (r2 > 0.0)
    ranges = np.sqrt(r2[valid])
    if not len(ranges):
        raise ValueError("IcpConfig auto settings: the first frame has no finite point to derive them from")
    update: dict = {}
    notes: dict = {"points": int(len(ranges)),
                   "range_quantiles_m": {str(q): round(float(np.quantile(ranges, q)), 3)
                                         for q in (0.05, 0.5, 0.9, 0.95, AUTO_RANGE_QUANTILE, 1.0)}}
    if "max_range_m" in auto:
        q = float(np.quantile(ranges, AUTO_RANGE_QUANTILE))
        update["max_range_m"] = float(min(max(math.ceil(q), AUTO_MIN_MAX_RANGE_M), AUTO_MAX_MAX_RANGE_M))
    max_range = update.get("max_range_m", config.max_range_m)
    if "min_range_m" in auto:
        near = float(np.quantile(ranges, AUTO_NEAR_QUANTILE))
        update["min_range_m"] = ROBOT_BODY_RANGE_M if near >= ROBOT_BODY_RANGE_M else math.floor(near * 100) / 100
    min_range = update.get("min_range_m", config.min_range_m)
    if "voxel_size_m" in auto:
        in_gate = valid & (r2 > min_range * min_range) & (r2 < max_range * max_range)
        update["voxel_size_m"], notes["voxel_rule"] = auto_voxel(max_range, points[in_gate], config.iteration_budget_ms)
    voxel = update.get("voxel_size_m", config.voxel_size_m)
    if "initial_threshold_m" in auto:
        update["initial_threshold_m"] = max(0.5, max_range / 50.0)
    if "min_motion_m" in auto:
        update["min_motion_m"] = max(0.05, 0.1 * voxel)
    resolved = IcpConfig.model_validate({**config.model_dump(), **update})
    return resolved, {"derived": {k: update[k] for k in sorted(update)}, **notes}


__all__ = [
    "AUTO", "GATE_WARN_FRACTION", "RangeGate", "auto_voxel", "count_range_gate", "gate_lines", "iteration_cap", "resolve_settings",
    "source_points",
]
