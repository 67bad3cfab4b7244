"""Deformable objects (a curtain, a strip door): the region where it hangs, in the odom frame.

Why: a rigid movable object (a box) is followed by the tracker (runtime/vpp/tracking/): it moves
as one body when pushed, and a template registered to each scan finds it again. A curtain does neither.
Its slats swing away from the robot and drape over it while the object itself stays where it
hangs; no rigid template matches it, its mask (captured from a distance) no longer covers the
slats that swung, and the slats over the robot's front are below the camera's view (the camera
sits 13 cm ahead of the base at 15 cm height). The partition then labels those points FIXED
(in view outside the stale mask) or takes them from the label memory (FIXED where they were seen
swinging), and the safety supervisor stops the robot inside the curtain. The DCT paper's curtain
run (section V-D) "maintains this memory throughout the run": this module is that memory for an
object that deforms.

Model: per object the backend called deformable (and movable, below the never-touch cost), an
oriented box in the odom floor plane fitted to the points its mask labelled in view (only
those within `band_m` of the line through them, at least `min_inlier_share` of them, else no
region: a few points of a crate the mask took in do not move it): centre,
the object's width axis (the principal axis of its points), the extent along it (1st-99th
percentile, trimmed by `end_margin_m` at each end: a doorway's jambs next to the curtain stay
P_fix), and its thickness across, widened by `reach_m` each side: how far its parts may swing
away from where they hang while the robot passes. A non-ground point inside a region is P_mov
of that object at its cost, in view or not, unless another object's mask or track labelled it,
when it is within `rest_swing_m` of the object's plane (parts swinging on their own), or within
`near_robot_m` ahead of or behind the robot's footprint and `near_robot_side_m` beside it and
not rigid (the motion test below), or on the robot (its footprint grown by `on_robot_m`): the
parts it lifts and pushes aside lie on it and against its front;
something standing behind the curtain away from the robot stays P_fix.

The fit is refreshed from the mask's points while the robot is at least `clear_m` outside every
region (the curtain hangs still then); while the robot is in or near one, every region is frozen
and none is made: the slats it pushes would drag the fit along, and the slats hanging in front of
the camera get masks that gate the lidar points seen past them (a far wall fitted as a
curtain). A region not refreshed for `max_age_s` while the robot is clear of it is dropped, and
so is the region of an object demoted (correcting mode: the robot got stuck in it, DCT eq. 14),
believed heavy or fragile, or no longer called deformable and touchable by a newer answer.

Known limits, stated in the README: the robot does not see behind a curtain, and neither does
this model. A rigid obstacle within the rest zone is taken for the curtain wherever the robot
is; one nearer the plane than `rigid_min_depth_m` that the robot comes within `near_robot_m`
of, one the motion test has not seen stand still while the robot moved, or one touching the
robot (within `on_robot_m`), likewise. The default reach (0.70 m) is how far a slat of a 1 m
curtain draped over the LIMO's top lies from where it hangs (DeformableConfig.reach_m).

Cost: a few numpy operations per region and scan on the points (no Python loop over points).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from runtime.vpp.partition.labels import FIXED, IGNORED, MOVABLE, PointPartition


class DeformableConfig(BaseModel):
    """Settings of the deformable-object regions (controller config `vpp.deformable`)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    #: Off: a deformable object is treated as any movable one (its mask, the tracker).
    enabled: bool = True
    #: How far (m) the object's parts may swing from where it hangs, each side of its plane. A
    #: slat of length L hanging from height H, lifted onto the robot's top at height h, lies
    #: sqrt(L^2 - (H - h)^2) out: 0.64 m for a 1 m curtain on the LIMO (lidar top at 0.3 m)
    #: (docs/decisions/vpp-deformable-regions.md).
    reach_m: float = Field(0.70, ge=0.0, le=3.0)
    #: Within this distance (m) of its plane (beyond its measured thickness) a point in the region
    #: is the object wherever the robot is: parts swinging on their own after a touch.
    rest_swing_m: float = Field(0.15, ge=0.0, le=3.0)
    #: Farther out (up to reach_m), a point is the object only within this distance (m) of the
    #: robot's footprint: the parts the robot lifts or pushes aside lie on it or against it
    #: (docs/decisions/vpp-deformable-regions.md). Something standing behind
    #: the curtain, away from the robot, stays P_fix (and blocks the way).
    near_robot_m: float = Field(0.15, ge=0.0, le=5.0)
    #: ... ahead of it or behind it; beside it only this far (m): the slats its front pushes span
    #: a little wider than the robot, and a rigid
    #: obstacle the robot passes beside must stay P_fix.
    near_robot_side_m: float = Field(0.10, ge=0.0, le=5.0)
    #: A point over the robot's footprint grown by this (m) lies on the robot (slats pressed
    #: against it). Known cost: a rigid thing touching the robot is taken too; 0 is worse
    #: (docs/decisions/vpp-deformable-regions.md).
    on_robot_m: float = Field(0.03, ge=0.0, le=1.0)
    #: The motion test of the points ahead of and behind the robot: a cell (this size, m, in the
    #: region's frame) occupied in every scan (gaps up to rigid_gap_s) while the robot moved
    #: rigid_motion_m is something standing still while the robot moves: rigid, P_fix. The parts
    #: of a curtain the robot pushes move with it and leave their cells.
    rigid_cell_m: float = Field(0.04, gt=0.005, le=1.0)
    rigid_motion_m: float = Field(0.08, gt=0.0, le=2.0)
    rigid_gap_s: float = Field(0.25, gt=0.0, le=5.0)
    rigid_hold_s: float = Field(1.0, gt=0.0, le=30.0)
    #: ... applied only this far (m) from the object's plane and beyond: nearer, the parts of a
    #: curtain beside the robot hang from fixed hinges and move little as it passes, and would be
    #: found "rigid" (docs/decisions/vpp-deformable-regions.md).
    rigid_min_depth_m: float = Field(0.45, ge=0.0, le=3.0)
    #: The region stops this far (m) short of the object's ends (what holds it stays P_fix).
    end_margin_m: float = Field(0.03, ge=0.0, le=1.0)
    #: In-view mask points a fit needs.
    min_points: int = Field(20, ge=3, le=100000)
    #: The fit keeps the points within this distance (m) of the line through the object: a curtain
    #: hangs in a plane (its slats a few cm thick, swinging a little); the others are not it.
    band_m: float = Field(0.10, gt=0.0, le=2.0)
    #: ... and at least this share of them must be: else the object is no curtain (no region).
    min_inlier_share: float = Field(0.7, ge=0.0, le=1.0)
    #: A region is refit only while the robot's centre is at least this far (m) outside it.
    clear_m: float = Field(0.30, ge=0.0, le=5.0)
    #: A region not refit for this long (s), the robot clear of it, is dropped.
    max_age_s: float = Field(30.0, gt=0.0, le=3600.0)


