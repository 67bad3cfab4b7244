"""Moving obstacles (people): clusters of P_fix followed from scan to scan, and where they go next.

Why: the MPC and the safety supervisor see P_fix as it is now. A person crossing the robot's way
at 1 m/s is half a metre further on half a second later: a robot that plans round where the person
is drives into where the person will be. A person is never pushed (the backend's cost 10, the
oracle's `fixed`); this module makes the robot yield to where the person is going.

How, per scan (P_fix in the odom frame, (N, 2), and the robot's position):
1-3. Clusters, tracks and velocities, and whether a track is moving (it left where it was and
   came into space seen free): runtime.perception.cluster_tracking.
4-5. Each moving track's way ahead, and whether the robot, going straight on, would meet the
   person on it; a conflict gives the planner and the supervisor the person's whole way ahead
   with P_fix (`with_predictions`): the reference path goes behind the person or waits, the MPC
   keeps clear, the supervisor stops a command that sweeps into it. Going on in front of the
   person where braking would not keep clear, and the way out for a robot already in the
   person's way: runtime.perception.way_prediction and runtime.perception.exit_channel.
The algorithm page is docs/algorithms/people.md; the choices and what they were measured by are
in docs/decisions/people-*.md.

Not a pedestrian model (no social forces, no intent): constant velocity over 1.5 s (longer for a
slow walker, `min_way_m`, or one coming down the robot's line, `max_horizon_s`), which is
what the robot needs to stay out of a walking person's way at its own 1 m/s. A track is found
moving after 0.6 s of scans at the earliest (`min_span_s` and the vacated test's `vacated_lag_s`
from its first scan). Cost: one labelling of a (2 range_m / cell_m)^2 grid (240 x 240 at the
default 12 m range) and a few numpy operations per cluster and scan (`dct bench tick` measures
the tick).
"""
from __future__ import annotations

import math

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from runtime.perception.cluster_tracking import ClusterTracker, Track
from runtime.perception.way_prediction import WayPredictor


