"""VPP Phase I (homography warp) and Phase II (IoU reconciliation), the trigger rule, age-out.

The geometry tests render a box face (a rectangle on a plane) directly at two camera poses, by
casting every pixel's ray, and compare the mask warped from the first pose with the mask
rendered at the second: the plane-induced homography must reproduce it, the rotation-only one
must not under translation and must under pure rotation.
"""
from __future__ import annotations

import math

import cv2
import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from calibration.camera_model import CameraModel
from models.vlm.interface import DetectedObject, VlmAnswer
from runtime.vpp.homography.image_warp import MaskWarper
from runtime.vpp.homography.plane import (HomographyError, Plane, estimate_plane, plane_homography, relative_motion,
                                          rotation_homography)
from runtime.vpp.mask_memory import MaskMemory, MaskMemoryConfig, MaskMemoryError, iou_matrix, query_due

W, H = 640, 480
K = np.array([[500.0, 0.0, 319.5], [0.0, 500.0, 239.5], [0.0, 0.0, 1.0]])
PINHOLE = CameraModel(K, np.zeros(0), W, H)
DISTORTED = CameraModel(K, np.array([-0.12, 0.03, 0.001, -0.0015, 0.0]), W, H)


def rot_y(a: float) -> np.ndarray:
    """Rotation about the camera's y axis (down): a robot yaw of -a."""
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def rot_x(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def pose(R=np.eye(3), t=(0.0, 0.0, 0.0)) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = t
    return T


def pixel_rays(camera: CameraModel) -> np.ndarray:
    """(H*W, 3) normalized rays of the raw pixels (undistorted when the camera distorts)."""
    u, v = np.meshgrid(np.arange(camera.width_px, dtype=float), np.arange(camera.height_px, dtype=float))
    px = np.stack([u.ravel(), v.ravel()], axis=1)
    if np.any(camera.dist):
        crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-12)
        xy = cv2.undistortPoints(px.reshape(-1, 1, 2), camera.K, camera.dist, None, None, None, crit).reshape(-1, 2)
    else:
        xy = (px - camera.K[:2, 2]) / np.diag(camera.K)[:2]
    return np.concatenate([xy, np.ones((len(xy), 1))], axis=1)


class Face:
    """A rectangle in the odom frame: centre c, in-plane unit axes a and b, half sizes."""

    def __init__(self, c, a, b, ha, hb):
        self.c, self.a, self.b = np.asarray(c, float), np.asarray(a, float), np.asarray(b, float)
        self.ha, self.hb = ha, hb
        self.n = np.cross(self.a, self.b)

    def render(self, camera: CameraModel, T_odom_cam: np.ndarray) -> np.ndarray:
        d = pixel_rays(camera) @ T_odom_cam[:3, :3].T
        o = T_odom_cam[:3, 3]
        denom = d @ self.n
        with np.errstate(divide="ignore", invalid="ignore"):
            s = ((self.c - o) @ self.n) / denom
        p = o + s[:, None] * d - self.c
        inside = (s > 0) & (np.abs(p @ self.a) <= self.ha) & (np.abs(p @ self.b) <= self.hb)
        return inside.reshape(camera.height_px, camera.width_px)

    def plane_in(self, T_odom_cam: np.ndarray) -> Plane:
        """The face's plane n^T X = d in the given camera's frame."""
        R, o = T_odom_cam[:3, :3], T_odom_cam[:3, 3]
        n = R.T @ self.n
        d = float(n @ (R.T @ (self.c - o)))
        return Plane(n, d) if d > 0 else Plane(-n, -d)

    def sample(self, n_a: int, n_b: int) -> np.ndarray:
        ga, gb = np.meshgrid(np.linspace(-self.ha, self.ha, n_a), np.linspace(-self.hb, self.hb, n_b))
        return self.c + ga.reshape(-1, 1) * self.a + gb.reshape(-1, 1) * self.b


def iou(a: np.ndarray, b: np.ndarray) -> float:
    return float(iou_matrix(a[None], b[None])[0, 0])


