"""A small synthetic lidar sequence written to disk like a user's recording (for the tests).

The scene is a walled room with a floor, pillars and boxes. Each scan samples fresh random
points on those surfaces within the sensor's range (no occlusion: ICP only needs structure),
so no two scans share a point. The robot drives a gentle arc at 0.1 m per scan.

sweep=True imitates a spinning lidar: every point has a time in [0, 0.1) s (from its azimuth)
and is observed from the pose the sensor had at that time, as a moving sensor sees the world;
the scan's reference pose is the pose at the end of the sweep, where KISS-ICP deskews to.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from calibration.pointcloud_write import write_pcd, write_ply
from runtime.odometry.metrics import interpolate_poses, planar_to_se3
from runtime.odometry.sequence import format_kitti_poses

SWEEP_S = 0.1


def write_kitti_bin(path: Path, xyz: np.ndarray, intensity: np.ndarray | None = None) -> None:
    """A KITTI velodyne .bin: float32 x, y, z, intensity per point."""
    rec = np.zeros((len(xyz), 4), dtype="<f4")
    rec[:, :3] = xyz
    rec[:, 3] = 0.0 if intensity is None else intensity
    path.write_bytes(rec.tobytes())


def _rect(rng, n, origin, u, v):
    a, b = rng.random((2, n))
    return origin + a[:, None] * u + b[:, None] * v


def scene_points(rng: np.random.Generator, n: int) -> np.ndarray:
    """n random points on the scene's surfaces, area-weighted."""
    surfaces = []  # (area, sampler)
    W, D, H = 16.0, 10.0, 3.0  # room from (-4,-5) to (12, 5)
    o = np.array([-4.0, -5.0, 0.0])
    ex, ey, ez = np.eye(3)
    surfaces.append((W * D, lambda k: _rect(rng, k, o, W * ex, D * ey)))  # floor
    surfaces.append((W * H, lambda k: _rect(rng, k, o, W * ex, H * ez)))
    surfaces.append((W * H, lambda k: _rect(rng, k, o + D * ey, W * ex, H * ez)))
    surfaces.append((D * H, lambda k: _rect(rng, k, o, D * ey, H * ez)))
    surfaces.append((D * H, lambda k: _rect(rng, k, o + W * ex, D * ey, H * ez)))
    for cx, cy, r in [(1.5, 1.8, 0.25), (3.0, -2.0, 0.3), (5.0, 2.5, 0.2), (-1.0, -1.5, 0.35), (7.0, -1.0, 0.25)]:
        def pillar(k, cx=cx, cy=cy, r=r):
            phi, z = rng.random(k) * 2 * np.pi, rng.random(k) * H
            return np.stack([cx + r * np.cos(phi), cy + r * np.sin(phi), z], axis=1)
        surfaces.append((2 * np.pi * r * H, pillar))
    for x0, y0, sx, sy, sz in [(2.0, 3.0, 1.2, 0.8, 0.9), (4.0, -3.5, 0.6, 1.5, 1.2), (-2.5, 2.5, 1.0, 1.0, 0.6),
                               (6.0, 0.8, 0.8, 0.5, 0.5)]:
        b = np.array([x0, y0, 0.0])
        for face in [(b, sx * ex, sz * ez), (b + sy * ey, sx * ex, sz * ez), (b, sy * ey, sz * ez),
                     (b + sx * ex, sy * ey, sz * ez), (b + sz * ez, sx * ex, sy * ey)]:
            area = np.linalg.norm(np.cross(face[1], face[2]))
            surfaces.append((area, lambda k, f=face: _rect(rng, k, *f)))
    areas = np.array([a for a, _ in surfaces])
    counts = rng.multinomial(n, areas / areas.sum())
    return np.concatenate([s(k) for (_, s), k in zip(surfaces, counts) if k > 0])