class MovingObstaclesConfig(BaseModel):
    """Settings of the moving-obstacle predictor (controller config `moving_obstacles`)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    enabled: bool = True
    #: The obstacle points' range (the controller sets planner.obstacle_points.max_range_m): a
    #: cluster with a point within range_margin_m of it is cut by it, and not followed.
    range_m: float | None = Field(None, gt=0.5, le=100.0)
    range_margin_m: float = Field(0.3, ge=0.0, le=5.0)
    cell_m: float = Field(0.10, gt=0.01, le=1.0)
    min_points: int = Field(8, ge=1, le=10000)
    #: Wider clusters (bounding box diagonal, m) are structure, not followed.
    max_extent_m: float = Field(1.0, gt=0.05, le=10.0)
    gate_m: float = Field(0.25, gt=0.0, le=5.0)
    max_speed_mps: float = Field(2.5, gt=0.0, le=20.0)
    lost_s: float = Field(0.5, gt=0.0, le=10.0)
    window_s: float = Field(0.6, gt=0.05, le=10.0)
    min_span_s: float = Field(0.2, gt=0.0, le=10.0)
    min_speed_mps: float = Field(0.35, gt=0.0, le=10.0)
    min_travel_m: float = Field(0.12, ge=0.0, le=10.0)
    #: ... and it left where it was: of its points vacated_lag_s ago, at most max_still_filled
    #: (a share) lie in cells this scan fills (step 3).
    vacated_lag_s: float = Field(0.4, gt=0.0, le=10.0)
    max_still_filled: float = Field(0.5, ge=0.0, le=1.0)
    #: ... and it came into space the lidar saw free vacated_lag_s ago, or left space the lidar
    #: sees free now: at least this share of its points now lie nearer than that scan's return on
    #: their bearing (seen from where the robot was), or of its points then nearer than this
    #: scan's return, by free_margin_m (step 3). 0: off. The faces a static object shows a
    #: passing robot were behind its other faces before (never seen free), and its old faces are
    #: hidden now, not empty. A person walking away moves into space its own body hid, and out of
    #: space seen free now (docs/decisions/people-moving-test.md).
    min_moved_in: float = Field(0.25, ge=0.0, le=1.0)
    free_margin_m: float = Field(0.10, ge=0.0, le=2.0)
    #: ... on every bearing within this (m, across the ray) of the point.
    free_lateral_m: float = Field(0.10, gt=0.0, le=2.0)
    #: The bearing bins (deg) of a scan's nearest return, for the test above.
    bearing_bin_deg: float = Field(1.0, gt=0.05, le=10.0)
    #: A track moving in every scan for this long (s) may conflict (step 5). 0: at once (a
    #: static object next to a turning robot can look moving for a few scans, but waiting costs
    #: contacts with people: docs/decisions/people-moving-test.md).
    min_moving_s: float = Field(0.0, ge=0.0, le=10.0)
    horizon_s: float = Field(1.5, ge=0.0, le=10.0)
    #: A person whose line passes over the robot (within in_the_way_m) and who comes towards it:
    #: the way is predicted until the person is past the robot (+ step_s), up to this (s): a way
    #: reaching past the robot leaves it the two sides, and the near one is the cheaper
    #: (docs/decisions/people-way-length.md).
    max_horizon_s: float = Field(4.0, ge=0.0, le=20.0)
    #: The way ahead is at least this long (m; time capped by max_horizon_s): a slow walker's
    #: 1.5 s is under a metre, and a path round its front passes in front of the person. Longer,
    #: going behind is the shorter way (docs/decisions/people-way-length.md).
    min_way_m: float = Field(2.0, ge=0.0, le=20.0)
    #: (The conflict test reads the longer way too: a slow or distant walker conflicts sooner.)
    step_s: float = Field(0.25, gt=0.0, le=10.0)
    max_points: int = Field(24, ge=1, le=10000)
    #: A predicted point counts only where the robot would be about then (step 5): within this
    #: distance (m) of the robot's straight-line extrapolation over that step +- one step.
    conflict_radius_m: float = Field(0.45, gt=0.0, le=5.0)
    #: The extrapolation's speeds: the robot's own, at least this (a robot standing, waiting,
    #: asks whether going would meet the person), and its cruise speed (the reference path's
    #: target speed unless set here): a conflict is one at both.
    min_extrapolation_speed_mps: float = Field(0.5, ge=0.0, le=5.0)
    cruise_speed_mps: float | None = Field(None, gt=0.0, le=5.0)
    #: A conflict holds this long (s) after the last scan that found it (no flicker).
    conflict_hold_s: float = Field(0.5, ge=0.0, le=10.0)
    #: A robot whose centre is within in_the_way_m of the person's predicted centre line (a
    #: person's radius, 0.25 m, and the robot's circumscribed radius, 0.2 m: the person's body
    #: would sweep over it) is in the person's way: the predicted points within own_clearance_m
    #: of it are left out, so that it leaves the way rather than holding still in it. A robot
    #: beside the way keeps them all and holds before it.
    in_the_way_m: float = Field(0.45, ge=0.0, le=5.0)
    own_clearance_m: float = Field(0.35, ge=0.0, le=5.0)
    #: ... the channel out keeps the way's points farther than this on the robot's far side (m):
    #: the path may not cross the person's line there (runtime.perception.exit_channel).
    far_side_m: float = Field(0.22, ge=0.0, le=5.0)
    #: ... and, head-on, reaches this much further towards the person (m).
    head_on_reach_m: float = Field(0.4, ge=0.0, le=5.0)
    #: ... and a robot along the line goes to the side it will be on after this much driving on
    #: (m): the side it heads to, unless it is well on the other (runtime.perception.exit_channel).
    exit_heading_lead_m: float = Field(0.3, ge=0.0, le=5.0)
    #: A side once chosen is kept until the robot is this far (m) on the other side of the line
    #: (with the lead above, along it).
    exit_switch_m: float = Field(0.15, ge=0.0, le=5.0)
    #: Going on or yielding (step 5, WayPredictor._goes_first): the footprint (the robot description's, set by
    #: the controller) against the person's predicted points every go_dt_s, braking at the
    #: acceleration limit and hurrying on to cruise; a way's margin is its gap less
    #: go_uncertainty_mps x the time ahead (at most horizon_s: a velocity estimated over 0.6 s of
    #: a person who just set off is short, docs/decisions/people-go-first.md). The robot yields when
    #: braking keeps a margin of go_clearance_m; else it goes on if that has the larger gap and a
    #: margin of at least 0, and then goes on while the gap stays above go_commit_clearance_m.
    go_clearance_m: float = Field(0.15, ge=0.0, le=5.0)
    go_uncertainty_mps: float = Field(0.25, ge=0.0, le=5.0)
    go_commit_clearance_m: float = Field(0.05, ge=0.0, le=5.0)
    go_dt_s: float = Field(0.05, ge=0.01, le=1.0)
    #: A track moving this far (m) since it was found moving is left out of the lidar odometry
    #: (moving_points).
    odometry_travel_m: float = Field(0.3, ge=0.0, le=10.0)


class PredictorSettings(MovingObstaclesConfig):
    """What the predictor runs with: the user's `moving_obstacles:` section with its derived
    fields filled (runtime.config: the obstacle points' range, the reference path's cruise
    speed), and the robot description's acceleration limit and footprint. The defaults are the
    LIMO's (tests)."""

    range_m: float = Field(6.0, gt=0.5, le=100.0)
    cruise_speed_mps: float = Field(1.0, gt=0.0, le=5.0)
    #: The robot reaches its cruise speed and brakes at this acceleration (m/s^2).
    accel_mps2: float = Field(2.0, gt=0.0, le=20.0)
    robot_half_length_m: float = Field(0.161, gt=0.0, le=5.0)
    robot_half_width_m: float = Field(0.11, gt=0.0, le=5.0)

    @classmethod
    def for_robot(cls, config: MovingObstaclesConfig, robot) -> "PredictorSettings":
        """config: resolved (range_m and cruise_speed_mps set); robot: a RobotDescription."""
        return cls.model_validate({
            **config.model_dump(), "accel_mps2": robot.limits.max_linear_accel_mps2,
            "robot_half_length_m": robot.footprint.length_m / 2.0,
            "robot_half_width_m": robot.footprint.width_m / 2.0})


