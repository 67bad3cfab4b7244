"""KISS-ICP settings of the lidar odometry (config section `odometry.icp`).

The range gate, the voxel, KISS-ICP's adaptive-threshold start values and the iteration cap are
"auto" by default: derived from the first frame's own ranges (runtime.odometry.icp_settings,
docs/decisions/odometry-auto-settings.md), so that an outdoor sensor that sees 100 m is not
gated at the indoor robot's 12 m. A number given for any of them is used as it is.
"""
from __future__ import annotations

import math
from typing import Annotated, Literal, Union

from pydantic import BaseModel, ConfigDict, Field, PlainValidator, model_validator

#: The value of a setting derived from the data (runtime.odometry.icp_settings.resolve_settings).
AUTO = "auto"


def _auto_or(lo: float, hi: float, lo_open: bool = False, integer: bool = False):
    """A field type: "auto" or a number in [lo, hi] ((lo, hi] when lo_open), one error message."""
    def check(value):
        if value == AUTO:
            return AUTO
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ValueError("Input should be a number or 'auto'")
        if integer and value != int(value):
            raise ValueError("Input should be a whole number or 'auto'")
        if not math.isfinite(value):
            raise ValueError("Input should be a finite number")
        if value < lo or (lo_open and value == lo):
            raise ValueError(f"Input should be greater than {'' if lo_open else 'or equal to '}{lo:g}")
        if value > hi:
            raise ValueError(f"Input should be less than or equal to {hi:g}")
        return int(value) if integer else float(value)

    return Annotated[Union[int, float, str], PlainValidator(check)]

#: The fields that may be "auto" (the rest are always numbers).
AUTO_FIELDS = ("voxel_size_m", "min_range_m", "max_range_m", "max_iterations", "initial_threshold_m", "min_motion_m")


class IcpConfig(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)

    enabled: bool = True
    #: KISS-ICP's map voxel (m). Its cost rises steeply as it shrinks (docs/decisions/odometry-icp-voxel.md).
    voxel_size_m: _auto_or(0.01, 5.0, lo_open=True) = AUTO
    min_range_m: _auto_or(0.0, 10.0) = AUTO
    max_range_m: _auto_or(0.5, 500.0, lo_open=True) = AUTO
    max_points_per_voxel: int = Field(20, ge=1, le=200)
    #: The iteration cap of one registration. auto: per frame, as many iterations as
    #: `iteration_budget_ms` pays for at the measured cost per source point (icp_settings).
    max_iterations: _auto_or(1, 500, integer=True) = AUTO
    #: What the iterations of one frame may cost at most (ms, on the 2-core reference machine):
    #: the auto iteration cap's budget. A count follows from it, never a clock.
    iteration_budget_ms: float = Field(80.0, gt=1.0, le=2000.0)
    #: KISS-ICP stops iterating when an iteration's step (the norm of its 6-vector: m and rad) is
    #: below this. KISS-ICP's 1e-4 is made for cars (about 1 m per frame); indoors, 1e-3 (a 1 mm,
    #: 1 mrad step) halves the iterations (20k-ray frames: 10 -> 4 median, 20 -> 12 p99) with the
    #: simulator's and the real sequences' accuracy kept (docs/decisions/odometry-icp-speed.md).
    convergence_criterion: float = Field(1e-3, gt=0.0, le=1.0)
    #: The iteration cap of a frame whose translation the scan leaves unconstrained along a
    #: direction (the degeneracy analysis runs before the registration): with a prior the pose
    #: keeps the prior's translation there (runtime.odometry.icp), and the iterations past the
    #: constrained directions' convergence only slide along it.
    degenerate_max_iterations: int = Field(10, ge=1, le=500)
    #: KISS-ICP's TBB threads. 1: the registration is then deterministic (a parallel reduction
    #: sums in a varying order), and the robot's second core is the tick's.
    threads: int = Field(1, ge=1, le=16)
    #: Adaptive correspondence threshold: its start value and the motion below which a frame
    #: does not update it (KISS-ICP's initial_threshold and min_motion_th).
    initial_threshold_m: _auto_or(0.0, 10.0, lo_open=True) = AUTO
    min_motion_m: _auto_or(0.0, 5.0) = AUTO
    #: Motion compensation of the sweep: "kiss" (KISS-ICP's constant-velocity deskew, fed with
    #: the wheel/IMU motion of the frame), "odometry" (ours: every point moved by the wheel/IMU
    #: pose at its own time), or "off".
    deskew: Literal["kiss", "odometry", "off"] = "kiss"

    @model_validator(mode="after")
    def _ranges(self) -> "IcpConfig":
        lo, hi = self.min_range_m, self.max_range_m
        if lo != AUTO and hi != AUTO and lo >= hi:
            raise ValueError(f"min_range_m ({lo}) must be below max_range_m ({hi})")
        return self

    def auto_fields(self) -> tuple[str, ...]:
        """The fields still "auto" (resolved from the first frame)."""
        return tuple(name for name in AUTO_FIELDS if getattr(self, name) == AUTO)

    @property
    def resolved(self) -> bool:
        """Every setting KISS-ICP is built from is a number (max_iterations may stay auto: per frame)."""
        return all(name == "max_iterations" for name in self.auto_fields())


def make_kiss_config(config: IcpConfig, deskew: bool | None = None, max_iterations: int | None = None):
    """A KISS-ICP `KISSConfig` from ours (every field explicit: KISSConfig's voxel_size is None
    by default). deskew: override KISS-ICP's own deskew (None: on for deskew="kiss").
    max_iterations: the cap to build it with (None: config's; required when that is auto)."""
    from kiss_icp.config import KISSConfig

    if not config.resolved:
        raise ValueError(f"IcpConfig: {', '.join(config.auto_fields())} still auto "
                         f"(runtime.odometry.icp_settings.resolve_settings derives them from a frame)")
    cap = config.max_iterations if max_iterations is None else max_iterations
    if cap == AUTO:
        raise ValueError("IcpConfig.max_iterations: auto (a cap per frame): give max_iterations")
    kc = KISSConfig()
    kc.data.max_range = float(config.max_range_m)
    kc.data.min_range = float(config.min_range_m)
    kc.data.deskew = (config.deskew == "kiss") if deskew is None else bool(deskew)
    kc.mapping.voxel_size = float(config.voxel_size_m)
    kc.mapping.max_points_per_voxel = int(config.max_points_per_voxel)
    kc.registration.max_num_iterations = int(cap)
    kc.registration.convergence_criterion = float(config.convergence_criterion)
    kc.registration.max_num_threads = int(config.threads)
    kc.adaptive_threshold.initial_threshold = float(config.initial_threshold_m)
    kc.adaptive_threshold.min_motion_th = float(config.min_motion_m)
    return kc


def new_kiss_icp(config: IcpConfig, deskew: bool | None = None):
    """A fresh KISS-ICP pipeline with our settings (runtime.odometry.kiss_pipeline.KissPipeline:
    KISS-ICP's own steps; "auto" settings are resolved from the first frame it registers)."""
    from runtime.odometry.kiss_pipeline import KissPipeline

    return KissPipeline(config, deskew=deskew)


__all__ = ["AUTO", "AUTO_FIELDS", "IcpConfig", "make_kiss_config", "new_kiss_icp"]