FRONT = Face((0.0, 0.0, 2.0), (1, 0, 0), (0, 1, 0), 0.3, 0.25)  # a box face 2 m ahead
SLANT = Face((0.2, 0.1, 2.0), rot_y(0.5) @ [1, 0, 0], (0, 1, 0), 0.3, 0.25)  # turned ~29 deg


def motion(kind: str, dist: float) -> np.ndarray:
    """Current camera pose (odom = capture camera frame) after a motion of `dist` metres."""
    if kind == "forward":
        return pose(t=(0.0, 0.0, dist))
    if kind == "sideways":  # with a yaw that keeps the face in view
        return pose(rot_y(-math.atan2(dist, 2.0) * 0.7), (dist, 0.0, 0.0))
    if kind == "diagonal":
        return pose(rot_y(math.radians(8.0)), (-0.6 * dist, 0.02, 0.8 * dist))
    raise AssertionError(kind)


# ---------------------------------------------------------------- Phase I geometry
@pytest.mark.parametrize("camera", [PINHOLE, DISTORTED], ids=["pinhole", "distorted"])
@pytest.mark.parametrize("face", [FRONT, SLANT], ids=["front", "slanted"])
@pytest.mark.parametrize("kind", ["forward", "sideways", "diagonal"])
@pytest.mark.parametrize("dist", [0.25, 0.5, 1.0])
def test_plane_warp_matches_direct_render_and_beats_rotation_only(camera, face, kind, dist):
    T_cap, T_cur = np.eye(4), motion(kind, dist)
    capture, truth = face.render(camera, T_cap), face.render(camera, T_cur)
    assert capture.sum() > 5000 and truth.sum() > 5000
    warper = MaskWarper(camera)
    R, t = relative_motion(T_cap, T_cur)
    by_plane = warper.warp(capture, R, t, face.plane_in(T_cap))
    by_rotation = warper.warp(capture, R, t, None)
    iou_plane, iou_rot = iou(by_plane, truth), iou(by_rotation, truth)
    assert iou_plane >= 0.95, (iou_plane, iou_rot)
    assert iou_rot < iou_plane - 0.05, (iou_plane, iou_rot)


@pytest.mark.parametrize("camera", [PINHOLE, DISTORTED], ids=["pinhole", "distorted"])
def test_rotation_only_is_exact_under_pure_rotation(camera):
    T_cur = pose(rot_y(math.radians(12.0)) @ rot_x(math.radians(4.0)))
    capture, truth = FRONT.render(camera, np.eye(4)), FRONT.render(camera, T_cur)
    R, t = relative_motion(np.eye(4), T_cur)
    assert np.allclose(t, 0.0)
    warper = MaskWarper(camera)
    assert iou(warper.warp(capture, R, t, None), truth) >= 0.99
    assert iou(warper.warp(capture, R, t, FRONT.plane_in(np.eye(4))), truth) >= 0.99


def test_warp_from_a_moved_capture_pose_uses_the_relative_motion():
    """Both poses away from the odom origin: only their relative motion matters."""
    T0 = pose(rot_y(0.3), (1.0, 0.0, -2.0))
    face = Face(T0[:3, :3] @ [0.0, 0.0, 2.5] + T0[:3, 3], T0[:3, :3] @ [1, 0, 0], T0[:3, :3] @ [0, 1, 0], 0.3, 0.3)
    T1 = T0 @ motion("diagonal", 0.5)
    R, t = relative_motion(T0, T1)
    out = MaskWarper(PINHOLE).warp(face.render(PINHOLE, T0), R, t, face.plane_in(T0))
    assert iou(out, face.render(PINHOLE, T1)) >= 0.95


@pytest.mark.parametrize("camera", [PINHOLE, DISTORTED], ids=["pinhole", "distorted"])
def test_camera_behind_the_plane_gives_an_empty_mask(camera):
    capture = FRONT.render(camera, np.eye(4))
    R, t = relative_motion(np.eye(4), pose(t=(0.0, 0.0, 2.5)))  # walked through the face
    assert not MaskWarper(camera).warp(capture, R, t, FRONT.plane_in(np.eye(4))).any()