@dataclass(frozen=True)
class RobotBox:
    """The robot's footprint: half length and half width (m)."""

    half_length_m: float = 0.161
    half_width_m: float = 0.11


@dataclass(frozen=True)
class DeformableRegion:
    """An oriented box in the odom floor plane: centre (x, y), unit axis along the object's
    width, half extents along it and across it (reach included), the object's cost, fit time."""

    object_id: int
    centre: tuple[float, float]
    axis: tuple[float, float]
    half_length_m: float
    half_depth_m: float  # reach included
    rest_depth_m: float  # the measured half thickness plus the rest swing
    cost: float
    fitted_s: float
    points: int  # mask points the fit used

    def local(self, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(along, across) coordinates of (N, 2) odom points in the region's frame."""
        dx, dy = xy[:, 0] - self.centre[0], xy[:, 1] - self.centre[1]
        ax, ay = self.axis
        return dx * ax + dy * ay, -dx * ay + dy * ax

    def contains(self, xy: np.ndarray, grow_m: float = 0.0) -> np.ndarray:
        s, t = self.local(xy)
        return (np.abs(s) <= self.half_length_m + grow_m) & (np.abs(t) <= self.half_depth_m + grow_m)

    def zones(self, xyz: np.ndarray, pose: tuple[float, float, float], robot: "RobotBox",
              config: "DeformableConfig") -> tuple[np.ndarray, ...]:
        """(N,) bool masks of the points (module docstring): in the region; within its rest
        depth; on the robot (within its footprint, grown by on_robot_m: nothing rigid can be
        there, the robot would be in it); ahead of or behind the robot (within near_robot_m of
        its front or back, near_robot_side_m beside it); and each point's distance from the
        object's plane."""
        s, t = self.local(xyz)
        inside = (np.abs(s) <= self.half_length_m) & (np.abs(t) <= self.half_depth_m)
        c, si = math.cos(pose[2]), math.sin(pose[2])
        dx, dy = xyz[:, 0] - pose[0], xyz[:, 1] - pose[1]
        ax, ay = np.abs(c * dx + si * dy), np.abs(-si * dx + c * dy)
        on_robot = (ax <= robot.half_length_m + config.on_robot_m) & (ay <= robot.half_width_m + config.on_robot_m)
        ahead = (ax <= robot.half_length_m + config.near_robot_m) & (ay <= robot.half_width_m + config.near_robot_side_m)
        return inside, np.abs(t) <= self.rest_depth_m, on_robot, ahead & ~on_robot, np.abs(t)

    def describe(self) -> dict:
        return {"object_id": self.object_id, "centre_m": [round(self.centre[0], 3), round(self.centre[1], 3)],
                "axis_deg": round(math.degrees(math.atan2(self.axis[1], self.axis[0])), 1),
                "length_m": round(2 * self.half_length_m, 3), "depth_m": round(2 * self.half_depth_m, 3),
                "rest_depth_m": round(2 * self.rest_depth_m, 3),
                "cost": self.cost, "fitted_s": round(self.fitted_s, 3), "points": self.points}


def fit_region(object_id: int, xy: np.ndarray, cost: float, now_s: float, config: DeformableConfig
               ) -> DeformableRegion | None:
    """The region of an object from its (N, 2) odom mask points (None: too few, or too short
    once its ends are trimmed)."""
    if len(xy) < config.min_points:
        return None
    # The line through the points, robust to a few that are not the curtain (a crate behind it
    # that the mask's completion or its image region took in): principal axis about the median,
    # the points within band_m of that line kept, the axis fitted again on them.
    n_in = len(xy)
    c = np.median(xy, axis=0)
    for _ in range(2):
        d = xy - c
        w, v = np.linalg.eigh(d.T @ d)  # ascending eigenvalues: v[:, 1] is the width axis
        axis = v[:, 1]
        t = d[:, 0] * -axis[1] + d[:, 1] * axis[0]
        keep = np.abs(t - np.median(t)) <= config.band_m
        if np.count_nonzero(keep) < max(config.min_points, config.min_inlier_share * n_in):
            return None  # not a thin hanging thing: no region
        xy = xy[keep]
        c = xy.mean(axis=0)
    d = xy - c
    w, v = np.linalg.eigh(d.T @ d)
    axis = v[:, 1]
    if axis[0] < 0 or (axis[0] == 0 and axis[1] < 0):  # one sign, so refits compare
        axis = -axis
    s = d @ axis
    t = d[:, 0] * -axis[1] + d[:, 1] * axis[0]
    s_lo, s_hi = np.percentile(s, [1.0, 99.0])
    t_lo, t_hi = np.percentile(t, [1.0, 99.0])
    half_len = 0.5 * (s_hi - s_lo) - config.end_margin_m
    if half_len <= 0.0 or t_hi - t_lo > 2.0 * config.band_m:
        return None
    sm, tm = 0.5 * (s_lo + s_hi), 0.5 * (t_lo + t_hi)
    centre = c + sm * axis + tm * np.array([-axis[1], axis[0]])
    half_thick = 0.5 * (t_hi - t_lo)
    return DeformableRegion(int(object_id), (float(centre[0]), float(centre[1])), (float(axis[0]), float(axis[1])),
                            float(half_len), float(half_thick + config.reach_m),
                            float(half_thick + min(config.rest_swing_m, config.reach_m)), float(cost), float(now_s),
                            int(len(xy)))


class DeformableRegions:
    """The regions of the deformable objects seen so far (module docstring)."""

    def __init__(self, config: DeformableConfig | None = None) -> None:
        self.config = config or DeformableConfig()
        self.regions: dict[int, DeformableRegion] = {}
        self.fits = 0  # regions fitted or refit (never reset)
        self.points_labelled = 0  # points the regions made P_mov that the partition had not (never reset)
        self.rigid_points = 0  # points near the robot the motion test kept P_fix (never reset)
        self.points_dropped = 0  # points the object's mask or memory gave it outside its region (never reset)
        # id -> (fit time, per cell: last seen, robot xy when its run began, rigid)
        self._runs: dict[int, tuple[float, np.ndarray, np.ndarray, np.ndarray]] = {}

    def update(self, now_s: float, part: PointPartition, points_odom: np.ndarray, objects: dict[int, float],
               robot_xy: tuple[float, float]) -> None:
        """Refit the region of each deformable object (id -> cost) from the points its mask
        labelled in view this scan, unless the robot is near it; drop regions gone stale."""
        c = self.config
        robot = np.array([robot_xy], dtype=np.float64)
        near = {k for k, r in self.regions.items() if r.contains(robot, grow_m=c.clear_m)[0]}
        # A region ages only while the robot is clear of it (in it, it cannot be refitted: a robot
        # held inside a curtain for max_age_s must not find the slats fixed again).
        for k in [k for k, r in self.regions.items() if now_s - r.fitted_s > c.max_age_s and k not in near]:
            self.remove(k)
        if not c.enabled or not objects:
            return
        if near:
            # Frozen while the robot is in or near a region: the object swings, and its parts
            # hang in front of the camera, whose masks of them then gate the lidar points seen
            # past them (docs/decisions/vpp-deformable-regions.md).
            return
        seen = (part.label == MOVABLE) & part.in_view & ~part.from_memory
        for oid, cost in sorted(objects.items()):
            sel = seen & (part.object_id == oid)
            if np.count_nonzero(sel) < c.min_points:
                continue
            region = fit_region(oid, points_odom[sel, :2], cost, now_s, c)
            if region is not None and region.contains(robot, grow_m=c.clear_m)[0]:
                region = None  # the robot is in it already: its mask points may be swinging slats
            if region is not None:
                self.regions[oid] = region
                self.fits += 1

    def label(self, now_s: float, part: PointPartition, points_odom: np.ndarray, pose: tuple[float, float, float],
              robot: RobotBox) -> int:
        """Make every non-ground point a region takes (module docstring; the robot at its odom
        pose) P_mov of its object (in place), unless another object labelled it; returns the
        points that changed."""
        if not self.config.enabled or not self.regions:
            return 0
        changed = 0
        solid = part.label != IGNORED
        for oid, r in sorted(self.regions.items()):
            inside, rest, on_robot, ahead, depth = r.zones(points_odom, pose, robot, self.config)
            inside &= solid
            tested = inside & ~on_robot & (depth >= self.config.rigid_min_depth_m)
            rigid = self._rigid(oid, r, points_odom, tested, now_s, pose)
            self.rigid_points += int(np.count_nonzero(rigid & ahead))
            inside &= rest | on_robot | (ahead & ~rigid)
            mine = (part.label == MOVABLE) & (part.object_id == oid)
            take = inside & ((part.label != MOVABLE) | mine)
            # The region is the object now: what its mask or the label memory gave it elsewhere
            # (a crate behind the curtain is inside the curtain's mask in the image; a voxel a
            # swinging slat passed through remembers the curtain) is not the curtain.
            drop = mine & ~take
            part.label[drop] = FIXED
            part.object_id[drop] = -1
            part.cost[drop] = np.nan
            self.points_dropped += int(np.count_nonzero(drop))
            fresh = take & (part.label != MOVABLE)
            changed += int(np.count_nonzero(fresh))
            part.label[take] = MOVABLE
            part.object_id[take] = oid
            part.cost[take] = r.cost
        self.points_labelled += changed
        return changed

    def _rigid(self, oid: int, r: DeformableRegion, points_odom: np.ndarray, sel: np.ndarray, now_s: float,
               pose: tuple[float, float, float]) -> np.ndarray:
        """(N,) bool: the points of `sel` in rigid cells (DeformableConfig.rigid_*): cells that
        stayed occupied while the robot moved rigid_motion_m. A rigid cell stays rigid while it is
        seen again within rigid_hold_s (a stopped robot cannot tell a still crate from still
        slats, so what was found rigid while it moved is not forgotten when it stops). Per region
        a grid over its box in its own frame; a refit (a new frame) starts it afresh."""
        c = self.config
        out = np.zeros(len(points_odom), dtype=bool)
        nx = max(1, math.ceil(2 * r.half_length_m / c.rigid_cell_m))
        ny = max(1, math.ceil(2 * r.half_depth_m / c.rigid_cell_m))
        state = self._runs.get(oid)
        if state is None or state[0] != r.fitted_s:
            state = (r.fitted_s, np.full(nx * ny, -np.inf), np.zeros((nx * ny, 2)), np.zeros(nx * ny, dtype=bool))
            self._runs[oid] = state
        _, last, start_xy, rigid = state
        idx = np.flatnonzero(sel)
        if not idx.size:
            return out
        s, t = r.local(points_odom[idx])
        i = np.clip(((s + r.half_length_m) / c.rigid_cell_m).astype(np.intp), 0, nx - 1)
        j = np.clip(((t + r.half_depth_m) / c.rigid_cell_m).astype(np.intp), 0, ny - 1)
        cell = i * ny + j
        cells = np.unique(cell)
        gap = now_s - last[cells]
        fresh = cells[gap > c.rigid_gap_s]
        start_xy[fresh] = (pose[0], pose[1])
        rigid[cells[gap > c.rigid_hold_s]] = False
        last[cells] = now_s
        rigid[cells] |= np.hypot(start_xy[cells, 0] - pose[0], start_xy[cells, 1] - pose[1]) >= c.rigid_motion_m
        out[idx] = rigid[cell]
        return out

    def remove(self, object_id: int) -> bool:
        self._runs.pop(int(object_id), None)
        return self.regions.pop(int(object_id), None) is not None

    def describe(self) -> dict:
        return {"regions": [r.describe() for _, r in sorted(self.regions.items())], "fits": self.fits,
                "points_labelled": self.points_labelled, "rigid_points": self.rigid_points,
                "points_dropped": self.points_dropped}


__all__ = ["DeformableConfig", "DeformableRegion", "DeformableRegions", "RobotBox", "fit_region"]