class MovingObstacles:
    """Tracks of P_fix clusters and their predicted points (module docstring)."""

    def __init__(self, config: PredictorSettings | None = None) -> None:
        self.config = config or PredictorSettings()
        self._tracker = ClusterTracker(self.config)
        self._ways = WayPredictor(self.config)
        self._predicted = np.zeros((0, 2))
        self.moving_seen = 0  # tracks that were ever found moving (never reset)
        self._ever_moving: set[int] = set()
        self.max_moving = 0  # most tracks moving in one scan

    @property
    def tracks(self) -> list[Track]:
        """The tracks followed now."""
        return self._tracker.tracks

    @property
    def conflicts(self) -> int:
        """Scans in which a moving track would meet the robot (never reset)."""
        return self._ways.conflicts

    @property
    def predicted(self) -> np.ndarray:
        """(M, 2) odom points: the moving clusters carried along their velocity (step 4)."""
        return self._predicted

    def reset(self) -> None:
        self._tracker.reset()
        self._predicted = np.zeros((0, 2))

    def update(self, now_s: float, points_fix: np.ndarray, robot_pose: tuple[float, float, float],
               robot_speed_mps: float = 0.0) -> np.ndarray:
        """One scan's P_fix (odom (N, 2)), the robot's odom pose and speed; returns the predicted
        points that conflict with the robot's way (also `predicted`)."""
        c = self.config
        if not c.enabled:
            return self._predicted
        robot_xy = (float(robot_pose[0]), float(robot_pose[1]))
        points_fix = np.asarray(points_fix, dtype=np.float64).reshape(-1, 2)
        self._tracker.scan(now_s, points_fix, robot_xy)
        moving = [t for t in self.tracks if t.moving and t.last[0] == now_s]
        self.max_moving = max(self.max_moving, len(moving))
        for t in moving:
            if t.track_id not in self._ever_moving:
                self._ever_moving.add(t.track_id)
                self.moving_seen += 1
        self._predicted = self._ways.predict(float(now_s), moving, robot_pose, robot_speed_mps)
        return self._predicted

    def moving_points(self, now_s: float) -> np.ndarray:
        """(M, 2) odom points of the tracks moving at their last scan that have gone at least
        `odometry_travel_m` since they were found moving, carried along their velocity to now_s:
        where the people are (the odometry leaves them out of its ICP). The travel test keeps a
        static object that looked moving for a few scans in the ICP
        (docs/decisions/people-moving-test.md)."""
        c = self.config
        out = [t.points + t.velocity * max(0.0, now_s - t.last[0]) for t in self.tracks
               if t.moving and len(t.points) and t.moving_from is not None
               and math.hypot(t.last[1] - t.moving_from[0], t.last[2] - t.moving_from[1]) >= c.odometry_travel_m]
        return np.concatenate(out) if out else np.zeros((0, 2))

    def with_predictions(self, points_fix: np.ndarray) -> np.ndarray:
        """P_fix and the predicted points, for the planner and the supervisor."""
        if not len(self._predicted):
            return points_fix
        return np.concatenate([np.asarray(points_fix, dtype=np.float64).reshape(-1, 2), self._predicted])

    def shift(self, correction: np.ndarray) -> None:
        """An odometry correction (dx, dy, dyaw) moved the odom frame's points: the tracks and the
        predictions move with them (as the controller's P_fix does)."""
        c, s = math.cos(correction[2]), math.sin(correction[2])
        R = np.array([[c, -s], [s, c]])

        def move(p: np.ndarray) -> np.ndarray:
            return p @ R.T + correction[:2] if len(p) else p

        self._predicted = move(self._predicted)
        self._tracker.shift(move, R, correction[2] / math.radians(self.config.bearing_bin_deg))

    def describe(self) -> dict:
        return {"tracks": len(self.tracks), "moving_now": sum(t.moving for t in self.tracks),
                "moving_seen": self.moving_seen, "max_moving": self.max_moving,
                "conflict_scans": self.conflicts, "predicted_points": int(len(self._predicted))}


__all__ = ["MovingObstacles", "MovingObstaclesConfig"]
