"""The partition's fast paths against the plain code they replace: the fused projection kernel
against CameraModel.project, the cropped capture masks against the full ones, the cost-ordered
warp lookup against the bitmap rule (highest cost wins, the lower index among equal costs), and
the label memory read through the partition's voxel keys against LabelMemory.read."""
from __future__ import annotations

import math

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from calibration.camera_model import CameraModel
from runtime.vpp.homography.lookup import mask_crops, warp_lookup
from runtime.vpp.homography.plane import Plane
from hil_sim.bench.vpp import synthetic_frame
from runtime.vpp.partition.partitioner import PointPartitioner
from runtime.vpp.partition.projection import project_fused, transform

W, H = 160, 120

#: Distortion vectors of every length the fused kernel implements (0, 4, 5, 8, 12).
distortions = st.one_of(
    st.just(np.zeros(0)),
    st.lists(st.floats(-0.3, 0.3), min_size=4, max_size=4).map(lambda d: np.array(d) * [1, 1, 0.02, 0.02]),
    st.lists(st.floats(-0.3, 0.3), min_size=5, max_size=5).map(lambda d: np.array(d) * [1, 1, 0.02, 0.02, 0.5]),
    st.lists(st.floats(-0.3, 0.3), min_size=8, max_size=8).map(
        lambda d: np.array(d) * [1, 1, 0.02, 0.02, 0.5, 0.5, 0.5, 0.5]),
    st.lists(st.floats(-0.3, 0.3), min_size=12, max_size=12).map(
        lambda d: np.array(d) * [1, 1, 0.02, 0.02, 0.5, 0.5, 0.5, 0.5, 0.02, 0.02, 0.02, 0.02]),
)


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), dist=distortions, f=st.floats(60.0, 300.0), skew=st.sampled_from([0.0, 0.7]),
       rot=st.tuples(st.floats(-3.2, 3.2), st.floats(-3.2, 3.2), st.floats(-3.2, 3.2)),
       dtype=st.sampled_from([np.float32, np.float64]))
def test_fused_projection_is_project_bit_for_bit(seed, dist, f, skew, rot, dtype):
    rng = np.random.default_rng(seed)
    K = np.array([[f, skew, (W - 1) / 2 + rng.uniform(-5, 5)], [0.0, f * rng.uniform(0.9, 1.1), (H - 1) / 2], [0, 0, 1]])
    cam = CameraModel(K, dist, W, H)
    T = np.eye(4)
    T[:3, :3] = cv2.Rodrigues(np.array(rot))[0]
    T[:3, 3] = rng.uniform(-0.5, 0.5, 3)
    # points all around (a 360-degree scan: half behind the camera), some near the image border,
    # some on the camera plane (z ~ 0) and some exactly at z = 0 in the camera frame
    p = rng.normal(0.0, 3.0, (3000, 3))
    p[:5] = 0.0
    p = p.astype(dtype)
    uv, valid = project_fused(p, T, cam)
    p_cam = transform(np.ascontiguousarray(p), T)
    ref_uv, ref_valid = cam.project(p_cam)
    np.testing.assert_array_equal(valid, ref_valid)
    assert valid.any()
    np.testing.assert_array_equal(uv[valid], ref_uv[valid])  # bit for bit, not allclose


def test_fused_projection_refuses_the_tilted_model():
    cam = CameraModel(np.array([[100.0, 0, 79.5], [0, 100.0, 59.5], [0, 0, 1]]), np.zeros(14), W, H)
    with pytest.raises(ValueError, match="camera"):
        project_fused(np.zeros((3, 3)), np.eye(4), cam)


def _masks(rng, n):
    m = np.zeros((n, H, W), bool)
    for k in range(n):
        for _ in range(int(rng.integers(1, 3))):
            c = (int(rng.integers(10, W - 10)), int(rng.integers(10, H - 10)))
            cv2.ellipse(m[k].view(np.uint8), c, (int(rng.integers(3, 40)), int(rng.integers(3, 30))),
                        float(rng.uniform(0, 180)), 0, 360, 1, -1)
    return m


def test_mask_crops_hold_every_mask_bit():
    rng = np.random.default_rng(3)
    m = _masks(rng, 5)
    m[2] = False  # an empty mask: an empty box
    m[4, 0, 0] = m[4, H - 1, W - 1] = True  # a mask that spans the image
    crop, start, box = mask_crops(m)
    assert crop.dtype == np.bool_ and crop.shape[0] == start[-1] + 1
    for e in range(len(m)):
        u0, v0, u1, v1 = box[e]
        if not m[e].any():
            assert u0 > u1 and start[e + 1] == start[e]
            continue
        full = np.zeros((H, W), bool)
        full[v0:v1 + 1, u0:u1 + 1] = crop[start[e]:start[e + 1]].reshape(v1 - v0 + 1, u1 - u0 + 1)
        np.testing.assert_array_equal(full, m[e])


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), dist=st.sampled_from([0, 1, 2]),
       motion=st.tuples(st.floats(-0.1, 0.1), st.floats(-0.2, 0.2), st.floats(-0.3, 0.3), st.floats(-0.3, 0.5)))
