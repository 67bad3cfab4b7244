"""How far an estimated trajectory is from a reference one: drift and relative pose error.

One module for every odometry evaluation (`dct odom eval` on a scenario or on a recorded
sequence), so the figures of ICP alone, wheels+IMU and the fused stream are computed the same
way and can be put side by side. numpy (and scipy's rotations) only: it runs on the robot too.

Poses are SE(3) matrices, an (N,4,4) array: pose i maps points of the body (sensor) frame at
sample i into the trajectory's world frame, `p_world = T_i @ p_body`. Planar poses (x, y, yaw)
convert with `planar_to_se3` / `se3_to_planar`. The world frame has z up (yaw is about z).

Definitions (`trajectory_errors(estimate, reference)`; sample i of one is sample i of the other):

* Both trajectories are first expressed relative to their own first pose, `T_i <- T_0^-1 T_i`:
  odometry starts wherever it starts, so only the motion since the first sample is compared.
  The errors are therefore unchanged when either trajectory is moved as a whole by a rigid
  transform.
* `length_m`: the reference path length, the sum of the distances between consecutive
  reference positions.
* `end_error_m`: the distance between the estimated and the reference position of the last
  sample (after the step above).
* `drift_percent`: 100 * end_error_m / length_m (null when length_m is 0).
* `yaw_drift_deg`: the absolute difference, wrapped to [0, 180], between the estimated and the
  reference heading of the last sample; the heading of a pose is the direction of its body x
  axis in the world xy plane, atan2(R[1,0], R[0,0]).
* `end_rotation_error_deg`: the angle of the whole 3-D rotation error R_ref^T R_est at the last
  sample (equals yaw_drift_deg for planar motion).
* `rpe_percent` and `rpe_deg_per_m`: the relative pose error per metre, as KITTI's odometry
  benchmark defines it but for robot-sized trajectories. For each segment length L (below) and
  each start sample i (one every min(0.5 m, L/2) of reference path), the end sample j is the
  first one at least L further along the reference path. The error of that segment is
  E = (R_i^-1 R_j)^-1 (E_i^-1 E_j) (reference motion over the segment, undone by the estimated
  one); its translation error is |t(E)| and its rotation error the angle of E. Each is divided
  by the reference path length actually covered between i and j (at least L; KITTI divides by
  the nominal L, which biases the figure up by the sample spacing), and the mean over all
  segments of all lengths is reported: rpe_percent = 100 * mean(|t(E)| / d_ij),
  rpe_deg_per_m = mean(angle(E) / d_ij) in degrees. Unlike the end error, the RPE does not
  depend on where along the trajectory an error happened.
* `rpe_segments_m`: the segment lengths used: the 1-2-5 series (0.1, 0.2, 0.5, 1, 2, 5, 10,
  20, 50, ... 5000 m), the largest RPE_MAX_SEGMENT_LENGTHS values not longer than length_m (a 15 m
  run uses 2, 5, 10 m; KITTI's 100..800 m suits its 1-5 km runs, not a robot crossing a room).
  Empty, and both RPE figures null, when the path is shorter than the shortest length.
* `rpe_count`: how many segments were averaged.
* `poses`: the number of samples.

Inputs are validated: same number of poses (at least 2), finite, bottom row (0, 0, 0, 1),
rotations orthonormal within ROTATION_TOLERANCE with determinant +1. A violation raises
ValueError naming which trajectory, which pose and what is wrong.
"""
from __future__ import annotations

import math
from typing import Sequence

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

#: Largest |R^T R - I| entry accepted for a rotation. Pose files written with 6-7 significant
#: digits (KITTI's %e) are orthonormal to about 1e-7; 1e-4 still refuses anything that is not
#: a rotation matrix while accepting text round-trips.
ROTATION_TOLERANCE = 1e-4
#: Candidate RPE segment lengths (m): the 1-2-5 series, 0.1 m to 5 km.
RPE_CANDIDATE_LENGTHS_M = tuple(round(m * 10.0**e, 6) for e in range(-1, 4) for m in (1, 2, 5))
#: How many of the longest fitting candidates are used.
RPE_MAX_SEGMENT_LENGTHS = 4
#: Start samples of the RPE segments are this far apart along the path (at most L/2).
RPE_START_STEP_M = 0.5


