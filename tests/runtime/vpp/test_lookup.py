"""The per-pixel warp (homography.WarpLookup) the stage uses per scan, against the full-image warp
(MaskWarper) it replaces there: same pixels (exactly against the exact map, up to the border
against the default interpolated one), a box that holds the warp, the area the growth test
reads, the same partition, and the stage's tracking against its previous implementation."""
from __future__ import annotations

import math

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from calibration.camera_model import CameraModel
from runtime.vpp.homography.image_warp import MaskWarper
from runtime.vpp.homography.lookup import AREA_SAMPLES, warp_lookup
from runtime.vpp.homography.plane import Plane, relative_motion
from hil_sim.bench.vpp import synthetic_frame
from runtime.vpp.partition.partitioner import PointPartitioner
from runtime.vpp.config import VppConfig
from runtime.vpp.stage import pose_matrix

W, H = 320, 240
K = np.array([[260.0, 0.0, 159.5], [0.0, 260.0, 119.5], [0.0, 0.0, 1.0]])
CAMERAS = {
    "pinhole": CameraModel(K, np.zeros(0), W, H),
    "distorted": CameraModel(K, np.array([-0.12, 0.03, 0.001, -0.0015, 0.0]), W, H),
    "rational": CameraModel(K, np.array([-0.1, 0.02, 0.0005, 0.0005, 0.0, 0.01, 0.0, 0.0]), W, H),
}


def rot(rx: float, ry: float, rz: float) -> np.ndarray:
    return cv2.Rodrigues(np.array([rx, ry, rz]))[0]


def pose(R: np.ndarray, t) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, t
    return T


def random_mask(rng: np.random.Generator) -> np.ndarray:
    """A few ellipses and rectangles (one object's sloppy mask, possibly in pieces, with holes)."""
    m = np.zeros((H, W), np.uint8)
    for _ in range(int(rng.integers(1, 4))):
        c = (int(rng.integers(20, W - 20)), int(rng.integers(20, H - 20)))
        if rng.random() < 0.5:
            cv2.ellipse(m, c, (int(rng.integers(3, 60)), int(rng.integers(3, 60))), float(rng.uniform(0, 180)), 0, 360,
                        1, -1)
        else:
            cv2.rectangle(m, c, (c[0] + int(rng.integers(2, 80)), c[1] + int(rng.integers(2, 80))), 1, -1)
    if rng.random() < 0.3:
        cv2.circle(m, (int(rng.integers(0, W)), int(rng.integers(0, H))), int(rng.integers(2, 15)), 0, -1)
    return m.astype(bool)


def border(mask: np.ndarray, px: int = 1) -> np.ndarray:
    """Pixels within px of the mask's edge (dilation minus erosion)."""
    k = np.ones((2 * px + 1, 2 * px + 1), np.uint8)
    m = mask.astype(np.uint8)
    return (cv2.dilate(m, k) - cv2.erode(m, k)).astype(bool)


motions = st.tuples(
    st.floats(-0.15, 0.15), st.floats(-0.25, 0.25), st.floats(-0.1, 0.1),  # rotation (rad)
    st.floats(-0.4, 0.4), st.floats(-0.2, 0.2), st.floats(-0.6, 0.6),  # translation (m)
)


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), motion=motions, camera=st.sampled_from(sorted(CAMERAS)),
       plane=st.one_of(st.none(), st.tuples(st.floats(-0.5, 0.5), st.floats(-0.5, 0.5), st.floats(0.8, 6.0))))
