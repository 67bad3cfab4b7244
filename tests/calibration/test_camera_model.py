"""CameraModel: agrees with cv2.projectPoints, reports validity, rejects bad parameters."""
import cv2
import numpy as np
import pytest

from calibration.camera_model import CameraModel, CameraModelError, transform_points

K = np.array([[500.0, 0.0, 320.0], [0.0, 480.0, 240.0], [0.0, 0.0, 1.0]])
DISTS = {
    0: np.zeros(0),
    4: np.array([-0.2, 0.05, 0.001, -0.002]),
    5: np.array([-0.2, 0.05, 0.001, -0.002, 0.01]),
    8: np.array([-0.2, 0.05, 0.001, -0.002, 0.01, 0.02, -0.01, 0.005]),
    12: np.array([-0.2, 0.05, 0.001, -0.002, 0.01, 0.02, -0.01, 0.005, 0.001, -0.002, 0.003, 0.001]),
    14: np.array([-0.2, 0.05, 0.001, -0.002, 0.01, 0.02, -0.01, 0.005, 0.001, -0.002, 0.003, 0.001, 0.01, -0.02]),
}


@pytest.mark.parametrize("n", sorted(DISTS))
def test_matches_cv2_project_points(n):
    rng = np.random.default_rng(n)
    pts = np.column_stack([rng.uniform(-1.5, 1.5, 5000), rng.uniform(-1, 1, 5000), rng.uniform(0.5, 5, 5000)])
    cam = CameraModel(K, DISTS[n], 640, 480)
    uv, valid = cam.project(pts)
    ref, _ = cv2.projectPoints(pts, np.zeros(3), np.zeros(3), K, DISTS[n] if n else None)
    ref = ref.reshape(-1, 2)
    assert valid.sum() > 1000
    np.testing.assert_allclose(uv[valid], ref[valid], atol=1e-6)
    inside = (ref[:, 0] >= -0.5) & (ref[:, 0] < 639.5) & (ref[:, 1] >= -0.5) & (ref[:, 1] < 479.5)
    # every valid point is inside; points inside the image and well within the model domain are valid
    assert np.all(inside[valid])
    assert np.all(valid[inside & (np.hypot(pts[:, 0], pts[:, 1]) / pts[:, 2] < 0.8)])


def test_behind_nan_and_outside_are_invalid():
    cam = CameraModel(K, DISTS[5], 640, 480)
    pts = np.array([[0, 0, 1.0], [0, 0, -1.0], [0, 0, 0.0], [np.nan, 0, 1], [10.0, 0, 1.0], [0, 0, np.inf]])
    _, valid = cam.project(pts)
    assert valid.tolist() == [True, False, False, False, False, False]


def test_reused_buffers_do_not_alias_results():
    cam = CameraModel(K, DISTS[5], 640, 480)
    a = np.array([[0.1, 0.1, 1.0], [0.2, -0.1, 2.0]])
    uv1, _ = cam.project(a)
    uv1_copy = uv1.copy()
    cam.project(a * [1, 1, 2])
    np.testing.assert_array_equal(uv1, uv1_copy)


def test_fold_back_of_polynomial_is_invalid():
    # k1 < 0 alone folds back at r = 1/sqrt(3|k1|); a point far outside the view must not re-enter.
    cam = CameraModel(K, np.array([-0.5, 0.0, 0.0, 0.0]), 640, 480)
    # radii beyond the fold whose (folded) distorted image lands inside the image
    r = np.linspace(0.9, 2.0, 200)
    xd = r * (1 - 0.5 * r * r)
    u = 500 * xd + 320
    inside = (u > 0) & (u < 639)
    assert inside.any()
    pts = np.column_stack([r[inside], np.zeros(inside.sum()), np.ones(inside.sum())])
    _, valid = cam.project(pts)
    assert not valid.any()


def test_project_lidar_uses_transform():
    T = np.eye(4)
    T[:3, :3] = [[0, -1, 0], [0, 0, -1], [1, 0, 0]]  # lidar x fwd, y left, z up -> optical
    T[:3, 3] = [0.0, 0.1, 0.0]
    cam = CameraModel(K, np.zeros(5), 640, 480)
    uv, valid = cam.project_lidar(np.array([[2.0, 0.0, 0.0]]), T)
    assert valid[0]
    np.testing.assert_allclose(uv[0], [320.0, 240.0 + 480 * 0.1 / 2.0])
    np.testing.assert_allclose(transform_points(T, np.array([[2.0, 0, 0]])), [[0, 0.1, 2.0]])


@pytest.mark.parametrize(
    "K_bad,dist,w,h,match",
    [
        ([[-500, 0, 320], [0, 480, 240], [0, 0, 1]], np.zeros(5), 640, 480, "focal"),
        ([[500, 0, 320], [0, 480, 240]], np.zeros(5), 640, 480, "3x3"),
        (K, np.zeros(6), 640, 480, "distortion"),
        (K, np.array([np.nan, 0, 0, 0]), 640, 480, "finite"),
        (K, np.zeros(5), 0, 480, "image size"),
    ],
)
def test_bad_parameters_raise(K_bad, dist, w, h, match):
    with pytest.raises(CameraModelError, match=match):
        CameraModel(np.array(K_bad, dtype=float), dist, w, h)


def test_bad_points_shape_raises():
    with pytest.raises(CameraModelError, match="N, 3"):
        CameraModel(K, np.zeros(5), 640, 480).project(np.zeros((4, 2)))