# ---------------------------------------------------------------------------- validation
def check_poses(poses, what: str = "poses", tolerance: float = ROTATION_TOLERANCE) -> np.ndarray:
    """`poses` as a float64 (N,4,4) array of rigid transforms, or ValueError naming `what`, the
    pose index and the problem."""
    arr = np.asarray(poses, dtype=np.float64)
    if arr.ndim != 3 or arr.shape[1:] != (4, 4):
        raise ValueError(f"{what}: expected an (N,4,4) array of poses, got shape {arr.shape}")
    bad = ~np.isfinite(arr).all(axis=(1, 2))
    if bad.any():
        raise ValueError(f"{what}: pose {int(np.argmax(bad))} has a value that is not finite")
    bottom = np.abs(arr[:, 3, :] - (0.0, 0.0, 0.0, 1.0)).max(axis=1)
    if (bottom > 1e-9).any():
        i = int(np.argmax(bottom > 1e-9))
        raise ValueError(f"{what}: pose {i}: bottom row must be 0 0 0 1, got {arr[i, 3].tolist()}")
    check_rotations(arr[:, :3, :3], what, tolerance)
    return arr


def rotation_problem(R: np.ndarray, tolerance: float = ROTATION_TOLERANCE) -> str | None:
    """Why a (3,3) matrix is not a rotation (None when it is one within `tolerance`)."""
    R = np.asarray(R, dtype=np.float64)
    dev = float(np.abs(R.T @ R - np.eye(3)).max())
    if not dev <= tolerance:
        return f"rotation is not orthonormal (largest |R^T R - I| entry {dev:.2g} > {tolerance:g})"
    det = float(np.linalg.det(R))
    if det < 0:
        return f"rotation has determinant {det:.3f} (a reflection, not a rotation)"
    return None


def check_rotations(rotations: np.ndarray, what: str, tolerance: float = ROTATION_TOLERANCE) -> None:
    """ValueError unless every (3,3) matrix is orthonormal within `tolerance` with determinant +1."""
    R = np.asarray(rotations, dtype=np.float64)
    dev = np.abs(np.einsum("nji,njk->nik", R, R) - np.eye(3)).max(axis=(1, 2))
    bad = ~(dev <= tolerance) | (np.linalg.det(R) < 0)
    if bad.any():
        i = int(np.argmax(bad))
        raise ValueError(f"{what}: pose {i}: {rotation_problem(R[i], tolerance)}")


# ---------------------------------------------------------------------------- conversions
def planar_to_se3(xy_yaw) -> np.ndarray:
    """(N,3) rows of (x m, y m, yaw rad) to (N,4,4) poses in the z = 0 plane."""
    a = np.asarray(xy_yaw, dtype=np.float64)
    if a.ndim != 2 or a.shape[1] != 3:
        raise ValueError(f"planar poses: expected an (N,3) array of x, y, yaw, got shape {a.shape}")
    if not np.isfinite(a).all():
        raise ValueError(f"planar poses: row {int(np.argmax(~np.isfinite(a).all(axis=1)))} is not finite")
    out = np.zeros((len(a), 4, 4))
    c, s = np.cos(a[:, 2]), np.sin(a[:, 2])
    out[:, 0, 0], out[:, 0, 1], out[:, 1, 0], out[:, 1, 1] = c, -s, s, c
    out[:, 2, 2] = out[:, 3, 3] = 1.0
    out[:, 0, 3], out[:, 1, 3] = a[:, 0], a[:, 1]
    return out


def heading(poses) -> np.ndarray:
    """Yaw (rad) of each pose: the direction of its body x axis in the world xy plane."""
    p = np.asarray(poses, dtype=np.float64)
    return np.arctan2(p[:, 1, 0], p[:, 0, 0])