@pytest.mark.parametrize("camera", [PINHOLE, DISTORTED], ids=["pinhole", "distorted"])
def test_rotation_only_does_not_mirror_points_from_behind_the_camera(camera):
    """Turned around: the face is behind the camera; a bare homography would paint it."""
    capture = FRONT.render(camera, np.eye(4))
    R, t = relative_motion(np.eye(4), pose(rot_y(math.radians(180.0))))
    assert not MaskWarper(camera).warp(capture, R, t, None).any()
    capture = FRONT.render(PINHOLE, np.eye(4))
    H_bare = cv2.warpPerspective(capture.view(np.uint8), rotation_homography(K, R), (W, H), flags=cv2.INTER_NEAREST)
    assert H_bare.any()  # what the half-plane check removes


# ---------------------------------------------------------------- properties
def _rotation(rx, ry, rz):
    return cv2.Rodrigues(np.array([rx, ry, rz]))[0]


angles = st.floats(-0.5, 0.5)


SMALL_K = np.array([[60.0, 0, 31.5], [0, 60.0, 23.5], [0, 0, 1]])
SMALL = {"pinhole": MaskWarper(CameraModel(SMALL_K, np.zeros(0), 64, 48)),
         "distorted": MaskWarper(CameraModel(SMALL_K, np.array([-0.1, 0.02, 0.001, 0.0]), 64, 48))}


@settings(max_examples=60, deadline=None)
@given(mask_seed=st.integers(0, 2**32 - 1), n=st.floats(-0.5, 0.5), d=st.floats(0.3, 20.0),
       with_plane=st.booleans(), camera=st.sampled_from(sorted(SMALL)))
def test_identity_motion_returns_the_same_mask(mask_seed, n, d, with_plane, camera):
    mask = np.random.default_rng(mask_seed).random((48, 64)) < 0.3
    normal = np.array([n, -0.5 * n, 1.0])
    plane = Plane(normal / np.linalg.norm(normal), d) if with_plane else None
    out = SMALL[camera].warp(mask, np.eye(3), np.zeros(3), plane)
    assert np.array_equal(out, mask)


def test_coarse_distortion_map_agrees_with_the_exact_one():
    T1 = motion("diagonal", 1.0)
    R, t = relative_motion(np.eye(4), T1)
    cap = SLANT.render(DISTORTED, np.eye(4))
    exact = MaskWarper(DISTORTED, map_step_px=1).warp(cap, R, t, SLANT.plane_in(np.eye(4)))
    coarse = MaskWarper(DISTORTED, map_step_px=8).warp(cap, R, t, SLANT.plane_in(np.eye(4)))
    assert iou(exact, coarse) >= 0.995
    with pytest.raises(HomographyError, match="map_step_px"):
        MaskWarper(DISTORTED, map_step_px=0)


@settings(max_examples=60, deadline=None)
@given(rx=angles, ry=angles, rz=angles, nx=st.floats(-1, 1), ny=st.floats(-1, 1), d=st.floats(0.1, 50.0))
def test_pure_rotation_homography_does_not_depend_on_the_plane(rx, ry, rz, nx, ny, d):
    R = _rotation(rx, ry, rz)
    n = np.array([nx, ny, 1.0])
    Hp = plane_homography(K, R, np.zeros(3), Plane(n / np.linalg.norm(n), d))
    assert np.allclose(Hp, rotation_homography(K, R), atol=1e-9)


@settings(max_examples=60, deadline=None)
@given(rx=angles, ry=angles, rz=angles, t=st.lists(st.floats(-1.0, 1.0), min_size=3, max_size=3),
       nx=st.floats(-0.6, 0.6), ny=st.floats(-0.6, 0.6), d=st.floats(1.0, 10.0),
       a=st.floats(-0.3, 0.3), b=st.floats(-0.3, 0.3))