def test_lookup_is_the_full_image_warp_at_every_pixel(seed, motion, camera, plane):
    cam = CAMERAS[camera]
    rng = np.random.default_rng(seed)
    mask = random_mask(rng)
    R, t = rot(*motion[:3]), np.array(motion[3:])
    pl = None
    if plane is not None:
        n = np.array([plane[0], plane[1], 1.0])
        pl = Plane(n / np.linalg.norm(n), plane[2])
    T_cap = pose(rot(0.01, -0.02, 0.0), (0.1, 0.0, -0.2))
    T_cur = T_cap @ np.linalg.inv(pose(R, t))  # X_cur = R X_cap + t
    Rm, tm = relative_motion(T_cap, T_cur)
    exact = MaskWarper(cam, map_step_px=1).warp(mask, Rm, tm, pl)
    grid = MaskWarper(cam).warp(mask, Rm, tm, pl)  # the default the stage used per scan before
    lk = warp_lookup(cam, mask[None], T_cap[None], [pl], T_cur)
    got = lk.render(0)
    # the exact map: the same pixels but for rounding ties (a source exactly between two pixels)
    assert np.count_nonzero(got != exact) <= max(2, 0.001 * max(exact.sum(), 1))
    # the interpolated map: >= 99% agreement, differences on the border only
    diff = got != grid
    union = max(int((got | grid).sum()), 1)
    assert diff.sum() <= max(5, 0.01 * union)
    assert not (diff & ~border(grid, 2)).any() or diff.sum() <= 5
    # the box holds every warped pixel; the area is exact for a small box, close for a big one
    u0, v0, u1, v1 = lk.box[0]
    vs, us = np.nonzero(exact)
    if us.size:
        assert u0 <= us.min() and us.max() <= u1 and v0 <= vs.min() and vs.max() <= v1
        if (u1 - u0 + 1) * (v1 - v0 + 1) <= AREA_SAMPLES:
            assert lk.area_px[0] == got.sum()
        else:
            perimeter = border(got, 1).sum()  # the grid estimate errs by at most a stride on the border
            stride = math.ceil(math.sqrt((u1 - u0 + 1) * (v1 - v0 + 1) / AREA_SAMPLES))
            assert abs(lk.area_px[0] - got.sum()) <= 0.1 * got.sum() + stride * perimeter
    else:
        assert lk.area_px[0] == 0


def test_area_is_counted_only_where_asked():
    """The warp of every mask is set up; the warped area only of the masks asked for (the stage
    asks for those the tracker did not follow), NaN for the others."""
    cam = CAMERAS["distorted"]
    masks = np.zeros((2, H, W), bool)
    masks[0, 100:140, 140:180] = True
    masks[1, 200:260, 300:330] = True
    planes = [Plane(np.array([0.0, 0.0, 1.0]), 2.0)] * 2
    T_cur = pose(np.eye(3), (0.05, 0.0, 0.1))
    every = warp_lookup(cam, masks, np.stack([np.eye(4)] * 2), planes, T_cur)
    from runtime.vpp.homography.lookup import WarpSource, mask_outline

    src = WarpSource(cam, masks, [mask_outline(cam, m) for m in masks], np.stack([np.eye(4)] * 2), planes)
    some = src.at(T_cur, area_of=np.array([False, True]))
    assert np.isnan(some.area_px[0]) and some.area_px[1] == every.area_px[1] > 0
    np.testing.assert_array_equal(some.box, every.box)
    np.testing.assert_array_equal(some.Hinv, every.Hinv)
    assert (some.render(0) == every.render(0)).all() and some.render(0).any()


def test_camera_behind_the_plane_gives_nothing():
    cam = CAMERAS["distorted"]
    mask = np.zeros((H, W), bool)
    mask[100:140, 140:180] = True
    pl = Plane(np.array([0.0, 0.0, 1.0]), 1.0)
    T_cur = pose(np.eye(3), (0.0, 0.0, 1.5))  # 1.5 m forward: past the plane at 1 m
    lk = warp_lookup(cam, mask[None], np.eye(4)[None], [pl], T_cur)
    assert lk.area_px[0] == 0 and lk.box[0, 0] > lk.box[0, 2] and not lk.render(0).any()
    assert not MaskWarper(cam).warp(mask, *relative_motion(np.eye(4), T_cur), pl).any()


def _scene(pose_xyyaw, pts, T_base):
    """The synthetic scene (fixed in the odom frame) seen from a robot pose: lidar points, T_odom_lidar."""
    T_odom_lidar = pose_matrix(*pose_xyyaw) @ T_base
    world = pts.astype(np.float64) @ T_base[:3, :3].T + T_base[:3, 3]
    p = (world - T_odom_lidar[:3, 3]) @ T_odom_lidar[:3, :3]
    return p.astype(np.float32), T_odom_lidar


