"""The partition's settings (controller config `vpp.partition`)."""
from __future__ import annotations

from pydantic import BaseModel, ConfigDict, Field


class PartitionConfig(BaseModel):
    """Phase III parameters. Defaults are for a LIMO-sized robot indoors (objects 0.2-2 m, at
    0.3-6 m, a 16-64 ring lidar); the real-data test (a car at 40 m) sets its own."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    #: Points lower than this in the base frame (metres above the floor) are ground, removed
    #: before the partition. The same figure as ObstaclePointsConfig.ground_clearance_m.
    ground_max_z_m: float = Field(default=0.04, ge=-5.0, le=5.0)
    #: Cluster radius: two points of one object closer than this are connected. About twice the
    #: lidar's point spacing on an object at working range (Mid-360 at 3 m: ~5 cm).
    eps_cluster_m: float = Field(default=0.10, gt=0.0, le=5.0)
    #: A component with fewer points is an outlier (speckle through the mask), not an object.
    n_min: int = Field(default=5, ge=1, le=10000)
    #: Beyond the paper: keep a component only if its mean depth is within this of the object's
    #: largest component (None: the paper's rule, size only). See the module docstring.
    max_depth_gap_m: float | None = Field(default=0.5, gt=0.0, le=100.0)
    #: Cluster completion on/off, and the half-size (pixels) of the square by which a mask is
    #: dilated to bound where completion may add points.
    completion: bool = True
    completion_dilate_px: int = Field(default=8, ge=0, le=200)
    #: Odom-frame label memory: voxel edge, and how long a label stays valid unseen.
    memory_voxel_m: float = Field(default=0.10, gt=0.005, le=5.0)
    memory_max_age_s: float = Field(default=5.0, gt=0.0, le=600.0)
    #: Initial slot count of the memory's hash table (a power of two; it grows when half full).
    memory_initial_slots: int = Field(default=1 << 15, ge=64, le=1 << 26)


__all__ = ["PartitionConfig"]