def test_plane_homography_maps_a_plane_point_to_its_projection(rx, ry, rz, t, nx, ny, d, a, b):
    """Pins the sign: X on n^T X = d, x_cur ~ K (R X + t) equals H x_cap."""
    R, t = _rotation(rx, ry, rz), np.asarray(t)
    n = np.array([nx, ny, 1.0])
    n /= np.linalg.norm(n)
    ray = np.array([a, b, 1.0])
    X = ray * d / (n @ ray)  # the ray's point on the plane
    Xc = R @ X + t
    assume(Xc[2] > 1e-3)  # a point at (or behind) the current camera has no projection to compare
    Hx = plane_homography(K, R, t, Plane(n, d)) @ (K @ X)
    assert np.allclose(Hx / Hx[2], (K @ Xc) / (K @ Xc)[2], atol=1e-6 * max(1.0, abs(Xc[2]) ** -1))


# ---------------------------------------------------------------- plane estimate
def _scene_points(face: Face, rng) -> np.ndarray:
    on_face = face.sample(25, 20) + rng.normal(0.0, 0.005, (500, 3))
    wall = np.stack(np.meshgrid(np.linspace(-3, 3, 60), np.linspace(-1, 1, 20), [5.0]), -1).reshape(-1, 3)
    return np.concatenate([on_face, wall])


@pytest.mark.parametrize("face", [FRONT, SLANT], ids=["front", "slanted"])
def test_plane_estimate_from_lidar_points_in_the_mask(face):
    rng = np.random.default_rng(1)
    pts = _scene_points(face, rng)
    mask = face.render(PINHOLE, np.eye(4))
    mask = cv2.dilate(mask.view(np.uint8), np.ones((9, 9), np.uint8)).view(bool)  # edges bleed onto the wall
    truth = face.plane_in(np.eye(4))
    p = estimate_plane(PINHOLE, mask, pts)
    assert p is not None
    assert float(p.normal @ truth.normal) > math.cos(math.radians(2.0))
    assert abs(p.distance_m - truth.distance_m) < 0.02
    med = estimate_plane(PINHOLE, mask, pts, method="median")
    assert np.allclose(med.normal, [0, 0, 1]) and abs(med.distance_m - face.c[2]) < 0.1


def test_plane_estimate_without_enough_points_is_none_and_nonplanar_falls_back_to_median():
    mask = FRONT.render(PINHOLE, np.eye(4))
    assert estimate_plane(PINHOLE, mask, FRONT.sample(2, 2), min_points=8) is None
    assert estimate_plane(PINHOLE, mask, np.zeros((0, 3))) is None
    rng = np.random.default_rng(2)
    blob = FRONT.sample(20, 20) + np.array([0, 0, 1.0]) * rng.uniform(-0.3, 0.3, (400, 1))  # a bush, not a face
    p = estimate_plane(PINHOLE, mask, blob)
    assert np.allclose(p.normal, [0, 0, 1]) and abs(p.distance_m - 2.0) < 0.1


def test_memory_estimates_the_plane_of_a_fresh_mask_and_warps_with_it():
    mem = MaskMemory(PINHOLE)
    mask = FRONT.render(PINHOLE, np.eye(4))
    mem.reconcile(answer(0.0, np.eye(4), [mask]), points_cam=_scene_points(FRONT, np.random.default_rng(3)))
    (e,) = mem.entries
    assert e.plane is not None and abs(e.plane.distance_m - 2.0) < 0.02
    T1 = motion("diagonal", 0.5)
    (w,) = mem.propagate(0.5, T1)
    assert w.method == "plane" and iou(w.mask, FRONT.render(PINHOLE, T1)) >= 0.95
    mem2 = MaskMemory(PINHOLE)
    mem2.reconcile(answer(0.0, np.eye(4), [mask]))  # no lidar points: depth unknown
    (w2,) = mem2.propagate(0.5, T1)
    assert w2.method == "rotation" and iou(w2.mask, FRONT.render(PINHOLE, T1)) < 0.9


# ---------------------------------------------------------------- Phase II reconciliation
def rect(x0, y0, x1, y1, shape=(H, W)) -> np.ndarray:
    m = np.zeros(shape, dtype=bool)
    m[y0:y1, x0:x1] = True
    return m