def test_partition_through_the_lookup_equals_the_partition_of_warped_images():
    pts, T_cam_lidar, cam, masks, ids, costs, T_base = synthetic_frame(6000, 6, seed=3)
    T_base_cam = T_base @ np.linalg.inv(T_cam_lidar)
    from runtime.vpp.homography.plane import estimate_plane

    p_cam0 = pts.astype(np.float64) @ T_cam_lidar[:3, :3].T + T_cam_lidar[:3, 3]
    planes = [estimate_plane(cam, m, p_cam0) for m in masks]
    assert all(p is not None for p in planes)
    exact, grid = MaskWarper(cam, map_step_px=1), MaskWarper(cam)
    a, b, g = PointPartitioner(), PointPartitioner(), PointPartitioner()
    for xyyaw in [(0.0, 0.0, 0.0), (0.2, 0.1, 0.05), (-0.25, -0.1, -0.08), (0.3, 0.15, 0.1)]:
        p, T_odom_lidar = _scene(xyyaw, pts, T_base)
        T_cur = pose_matrix(*xyyaw) @ T_base_cam
        lk = warp_lookup(cam, masks, np.stack([T_base_cam] * len(masks)), planes, T_cur)
        R, t = relative_motion(T_base_cam, T_cur)
        kw = dict(T_base_lidar=T_base, T_odom_lidar=T_odom_lidar, stamp_s=0.0)
        want = a.partition(p, T_cam_lidar, cam, np.stack([exact.warp(m, R, t, pl) for m, pl in zip(masks, planes)]),
                           ids, costs, **kw)
        got = b.partition(p, T_cam_lidar, cam, lk, ids, costs, **kw)
        assert np.array_equal(got.label, want.label) and np.array_equal(got.object_id, want.object_id)
        assert (got.n_outliers_removed, got.n_completed) == (want.n_outliers_removed, want.n_completed)
        assert got.movable.sum() > 100
        old = g.partition(p, T_cam_lidar, cam, np.stack([grid.warp(m, R, t, pl) for m, pl in zip(masks, planes)]),
                          ids, costs, **kw)
        assert (old.label == got.label).mean() >= 0.99


def test_completion_near_mask_through_the_lookup():
    """A point beside its object, outside the mask but within completion_dilate_px of it, joins
    the object through the lookup as it does through the warped image."""
    cam = CAMERAS["distorted"]
    z = 2.0
    ys, xs = np.meshgrid(np.linspace(-0.2, 0.2, 21), np.linspace(-0.3, 0.3, 31))
    pts = np.c_[xs.ravel(), ys.ravel(), np.full(xs.size, z)]
    uv, _ = cam.project(pts)
    mask = np.zeros((H, W), bool)
    inner = uv[:, 0] < np.percentile(uv[:, 0], 80)  # the mask misses the rightmost fifth of the face
    u0, v0 = np.floor(uv[inner].min(0)).astype(int)
    u1, v1 = np.ceil(uv[inner].max(0)).astype(int)
    mask[v0:v1 + 1, u0:u1 + 1] = True
    pl = Plane(np.array([0.0, 0.0, 1.0]), z)
    lk = warp_lookup(cam, mask[None], np.eye(4)[None], [pl], np.eye(4))
    img = MaskWarper(cam, map_step_px=1).warp(mask, np.eye(3), np.zeros(3), pl)
    a = PointPartitioner().partition(pts, np.eye(4), cam, img[None], [0], [2.0])
    b = PointPartitioner().partition(pts, np.eye(4), cam, lk, [0], [2.0])
    assert a.n_completed > 0 and np.array_equal(a.label, b.label) and a.n_completed == b.n_completed


@pytest.mark.xfail(strict=True, reason="known defect kept: the completion reads warped masks' crops from the cell "
                   "runs' starts (docs/decisions/vpp-completion-crop-offsets.md); the fix waits for masks "
                   "that stop at the object")