def se3_to_planar(poses) -> np.ndarray:
    """(N,4,4) poses to (N,3) rows of (x, y, yaw); z, roll and pitch are dropped."""
    p = check_poses(poses)
    return np.stack([p[:, 0, 3], p[:, 1, 3], heading(p)], axis=1)


def relative_to_first(poses: np.ndarray) -> np.ndarray:
    """T_0^-1 T_i for every i: the trajectory as seen from its first pose."""
    return np.linalg.inv(poses[0]) @ poses


def rotation_angle_deg(rotations: np.ndarray) -> np.ndarray:
    """The angle (deg) of each (3,3) rotation (scipy's, exact near 0 where arccos of the trace is not)."""
    return np.degrees(Rotation.from_matrix(rotations).magnitude())


def wrap_deg(angle_deg):
    """Angles wrapped to [-180, 180)."""
    return (np.asarray(angle_deg) + 180.0) % 360.0 - 180.0


# ---------------------------------------------------------------------------- interpolation
def interpolate_poses(times, poses, query_times) -> np.ndarray:
    """Poses at `query_times`: translation linear, rotation by slerp between the two neighbours.

    times: (N,) strictly increasing seconds; poses: (N,4,4); query_times: (M,) within
    [times[0], times[-1]] (a query outside is a ValueError naming it: extrapolating a
    trajectory invents motion).
    """
    t = np.asarray(times, dtype=np.float64)
    q = np.asarray(query_times, dtype=np.float64)
    p = check_poses(poses)
    if t.ndim != 1 or len(t) != len(p):
        raise ValueError(f"interpolate_poses: {t.shape} times for {len(p)} poses")
    if len(t) == 0:
        raise ValueError("interpolate_poses: no poses to interpolate")
    if not np.isfinite(t).all() or not np.isfinite(q).all():
        raise ValueError("interpolate_poses: times must be finite")
    if len(t) > 1 and not (np.diff(t) > 0).all():
        i = int(np.argmax(~(np.diff(t) > 0)))
        raise ValueError(f"interpolate_poses: times must be strictly increasing (times[{i + 1}] = {t[i + 1]} "
                         f"<= times[{i}] = {t[i]})")
    q1 = np.atleast_1d(q)
    outside = (q1 < t[0]) | (q1 > t[-1])
    if outside.any():
        k = int(np.argmax(outside))
        raise ValueError(f"interpolate_poses: query time {q1[k]} is outside the trajectory's "
                         f"[{t[0]}, {t[-1]}] s (no extrapolation)")
    out = np.zeros((len(q1), 4, 4))
    out[:, 3, 3] = 1.0
    if len(t) == 1:
        out[:] = p[0]
    else:
        for k in range(3):
            out[:, k, 3] = np.interp(q1, t, p[:, k, 3])
        out[:, :3, :3] = Slerp(t, Rotation.from_matrix(p[:, :3, :3]))(q1).as_matrix()
    return out.reshape(q.shape + (4, 4)) if q.ndim == 0 else out


# ---------------------------------------------------------------------------- the metrics
def path_distances(poses: np.ndarray) -> np.ndarray:
    """(N,) cumulative path length (m) at each sample, 0 at the first."""
    steps = np.linalg.norm(np.diff(poses[:, :3, 3], axis=0), axis=1)
    return np.concatenate([[0.0], np.cumsum(steps)])


def rpe_segment_lengths(length_m: float) -> list[float]:
    """The RPE segment lengths for a path of `length_m` (see the module doc)."""
    fitting = [L for L in RPE_CANDIDATE_LENGTHS_M if L <= length_m + 1e-9]
    return fitting[-RPE_MAX_SEGMENT_LENGTHS:]