def obj(mask, label="box", movable=True, cost=2.0, conf=0.9) -> DetectedObject:
    return DetectedObject(mask=mask, label=label, movable=movable, contact_cost=cost, confidence=conf)


def answer(stamp, T, masks, labels=None, error=None) -> VlmAnswer:
    labels = labels or ["box"] * len(masks)
    objs = tuple(obj(m, label=l) for m, l in zip(masks, labels))
    return VlmAnswer(stamp_s=stamp, camera_pose_odom=T, objects=objs, backend="test", latency_s=0.0, error=error)


def test_first_answer_inserts_everything():
    mem = MaskMemory(PINHOLE)
    r = mem.reconcile(answer(0.0, np.eye(4), [rect(10, 10, 100, 100), rect(300, 200, 400, 300)]), prompt="push?")
    assert r.inserted == ((0, 0), (1, 1)) and r.matched == () and r.dropped == ()
    assert [e.object_id for e in mem.entries] == [0, 1] and mem.entries[0].prompt == "push?"


def test_match_keeps_the_id_and_takes_the_fresh_geometry_and_words():
    mem = MaskMemory(PINHOLE)
    mem.reconcile(answer(0.0, np.eye(4), [rect(100, 100, 200, 200)]))
    fresh = rect(101, 100, 201, 200)  # IoU 99/101
    r = mem.reconcile(answer(1.0, np.eye(4), [fresh], labels=["chair"]))
    assert r.matched == ((0, 0, pytest.approx(99 / 101)),) and r.dropped == () and r.inserted == ()
    (e,) = mem.entries
    assert e.object_id == 0 and e.label == "chair" and e.stamp_s == 1.0 and np.array_equal(e.mask, fresh)


def test_match_after_motion_compares_in_the_fresh_capture_view():
    """The remembered mask is warped to the fresh answer's pose before the IoU."""
    mem = MaskMemory(PINHOLE)
    pts = _scene_points(FRONT, np.random.default_rng(4))
    mem.reconcile(answer(0.0, np.eye(4), [FRONT.render(PINHOLE, np.eye(4))]), points_cam=pts)
    T1 = motion("forward", 0.5)
    r = mem.reconcile(answer(1.0, T1, [FRONT.render(PINHOLE, T1)]))
    assert len(r.matched) == 1 and r.matched[0][2] >= 0.9 and r.dropped == ()


def test_an_object_that_moved_with_the_camera_keeps_its_entry_when_its_motion_is_given():
    """A box pushed by the robot: the camera and the box moved together by 0.3 m, so the fresh
    mask is where the old one was. Warped as a still plane the old mask misses it (a new entry);
    warped from where the camera was relative to the box (the tracker's motion) it matches."""
    pts = _scene_points(FRONT, np.random.default_rng(4))
    T1 = pose(t=(0.3, 0.0, 0.0))
    moved = Face(FRONT.c + [0.3, 0.0, 0.0], FRONT.a, FRONT.b, FRONT.ha, FRONT.hb)
    fresh = answer(1.0, T1, [moved.render(PINHOLE, T1)])
    assert np.array_equal(fresh.objects[0].mask, FRONT.render(PINHOLE, np.eye(4)))
    results = {}
    for motions in (None, {0: (0.3, 0.0)}):
        mem = MaskMemory(PINHOLE)
        mem.reconcile(answer(0.0, np.eye(4), [FRONT.render(PINHOLE, np.eye(4))]), points_cam=pts)
        results[motions is not None] = mem.apply(mem.preparer.prepare(fresh, tuple(mem.entries), motions=motions))
    still, followed = results[False], results[True]
    assert still.matched == () and still.inserted == ((1, 0),) and still.dropped == (0,)
    assert followed.matched == ((0, 0, pytest.approx(1.0, abs=0.02)),) and followed.inserted == ()


