"""The way out for a robot standing in a person's predicted way (runtime.perception.moving_obstacles,
step 5): which of the way's predicted points it keeps, so that it leaves the way to one side
rather than holding still in it, and never crosses the person's line in front of the person.

Left out: the predicted points within `own_clearance_m` of the robot along the person's line
(and `head_on_reach_m` more towards a person it faces, so the way out is a forward arc a
differential drive can drive) and not farther than `far_side_m` to the far side of it: a channel
from the robot out to the side of the line it is on or, along the line, the side it will be on
after `exit_heading_lead_m` of driving on, kept until it is `exit_switch_m` on the other side
(exactly on the line: the way it faces when it crosses the line, its right when it is along it).
Kept: the rest of the way, which stops the path from following the line or crossing it in front
of the person. Why this shape and this side rule: docs/decisions/people-exit-channel.md.
"""
from __future__ import annotations

import math

import numpy as np

from runtime.perception.cluster_tracking import Track


def exit_channel(config, way: np.ndarray, a: np.ndarray, velocity: np.ndarray, robot_xy: np.ndarray,
                 heading: np.ndarray, track: Track | None = None) -> np.ndarray:
    """(M,) bool: the predicted points `way` kept for a robot at robot_xy heading along the unit
    vector `heading`, in the way of a person at `a` walking at `velocity` (module docstring);
    the side chosen is kept in track.exit_side. config: PredictorSettings."""
    c = config
    d = velocity / max(float(np.hypot(*velocity)), 1e-9)
    normal = np.array([-d[1], d[0]])
    side = _exit_side(c, (robot_xy, heading), (a, d, normal), track)
    if track is not None:
        track.exit_side = side * normal
    rel = way - robot_xy
    lon = rel @ d
    lat = side * (rel @ normal)  # > 0: towards the exit side
    # Head-on (the robot faces the person), the channel also reaches towards the person: the
    # way out is a forward arc to the side.
    upstream = c.own_clearance_m + (c.head_on_reach_m if float(heading @ d) < -0.7 else 0.0)
    channel = (lon >= -upstream) & (lon <= c.own_clearance_m) & (lat > -c.far_side_m)
    return ~(channel | (np.hypot(lon, lat) <= c.far_side_m))


def _exit_side(c, robot: tuple, line: tuple, track: Track | None) -> float:
    """+1 or -1: the side of the person's line (along `normal`) the robot leaves to. robot =
    (xy, heading), line = (a point on it, its unit direction, its unit normal)."""
    robot_xy, heading = robot
    a, d, normal = line
    e = float((robot_xy - a) @ normal)
    kept = 0.0 if track is None or track.exit_side is None else float(track.exit_side @ normal)
    along_line = abs(float(heading @ d)) >= 0.7
    # Along the line, where the robot heads counts as much as where it is: the offset it will
    # have after exit_heading_lead_m of driving on, to choose a side and to give it up (the line
    # is drawn from the person's visible face and estimated velocity: centimetres off near the
    # person, 0.2 m off 3 m away).
    offset = e + (c.exit_heading_lead_m * float(heading @ normal) if along_line else 0.0)
    if abs(kept) > 0.5 and offset * math.copysign(1.0, kept) > -c.exit_switch_m:
        # the side chosen before, unless the robot is now well on the other (or heading well
        # into it): the centre line, estimated anew every scan, passes a robot on it at a few
        # centimetres either side
        return math.copysign(1.0, kept)
    if abs(offset) > 0.05:  # (within 5 cm: on the line, for a line drawn from a face)
        return math.copysign(1.0, offset)
    if not along_line:  # on the line, across it: on, the way it faces
        return math.copysign(1.0, float(heading @ normal))
    # on the line, along it: to its right
    return math.copysign(1.0, float(np.array([heading[1], -heading[0]]) @ normal))
