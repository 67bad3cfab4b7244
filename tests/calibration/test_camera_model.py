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


def test_results_do_not_alias_between_calls():
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


def _reference_project(cam: CameraModel, p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The projection written out in numpy, in the order of operations calibration/lens.py keeps
    (the VPP's kernels share it: a last-bit change moves a point across a mask's edge)."""
    n = p.shape[0]
    x, y, r2, a, b, c = (np.empty(n) for _ in range(6))
    uv = np.empty((n, 2))
    z = p[:, 2]
    valid = (z > 1e-9) & (z < np.inf)
    with np.errstate(over="ignore"):  # a tiny z may overflow float32 points: those fail r2_max below
        np.divide(p[:, 0], z, out=x, where=valid)
        np.divide(p[:, 1], z, out=y, where=valid)
    x[~valid] = 0.0
    y[~valid] = 0.0
    np.multiply(x, x, out=r2)
    r2 += y * y
    valid &= r2 < cam._r2_max
    d = cam.dist
    if len(d):
        k1, k2, p1, p2 = d[:4]
        k3 = d[4] if len(d) > 4 else 0.0
        np.multiply(r2, k3, out=a)
        a += k2
        a *= r2
        a += k1
        a *= r2
        a += 1.0
        if len(d) >= 8:
            k4, k5, k6 = d[5:8]
            np.multiply(r2, k6, out=b)
            b += k5
            b *= r2
            b += k4
            b *= r2
            b += 1.0
            a /= b
        xy = x * y
        np.multiply(x, a, out=b)
        b += 2.0 * p1 * xy
        b += p2 * (r2 + 2.0 * x * x)
        np.multiply(y, a, out=c)
        c += p1 * (r2 + 2.0 * y * y)
        c += 2.0 * p2 * xy
        if len(d) >= 12:
            s1, s2, s3, s4 = d[8:12]
            r4 = r2 * r2
            b += s1 * r2 + s2 * r4
            c += s3 * r2 + s4 * r4
        xd, yd = b, c
    else:
        xd, yd = x, y
    Km = cam.K
    np.multiply(xd, Km[0, 0], out=uv[:, 0])
    uv[:, 0] += Km[0, 1] * yd + Km[0, 2]
    np.multiply(yd, Km[1, 1], out=uv[:, 1])
    uv[:, 1] += Km[1, 2]
    valid &= cam.inside_image(uv)
    return uv, valid


@pytest.mark.parametrize("n", [0, 4, 5, 8, 12])
@pytest.mark.parametrize("dtype", [np.float32, np.float64])
@pytest.mark.parametrize("skew", [0.0, 0.7])
def test_compiled_projection_is_the_reference_formula_bit_for_bit(n, dtype, skew):
    rng = np.random.default_rng(n)
    Ks = K.copy()
    Ks[0, 1] = skew
    cam = CameraModel(Ks, DISTS[n], 640, 480)
    pts = rng.normal(0.0, 3.0, (20000, 3)).astype(dtype)  # all around: half behind the camera
    pts[:3] = 0.0
    uv, valid = cam.project(pts)
    ref_uv, ref_valid = _reference_project(cam, pts)
    np.testing.assert_array_equal(valid, ref_valid)
    assert valid.sum() > 500
    np.testing.assert_array_equal(uv[valid], ref_uv[valid])


def test_monotone_radius_is_the_reference_search():
    """max_monotone_radius's compiled curve against the numpy one it replaces."""
    from calibration.lens import max_monotone_radius

    for d in list(DISTS.values())[1:] + [np.array([-0.5, 0.0, 0.0, 0.0]), np.array([0.1, -0.4, 0, 0, 0.2, 0.5, -0.9, 0.3])]:
        k = np.zeros(8)
        k[: min(len(d), 8)] = d[:8]
        k1, k2, _, _, k3, k4, k5, k6 = k
        r = np.linspace(0.0, 10.0, 20001)
        r2 = r * r
        with np.errstate(divide="ignore", invalid="ignore"):
            g = r * (1 + r2 * (k1 + r2 * (k2 + r2 * k3))) / (1 + r2 * (k4 + r2 * (k5 + r2 * k6)))
        dg = np.diff(g)
        bad = np.nonzero(~(dg > 0) | ~np.isfinite(dg))[0]
        assert max_monotone_radius(d) == (float(r[bad[0]]) if len(bad) else float(r[-1]))