def test_unmatched_memory_is_dropped_and_unmatched_detection_inserted():
    mem = MaskMemory(PINHOLE)
    mem.reconcile(answer(0.0, np.eye(4), [rect(10, 10, 100, 100), rect(300, 200, 400, 300)]))
    r = mem.reconcile(answer(1.0, np.eye(4), [rect(300, 200, 400, 300), rect(500, 50, 600, 150)]))
    assert r.matched == ((1, 0, 1.0),) and r.dropped == (0,) and r.inserted == ((2, 1),)
    assert sorted(e.object_id for e in mem.entries) == [1, 2]


@pytest.mark.parametrize("sigma, matches", [(0.90, False), (0.85, True), (0.80, True)])
def test_sigma_iou_is_a_threshold_on_iou(sigma, matches):
    old, new = rect(0, 0, 100, 100), rect(0, 0, 100, 85)  # IoU exactly 0.85
    assert iou(old, new) == pytest.approx(0.85)
    mem = MaskMemory(PINHOLE, MaskMemoryConfig(sigma_iou=sigma))
    mem.reconcile(answer(0.0, np.eye(4), [old]))
    r = mem.reconcile(answer(1.0, np.eye(4), [new]))
    if matches:
        assert r.matched == ((0, 0, pytest.approx(0.85)),) and r.inserted == ()
    else:
        assert r.matched == () and r.dropped == (0,) and r.inserted == ((1, 0),)


def test_two_entries_on_one_detection_the_better_keeps_it():
    mem = MaskMemory(PINHOLE, MaskMemoryConfig(sigma_iou=0.5))
    mem.reconcile(answer(0.0, np.eye(4), [rect(0, 0, 100, 100), rect(0, 0, 100, 80)]))
    r = mem.reconcile(answer(1.0, np.eye(4), [rect(0, 0, 100, 98)]))
    assert r.matched == ((0, 0, pytest.approx(0.98)),) and r.dropped == (1,) and r.inserted == ()


def test_failed_answer_changes_nothing_empty_answer_drops_all_old_answer_ignored():
    mem = MaskMemory(PINHOLE)
    mem.reconcile(answer(1.0, np.eye(4), [rect(0, 0, 50, 50)]))
    r = mem.reconcile(answer(2.0, np.eye(4), [], error="timeout"))
    assert r.ignored and "timeout" in r.ignored and len(mem.entries) == 1
    r = mem.reconcile(answer(0.5, np.eye(4), []))
    assert r.ignored and "older" in r.ignored and len(mem.entries) == 1
    r = mem.reconcile(answer(2.0, np.eye(4), []))
    assert r.dropped == (0,) and mem.entries == []


def test_iou_matrix_is_eq5_for_every_pair():
    a = np.stack([rect(0, 0, 10, 10, (20, 20)), rect(10, 10, 20, 20, (20, 20)), np.zeros((20, 20), bool)])
    b = np.stack([rect(0, 0, 10, 5, (20, 20)), np.zeros((20, 20), bool)])
    assert np.allclose(iou_matrix(a, b), [[0.5, 0.0], [0.0, 0.0], [0.0, 0.0]])


# ---------------------------------------------------------------- trigger rule, age-out
@pytest.mark.parametrize("now, moved, empty, due", [
    (1.0, 0.0, True, True),  # memory empty
    (1.0, 0.6, False, True),  # moved more than d_thres
    (1.0, 0.4, False, False),
    (1.0, 0.5, False, False),  # strict: exactly d_thres is not more
    (2.1, 0.0, False, True),  # t_thres passed
    (1.9, 0.0, False, False),
    (2.0, 0.0, False, False),
])
def test_trigger_rule(now, moved, empty, due):
    cfg = MaskMemoryConfig(d_thres_m=0.5, t_thres_s=2.0)
    T_now = pose(t=(moved * 0.6, 0.0, moved * 0.8))
    assert query_due(now, T_now, 0.0, np.eye(4), empty, cfg) is due


def test_trigger_without_a_previous_query_and_through_the_memory():
    cfg = MaskMemoryConfig()
    assert query_due(0.0, np.eye(4), None, None, False, cfg)
    mem = MaskMemory(PINHOLE, cfg)
    assert mem.query_due(0.0, np.eye(4))
    mem.note_query(0.0, np.eye(4))
    mem.reconcile(answer(0.0, np.eye(4), [rect(0, 0, 50, 50)]))
    assert not mem.query_due(1.0, pose(t=(0.1, 0, 0)))
    assert mem.query_due(1.0, pose(t=(0.0, 0, 0.51)))
    assert mem.query_due(2.01, np.eye(4))


