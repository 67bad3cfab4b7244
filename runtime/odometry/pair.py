"""Registering one scan against another with the KISS-ICP pipeline of the odometry.

`register_pair(source, target, config)` answers "where is the source scan in the target's
frame": the 4x4 T_target<-source with p_target = T p_source. It runs the same pipeline as the
odometry (`new_kiss_icp`): the target is registered first (it becomes the local map, at the
identity), then the source; KISS-ICP's pose of the second frame is then T_target<-source. This
checks the odometry's registration, with our settings, on real scans with a known answer.

OUTDOOR_PAIR_CONFIG: settings for automotive spinning lidars (HDL-32 class, returns out to
50-100 m), kept for `dct odom register`; IcpConfig's auto defaults derive the voxel and range from
the first scan instead (on this pair: 0.5 m, 0.3-27 m, 1.1 cm and 0.16 deg; the table below was
measured with the then-fixed threshold start 0.5 m and cap 50). Chosen by measurement on tests/data/real/hdl32_pair_small_gicp (two consecutive
HDL-32E scans, 0.50 m apart; 64.7k / 64.1k valid points, 95% within 14 m, farthest 53 m),
error against its T_target_source.txt, identity initial guess, 1 thread, on this 2-core machine:

  voxel  max range  threshold0   translation  rotation   time (both frames)
  0.25   100 m      0.5 m        1.0 cm       0.27 deg    51 ms
  0.3     12 m      0.5 m        2.3 cm       0.29 deg    48 ms   (the indoor defaults)
  0.4     40 m      0.5 m        0.5 cm       0.21 deg    44 ms
  0.5     60 m      0.5 m        0.8 cm       0.20 deg    26 ms   <- chosen
  0.5     40 m      2.0 m        2.9 cm       0.20 deg    33 ms
  0.75    20 m      2.0 m        4.9 cm       0.11 deg    14 ms
  1.0     30 m      2.0 m        4.2 cm       0.24 deg     8 ms
  0.15    12 m      0.5 m       41.0 cm       2.27 deg   106 ms   (a false minimum)

0.5 m / 60 m keeps every return of the sensor, is as accurate as smaller voxels at half their
cost, and stays well inside the 5 cm / 0.5 deg target. The rotation differences of 0.1-0.3 deg
are at the level of the reference itself: the same pair's reference in fast_gicp
(fast_gicp_relative.txt) differs from small_gicp's by 1.9 cm and 0.23 deg.
"""
from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from runtime.odometry.icp_config import IcpConfig, new_kiss_icp
from runtime.odometry.metrics import check_poses, rotation_angle_deg

OUTDOOR_PAIR_CONFIG = IcpConfig(voxel_size_m=0.5, max_range_m=60.0, min_range_m=0.0, deskew="off")


def _points(xyz, what: str) -> np.ndarray:
    a = np.ascontiguousarray(np.asarray(xyz, dtype=np.float64))
    if a.ndim != 2 or a.shape[1] != 3:
        raise ValueError(f"{what}: expected (N,3) points, got shape {a.shape}")
    if len(a) == 0 or not np.isfinite(a).all():
        raise ValueError(f"{what}: points must be finite and at least one (got {len(a)}, "
                         f"{int((~np.isfinite(a).all(axis=1)).sum())} not finite)")
    return a


def register_pair(source_xyz, target_xyz, config: IcpConfig = OUTDOOR_PAIR_CONFIG,
                  initial_guess=None) -> np.ndarray:
    """T_target<-source (4x4, p_target = T p_source) by KISS-ICP (module doc).

    source_xyz, target_xyz: (N,3) finite points (invalid returns already removed, e.g. with
    `sequence.load_scan`). initial_guess: T_target<-source to start from (default identity);
    it is fed in as KISS-ICP's constant-velocity prediction (`last_delta`), which is what
    its `register_frame` starts the second frame from. No deskew: a pair has no motion model.
    """
    source = _points(source_xyz, "source")
    target = _points(target_xyz, "target")
    icp = new_kiss_icp(config, deskew=False)
    no_times = np.zeros(0)
    guess = None
    if initial_guess is not None:
        guess = check_poses(np.asarray(initial_guess, dtype=np.float64)[None], "initial guess")[0].copy()
        # Sophus (inside KISS-ICP) aborts the whole process, no exception, on a rotation that is
        # not orthonormal to about 1e-10: a guess read from a 6-digit text file is 1e-8 off.
        guess[:3, :3] = Rotation.from_matrix(guess[:3, :3]).as_matrix()
    icp.register_frame(target, no_times)
    target_pose = icp.last_pose.copy()  # the identity (an empty map keeps the prediction)
    if guess is not None:
        icp.last_delta = guess  # register_frame predicts last_pose @ last_delta
    icp.register_frame(source, no_times)
    return np.linalg.inv(target_pose) @ icp.last_pose


def transform_difference(estimate, reference) -> tuple[float, float]:
    """(translation difference m, rotation difference deg) between two T_target<-source:
    |t_est - t_ref| and the angle of R_ref^T R_est."""
    est = check_poses(np.asarray(estimate, dtype=np.float64)[None], "estimate")[0]
    ref = check_poses(np.asarray(reference, dtype=np.float64)[None], "reference")[0]
    return (float(np.linalg.norm(est[:3, 3] - ref[:3, 3])),
            float(rotation_angle_deg(ref[:3, :3].T @ est[:3, :3])))


__all__ = ["OUTDOOR_PAIR_CONFIG", "register_pair", "transform_difference"]
