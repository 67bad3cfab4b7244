"""KISS-ICP settings of the lidar odometry (config section `odometry.icp`).

The values in runtime/config/default.yaml were chosen by measurement on the simulator's
Mid-360-class frames (20k points, 10 Hz) against ground truth; the measurements are quoted there.
"""
from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, model_validator


class IcpConfig(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)

    enabled: bool = True
    #: KISS-ICP's map voxel (m). Its cost rises steeply as it shrinks (docs/decisions/odometry-icp-voxel.md).
    voxel_size_m: float = Field(0.3, gt=0.01, le=5.0)
    min_range_m: float = Field(0.3, ge=0.0, le=10.0)
    max_range_m: float = Field(12.0, gt=0.5, le=200.0)
    max_points_per_voxel: int = Field(20, ge=1, le=200)
    #: The iteration cap of one registration (KISS-ICP's default is 500: unbounded in practice).
    max_iterations: int = Field(50, ge=1, le=500)
    convergence_criterion: float = Field(1e-4, gt=0.0, le=1.0)
    #: KISS-ICP's TBB threads. 1: the registration is then deterministic (a parallel reduction
    #: sums in a varying order), and the robot's second core is the tick's.
    threads: int = Field(1, ge=1, le=16)
    #: Adaptive correspondence threshold: its start value and the motion below which a frame
    #: does not update it (KISS-ICP's initial_threshold and min_motion_th).
    initial_threshold_m: float = Field(0.5, gt=0.0, le=10.0)
    min_motion_m: float = Field(0.05, ge=0.0, le=5.0)
    #: Motion compensation of the sweep: "kiss" (KISS-ICP's constant-velocity deskew, fed with
    #: the wheel/IMU motion of the frame), "odometry" (ours: every point moved by the wheel/IMU
    #: pose at its own time), or "off".
    deskew: Literal["kiss", "odometry", "off"] = "kiss"

    @model_validator(mode="after")
    def _ranges(self) -> "IcpConfig":
        if self.min_range_m >= self.max_range_m:
            raise ValueError(f"min_range_m ({self.min_range_m}) must be below max_range_m ({self.max_range_m})")
        return self


def make_kiss_config(config: IcpConfig, deskew: bool | None = None):
    """A KISS-ICP `KISSConfig` from ours (every field explicit: KISSConfig's voxel_size is None
    by default). deskew: override KISS-ICP's own deskew (None: on for deskew="kiss")."""
    from kiss_icp.config import KISSConfig

    kc = KISSConfig()
    kc.data.max_range = float(config.max_range_m)
    kc.data.min_range = float(config.min_range_m)
    kc.data.deskew = (config.deskew == "kiss") if deskew is None else bool(deskew)
    kc.mapping.voxel_size = float(config.voxel_size_m)
    kc.mapping.max_points_per_voxel = int(config.max_points_per_voxel)
    kc.registration.max_num_iterations = int(config.max_iterations)
    kc.registration.convergence_criterion = float(config.convergence_criterion)
    kc.registration.max_num_threads = int(config.threads)
    kc.adaptive_threshold.initial_threshold = float(config.initial_threshold_m)
    kc.adaptive_threshold.min_motion_th = float(config.min_motion_m)
    return kc


def new_kiss_icp(config: IcpConfig, deskew: bool | None = None):
    """A fresh KISS-ICP pipeline (kiss_icp.kiss_icp.KissICP) with our settings."""
    from kiss_icp.kiss_icp import KissICP

    return KissICP(make_kiss_config(config, deskew))


__all__ = ["IcpConfig", "make_kiss_config", "new_kiss_icp"]