def test_completion_through_the_lookup_reads_each_masks_own_crop():
    """Two objects: the first mask only the outline of its face (its crop mostly empty), the
    second mask missing the rightmost fifth of its face. The completion of the second one reads
    the second mask's crop (from its own start in the flat crop array, not another mask's
    bits), so that the lookup path completes exactly as the warped images do."""
    cam = CAMERAS["distorted"]
    z = 2.0
    masks, faces = [], []
    for x0 in (-0.45, 0.35):
        ys, xs = np.meshgrid(np.linspace(-0.2, 0.2, 21), np.linspace(x0 - 0.15, x0 + 0.15, 16))
        face = np.c_[xs.ravel(), ys.ravel(), np.full(xs.size, z)]
        uv, _ = cam.project(face)
        inner = uv[:, 0] < np.percentile(uv[:, 0], 80)
        u0, v0 = np.floor(uv[inner].min(0)).astype(int)
        u1, v1 = np.ceil(uv[inner].max(0)).astype(int)
        mask = np.zeros((H, W), bool)
        mask[v0:v1 + 1, u0:u1 + 1] = True
        if not masks:  # the first: its outline only
            mask[v0 + 2:v1 - 1, u0 + 2:u1 - 1] = False
        masks.append(mask)
        faces.append(face)
    pts = np.concatenate(faces)
    pl = Plane(np.array([0.0, 0.0, 1.0]), z)
    lk = warp_lookup(cam, np.stack(masks), np.stack([np.eye(4)] * 2), [pl, pl], np.eye(4))
    img = np.stack([MaskWarper(cam, map_step_px=1).warp(m, np.eye(3), np.zeros(3), pl) for m in masks])
    a = PointPartitioner().partition(pts, np.eye(4), cam, img, [0, 1], [2.0, 2.0])
    b = PointPartitioner().partition(pts, np.eye(4), cam, lk, [0, 1], [2.0, 2.0])
    second = np.arange(len(pts)) >= len(faces[0])
    assert (a.object_id[second] == 1).sum() > (second.sum() * 0.8)  # the completion filled the second face
    assert a.n_completed > 0 and np.array_equal(a.label, b.label) and np.array_equal(a.object_id, b.object_id)


# ----------------------------------------------------------------------------- tracking
def test_a_camera_the_lookup_does_not_model_gets_full_image_warps():
    """The 14-coefficient (tilted) model stays with cv2: the stage warps images for it."""
    from models.vlm.interface import DetectedObject, VlmAnswer
    from runtime.common.sensor_data import LidarScan
    from runtime.vpp.stage import VppStage

    class _Runner:
        busy = True  # never asked: the memory is filled by hand

        def poll(self, now_s):
            return []

        def close(self):
            pass

    tilted = CameraModel(K, np.r_[CAMERAS["distorted"].dist, np.zeros(9)], W, H)
    stage = VppStage(VppConfig(), tilted, np.eye(4), np.eye(4), _Runner())
    assert not stage._per_pixel and VppStage(VppConfig(), CAMERAS["distorted"], np.eye(4), np.eye(4), _Runner())._per_pixel
    ys, xs = np.meshgrid(np.linspace(-0.2, 0.2, 15), np.linspace(-0.2, 0.2, 15))
    face = np.c_[xs.ravel(), ys.ravel(), np.full(xs.size, 2.0)]
    uv, _ = tilted.project(face)
    mask = np.zeros((H, W), bool)
    u0, v0 = np.floor(uv.min(0)).astype(int) - 2
    u1, v1 = np.ceil(uv.max(0)).astype(int) + 2
    mask[v0:v1 + 1, u0:u1 + 1] = True
    stage.memory.reconcile(VlmAnswer(0.0, np.eye(4), (DetectedObject(mask, "box", True, 2.0, 0.9),), "t", 0.0),
                           points_cam=face, now_s=0.0)
    scan = LidarScan(stamp_s=0.1, points_m=face.astype(np.float32), point_time_offsets_s=np.zeros(len(face), np.float32),
                     frame_duration_s=0.1)
    frame = stage.update(0.1, (0.0, 0.0, 0.0), None, scan)  # camera = base = lidar, at the capture pose
    assert frame.masks_used == 1 and frame.movable_count == len(face)


def test_lookup_names_a_bad_camera_pose():
    import pytest

    from runtime.vpp.mask_memory import MaskMemory, MaskMemoryError

    mem = MaskMemory(CAMERAS["distorted"])
    assert mem.lookup(0.0, np.eye(4))[0] == []
    for bad, why in ((np.eye(3), "4x4"), (np.diag([1.0, 1.0, -1.0, 1.0]), "proper rotation"),
                     (np.r_[np.eye(4)[:3], [[0.5, 0.0, 0.0, 1.0]]], "last row"), (np.full((4, 4), np.nan), "finite")):
        with pytest.raises(MaskMemoryError, match=why):
            mem.lookup(0.0, bad)