def test_entries_age_out():
    mem = MaskMemory(PINHOLE, MaskMemoryConfig(max_age_s=5.0))
    mem.reconcile(answer(0.0, np.eye(4), [rect(0, 0, 50, 50)]))
    mem.reconcile(answer(3.0, np.eye(4), [rect(0, 0, 50, 50), rect(100, 100, 150, 150)]))  # refreshes id 0
    assert len(mem.propagate(4.9, np.eye(4))) == 2
    assert [w.object_id for w in mem.propagate(7.9, np.eye(4))] == [0, 1]
    assert mem.propagate(8.1, np.eye(4)) == [] and mem.entries == []
    mem.reconcile(answer(0.0 + 10, np.eye(4), [rect(0, 0, 50, 50)]), now_s=12.0)
    assert len(mem.entries) == 1
    # An answer captured longer ago than max_age_s is ignored (its masks would age out at once,
    # after dropping every entry they did not match).
    late = mem.reconcile(answer(8.5, np.eye(4), [rect(100, 100, 150, 150)]), now_s=14.0)
    assert late.ignored is not None and "older than max_age_s" in late.ignored
    assert [e.object_id for e in mem.entries] == [2]


# ---------------------------------------------------------------- bad inputs
def test_bad_inputs_name_the_field():
    mem = MaskMemory(PINHOLE)
    scaled = np.diag([2.0, 1.0, 1.0, 1.0])
    with pytest.raises(MaskMemoryError, match="camera_pose_odom.*rotation"):
        mem.propagate(0.0, scaled)
    with pytest.raises(MaskMemoryError, match="answer camera_pose_odom"):
        mem.reconcile(answer(0.0, scaled, [rect(0, 0, 5, 5)]))
    with pytest.raises(MaskMemoryError, match="last row"):
        query_due(0.0, np.ones((4, 4)), None, None, True, MaskMemoryConfig())
    with pytest.raises(MaskMemoryError, match="answer object 1 mask: empty"):
        mem.reconcile(answer(0.0, np.eye(4), [rect(0, 0, 5, 5), np.zeros((H, W), bool)]))
    with pytest.raises(MaskMemoryError, match=r"answer object 0 mask: shape \(10, 10\)"):
        mem.reconcile(answer(0.0, np.eye(4), [np.ones((10, 10), bool)]))
    assert mem.entries == []  # all or nothing
    with pytest.raises(MaskMemoryError, match="points_cam"):
        mem.reconcile(answer(0.0, np.eye(4), [rect(0, 0, 5, 5)]), points_cam=np.zeros((4, 2)))
    with pytest.raises(HomographyError, match="mask: dtype"):
        MaskWarper(PINHOLE).warp(np.zeros((H, W), np.uint8), np.eye(3), np.zeros(3), None)
    with pytest.raises(HomographyError, match="mask: shape"):
        MaskWarper(PINHOLE).warp(np.zeros((H, W + 1), bool), np.eye(3), np.zeros(3), None)
    with pytest.raises(HomographyError, match="plane normal: must be a unit"):
        Plane(np.array([0.0, 0.0, 2.0]), 1.0)
    with pytest.raises(HomographyError, match="plane distance_m"):
        Plane(np.array([0.0, 0.0, 1.0]), -1.0)
    with pytest.raises(HomographyError, match="camera pose at capture: expected a 4x4"):
        relative_motion(np.eye(3), np.eye(4))
    with pytest.raises(HomographyError, match="method"):
        estimate_plane(PINHOLE, rect(0, 0, 5, 5), np.zeros((0, 3)), method="ransac")
    with pytest.raises(ValueError, match="extra"):
        MaskMemoryConfig(sigma=0.5)
    with pytest.raises(ValueError, match="sigma_iou"):
        MaskMemoryConfig(sigma_iou=1.5)