def relative_pose_errors(estimate: np.ndarray, reference: np.ndarray, segment_lengths_m: Sequence[float],
                         start_step_m: float = RPE_START_STEP_M) -> tuple[np.ndarray, np.ndarray, list[float]]:
    """Per-segment translation error / distance and rotation error (deg) / distance (see the
    module doc), and the segment lengths that had at least one segment. Poses already
    validated, same count, relative to their first pose or not (the errors are the same)."""
    dist = path_distances(reference)
    trans, rot, used = [], [], []
    for L in segment_lengths_m:
        step = min(start_step_m, L / 2.0)
        starts = np.unique(np.searchsorted(dist, np.arange(0.0, dist[-1] - L + 1e-9, step), side="left"))
        ends = np.searchsorted(dist, dist[starts] + L - 1e-9, side="left")
        keep = ends < len(dist)
        starts, ends = starts[keep], ends[keep]
        if len(starts) == 0:
            continue
        d = dist[ends] - dist[starts]
        rel_ref = np.linalg.inv(reference[starts]) @ reference[ends]
        rel_est = np.linalg.inv(estimate[starts]) @ estimate[ends]
        err = np.linalg.inv(rel_ref) @ rel_est
        trans.append(np.linalg.norm(err[:, :3, 3], axis=1) / d)
        rot.append(rotation_angle_deg(err[:, :3, :3]) / d)
        used.append(float(L))
    if not trans:
        return np.zeros(0), np.zeros(0), []
    return np.concatenate(trans), np.concatenate(rot), used


def trajectory_errors(estimate, reference, segment_lengths_m: Sequence[float] | None = None) -> dict:
    """Drift and relative pose error of `estimate` against `reference` (module doc: definitions).

    estimate, reference: (N,4,4) poses, sample i of one at the time of sample i of the other
    (`interpolate_poses` aligns streams sampled at other times). segment_lengths_m: override the
    RPE segment lengths (default: chosen from the reference length). Returns a JSON-ready dict;
    a figure that is undefined (RPE of a path shorter than every segment, drift of a path of
    length 0) is None.
    """
    est = check_poses(estimate, "estimate")
    ref = check_poses(reference, "reference")
    if len(est) != len(ref):
        raise ValueError(f"estimate has {len(est)} poses, reference has {len(ref)}; they must be sampled alike")
    if len(ref) < 2:
        raise ValueError(f"at least 2 poses are needed to measure motion, got {len(ref)}")
    est, ref = relative_to_first(est), relative_to_first(ref)
    length = float(path_distances(ref)[-1])
    end_error = float(np.linalg.norm(est[-1, :3, 3] - ref[-1, :3, 3]))
    yaw_drift = float(abs(wrap_deg(np.degrees(heading(est[-1:]) - heading(ref[-1:])))[0]))
    end_rot = float(rotation_angle_deg(ref[-1, :3, :3].T @ est[-1, :3, :3]))
    if segment_lengths_m is None:
        segments = rpe_segment_lengths(length)
    else:
        segments = [float(L) for L in segment_lengths_m]
        if any(not (math.isfinite(L) and L > 0) for L in segments):
            raise ValueError(f"segment lengths must be positive, got {segments}")
    t_err, r_err, used = relative_pose_errors(est, ref, segments)
    return {
        "length_m": length,
        "end_error_m": end_error,
        "drift_percent": 100.0 * end_error / length if length > 0 else None,
        "yaw_drift_deg": min(yaw_drift, 180.0),
        "end_rotation_error_deg": end_rot,
        "rpe_percent": 100.0 * float(t_err.mean()) if len(t_err) else None,
        "rpe_deg_per_m": float(r_err.mean()) if len(r_err) else None,
        "rpe_segments_m": used,
        "rpe_count": int(len(t_err)),
        "poses": int(len(ref)),
    }


__all__ = [
    "ROTATION_TOLERANCE", "RPE_CANDIDATE_LENGTHS_M", "RPE_MAX_SEGMENT_LENGTHS", "RPE_START_STEP_M",
    "check_poses", "check_rotations", "heading", "interpolate_poses", "path_distances", "planar_to_se3",
    "relative_pose_errors", "relative_to_first", "rotation_problem", "rotation_angle_deg", "rpe_segment_lengths", "se3_to_planar",
    "trajectory_errors", "wrap_deg",
]