def test_cropped_lookup_is_the_full_mask_lookup(seed, dist, motion):
    d = [np.zeros(0), np.array([-0.12, 0.03, 0.001, -0.0015, 0.0]),
         np.array([-0.1, 0.02, 0.0005, 0.0005, 0.0, 0.01, 0.0, 0.0])][dist]
    cam = CameraModel(np.array([[130.0, 0, 79.5], [0, 130.0, 59.5], [0, 0, 1]]), d, W, H)
    rng = np.random.default_rng(seed)
    m = _masks(rng, 3)
    T_cur = np.eye(4)
    T_cur[:3, :3] = cv2.Rodrigues(np.array([0.0, motion[0], 0.0]))[0]
    T_cur[:3, 3] = motion[1:]
    planes = [Plane(np.array([0.0, 0.0, 1.0]), 2.0), None, Plane(np.array([0.0, 0.6, 0.8]), 1.5)]
    lk = warp_lookup(cam, m, np.stack([np.eye(4)] * 3), planes, T_cur)
    for k in range(3):
        np.testing.assert_array_equal(lk.render(k), lk.render(k, full=True))


@pytest.mark.parametrize("costs", [(2.0, 5.0, 5.0, 1.0), (3.0, 3.0, 3.0, 3.0), (7.0, 1.0, 7.0, 0.0)])
def test_warp_lookup_picks_as_the_bitmaps_do(costs):
    """Overlapping warped masks with ties in cost: the cost-ordered lookup (first hit wins) labels
    every point as the bitmap path's rule (highest cost wins, the lower index among equals) does
    on the rendered warps."""
    pts, T, cam, _, _, _, T_base = synthetic_frame(20000, 4, seed=2)
    rng = np.random.default_rng(0)
    masks = np.zeros((4, cam.height_px, cam.width_px), bool)
    for k in range(4):  # big overlapping rectangles over the boxes
        u0 = int(rng.integers(100, 300))
        masks[k, 150:350, u0:u0 + 250] = True
    T_cur = np.eye(4)
    T_cur[:3, 3] = (0.03, -0.01, 0.2)
    planes = [Plane(np.array([0.0, 0.0, 1.0]), 1.8 + 0.1 * k) for k in range(4)]
    lk = warp_lookup(cam, masks, np.stack([np.eye(4)] * 4), planes, T_cur)
    rendered = np.stack([lk.render(k) for k in range(4)])
    ids = np.arange(4)
    part = PointPartitioner()
    a = part.partition(pts, T, cam, lk, ids, costs, T_base_lidar=T_base)
    b = part.partition(pts, T, cam, rendered, ids, costs, T_base_lidar=T_base)
    assert a.movable.sum() > 1000
    for f in ("label", "object_id", "cost", "in_view"):
        np.testing.assert_array_equal(getattr(a, f), getattr(b, f))
    assert (a.n_outliers_removed, a.n_completed) == (b.n_outliers_removed, b.n_completed)


def test_partition_memory_reads_what_label_memory_reads():
    """The partition reads and writes the label memory through the voxel keys of its projection
    pass: unseen points get what LabelMemory.read gives for them."""
    pts, T, cam, masks, ids, costs, T_base = synthetic_frame(20000, 4, seed=1)
    part = PointPartitioner()
    T_odom = np.eye(4)
    part.partition(pts, T, cam, masks, ids, costs, T_base_lidar=T_base, T_odom_lidar=T_odom, stamp_s=0.0)
    # turn around: what was in view is now behind the camera, and read from the memory
    T_odom2 = np.eye(4)
    T_odom2[:3, :3] = cv2.Rodrigues(np.array([0.0, 0.0, math.pi]))[0]
    pts2 = transform(np.ascontiguousarray(pts), np.linalg.inv(T_odom2) @ T_odom).astype(np.float32)
    expect = part.memory.read(transform(pts2, T_odom2), np.ones(len(pts2), bool), 0.5)
    r = part.partition(pts2, T, cam, [], [], [], T_base_lidar=T_base, T_odom_lidar=T_odom2, stamp_s=0.5)
    unseen = ~r.in_view & (r.label != -1)
    assert r.from_memory.sum() > 1000
    np.testing.assert_array_equal(r.from_memory[unseen], expect[0][unseen])
    found = unseen & expect[0]
    np.testing.assert_array_equal(r.label[found], expect[1][found])
    np.testing.assert_array_equal(r.object_id[found], expect[2][found])
    np.testing.assert_array_equal(r.cost[found], expect[3][found])