def trajectory(n_scans: int, step_m=0.1, yaw_per_scan_rad=0.02, still_scans: int = 0) -> np.ndarray:
    """(n_scans + 1, 4, 4) sensor poses at the sweep boundaries: an arc from the origin, 0.3 m up,
    after standing still for the first `still_scans` sweeps. step_m and yaw_per_scan_rad are the
    motion of each sweep: one value for all, or one per sweep (n_scans values)."""
    moving = np.arange(n_scans) >= still_scans
    ds = np.broadcast_to(np.asarray(step_m, dtype=float), (n_scans,)) * moving
    dyaw = np.broadcast_to(np.asarray(yaw_per_scan_rad, dtype=float), (n_scans,)) * moving
    yaw = np.concatenate([[0.0], np.cumsum(dyaw)])
    x = np.concatenate([[0.0], np.cumsum(ds * np.cos(yaw[:-1] + dyaw / 2))])
    y = np.concatenate([[0.0], np.cumsum(ds * np.sin(yaw[:-1] + dyaw / 2))])
    poses = planar_to_se3(np.stack([x, y, yaw], axis=1))
    poses[:, 2, 3] = 0.3
    return poses


def make_sequence(folder: Path, n_scans: int = 20, points: int = 4000, sweep: bool = False, seed: int = 0,
                  noise_m: float = 0.01, fmt: str = "mixed", step_m=0.1,
                  yaw_per_scan_rad=0.02, still_scans: int = 0) -> tuple[Path, Path, Path]:
    """Write scans `scan_0 .. scan_{n-1}` (natural order matters: scan_10 after scan_9), a KITTI
    poses file and a times file under `folder`; returns (scans dir, poses file, times file).

    fmt: "pcd", "ply", "bin" (KITTI velodyne) or "mixed" (PCD and PLY alternating). Scans carry a
    float32 `t` field (seconds in the sweep) when sweep=True (not in .bin). step_m, yaw_per_scan_rad:
    see trajectory().
    """
    rng = np.random.default_rng(seed)
    scans = folder / "scans"
    scans.mkdir(parents=True)
    boundaries = trajectory(n_scans, step_m, yaw_per_scan_rad, still_scans)
    times = np.arange(n_scans + 1) * SWEEP_S
    ref = []
    for i in range(n_scans):
        start, end = boundaries[i], boundaries[i + 1]
        world = rng.permutation(scene_points(rng, points * 3))  # surfaces come in order: mix them
        centre = start if not sweep else interpolate_poses(times[i:i + 2], boundaries[i:i + 2], [times[i] + SWEEP_S / 2])[0]
        local = (world - centre[:3, 3]) @ centre[:3, :3]
        rng_m = np.linalg.norm(local, axis=1)
        keep = (rng_m > 0.5) & (rng_m < 11.0)
        world, local = world[keep][:points], local[keep][:points]
        fields = {}
        if sweep:
            az = np.arctan2(local[:, 1], local[:, 0])
            t = (az + np.pi) / (2 * np.pi) * SWEEP_S * (1 - 1e-6)
            at = interpolate_poses(times[i:i + 2], boundaries[i:i + 2], times[i] + t)
            local = np.einsum("nji,nj->ni", at[:, :3, :3], world - at[:, :3, 3])
            ref.append(end)
        else:
            ref.append(start)
        local = local + rng.normal(0.0, noise_m, local.shape)
        fields.update(x=local[:, 0].astype(np.float32), y=local[:, 1].astype(np.float32), z=local[:, 2].astype(np.float32))
        if sweep:
            fields["t"] = t.astype(np.float32)
        if fmt == "bin":
            write_kitti_bin(scans / f"{i:06d}.bin", local)
            continue
        use_ply = fmt == "ply" or (fmt == "mixed" and i % 2 == 1)
        (write_ply if use_ply else write_pcd)(scans / f"scan_{i}.{'ply' if use_ply else 'pcd'}", fields)
    poses_file = folder / "poses.txt"
    poses_file.write_text(format_kitti_poses(np.array(ref)))
    times_file = folder / "times.txt"
    times_file.write_text("".join(f"{100.0 + t:.6f}\n" for t in times[:n_scans] + (SWEEP_S if sweep else 0.0)))
    return scans, poses_file, times_file
