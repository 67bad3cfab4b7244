"""The simulated lens: MuJoCo's intrinsic camera and the distortion applied to its renders."""
import numpy as np
import pytest

from hil_sim.sensors.camera_lens import CameraLens, LensError

K = np.array([[340.0, 0.0, 322.5], [0.0, 338.0, 236.0], [0.0, 0.0, 1.0]])
BARREL = np.array([-0.12, 0.03, 0.0015, -0.001, -0.005])
PINCUSHION = np.array([0.08, 0.1, -0.001, 0.002, 0.01])


def _texture(w: int, h: int) -> np.ndarray:
    """A smooth random texture (the remap's bilinear sampling reproduces it closely)."""
    import cv2

    rng = np.random.default_rng(0)
    img = rng.uniform(0, 255, (h // 8 + 1, w // 8 + 1, 3)).astype(np.float32)
    return cv2.resize(img, (w, h), interpolation=cv2.INTER_CUBIC).clip(0, 255).astype(np.uint8)


@pytest.mark.parametrize("dist", [BARREL, PINCUSHION], ids=["barrel", "pincushion"])
def test_undistorting_the_lens_image_gives_the_pinhole_image_back(dist):
    """The canvas is a pinhole image; through the lens and back through cv2.undistort with the true
    K and distortion it is the pinhole image of the output's K again."""
    import cv2

    lens = CameraLens.build(K, dist, 640, 480)
    cw, ch = lens.canvas_size
    canvas = _texture(cw, ch)
    left, top = lens.margins_px[:2]
    pinhole = canvas[top:top + 480, left:left + 640].astype(float)  # the pinhole image with K
    distorted = lens.apply(canvas)
    assert distorted.shape == (480, 640, 3)
    back = cv2.undistort(distorted, lens.K, lens.dist).astype(float)
    inner = (slice(60, 420), slice(80, 560))  # undistort samples outside the image near its border
    assert np.abs(back[inner] - pinhole[inner]).mean() < 3.0
    assert np.abs(distorted.astype(float)[inner] - pinhole[inner]).mean() > 10.0  # the lens does change it


def test_lens_map_is_the_inverse_of_opencv_projection():
    """Each output pixel samples the canvas where its undistorted ray lands: projecting that ray
    with the true K and distortion lands back on the pixel."""
    import cv2

    lens = CameraLens.build(K, BARREL, 640, 480)
    map_x, map_y, _ = lens._map
    rng = np.random.default_rng(1)
    v, u = rng.integers(0, 480, 200), rng.integers(0, 640, 200)
    canvas_K = lens.canvas_K
    rays = np.stack([(map_x[v, u] - canvas_K[0, 2]) / canvas_K[0, 0], (map_y[v, u] - canvas_K[1, 2]) / canvas_K[1, 1],
                     np.ones(200)], axis=1)
    uv, _ = cv2.projectPoints(rays, np.zeros(3), np.zeros(3), lens.K, lens.dist)
    assert np.abs(uv.reshape(-1, 2) - np.stack([u, v], axis=1)).max() < 0.01


def test_barrel_lens_renders_a_larger_canvas_pinhole_none():
    barrel = CameraLens.build(K, BARREL, 640, 480)
    assert barrel.distorted and barrel.canvas_size[0] > 660 and barrel.canvas_size[1] > 490
    assert barrel.canvas_K[0, 2] == K[0, 2] + barrel.margins_px[0]
    pinhole = CameraLens.build(K, np.zeros(5), 640, 480)
    assert not pinhole.distorted and pinhole.canvas_size == (640, 480)
    img = _texture(640, 480)
    assert pinhole.apply(img) is img


def test_segmentation_goes_through_the_lens_by_nearest_label():
    lens = CameraLens.build(K, BARREL, 640, 480)
    cw, ch = lens.canvas_size
    labels = np.full((ch, cw), -1, np.int32)
    labels[:, cw // 2:] = 7
    out = lens.apply_nearest(labels)
    assert out.shape == (480, 640) and set(np.unique(out)) == {-1, 7}


@pytest.mark.parametrize("dist, problem", [
    ([-0.3, -0.1, 0.0, 0.0, 0.0], "folds over"),
    ([0.0, 0.0, 0.0], "5 finite coefficients"),
    ([float("nan"), 0.0, 0.0, 0.0, 0.0], "5 finite coefficients"),
])
def test_a_lens_that_cannot_be_rendered_is_refused_in_one_line(dist, problem):
    with pytest.raises(LensError) as e:
        CameraLens.build(K, np.array(dist), 640, 480)
    assert problem in str(e.value) and "\n" not in str(e.value)


def test_mujoco_intrinsic_camera_renders_the_asked_K():
    """The MjSpec camera's focal_pixel / principal_pixel give back K in OpenCV's convention (the
    principal point's sign was measured, see the module docstring)."""
    mujoco = pytest.importorskip("mujoco")
    from hil_sim.sensors.camera_lens import intrinsic_camera_K, set_intrinsic_camera

    spec = mujoco.MjSpec()
    cam = spec.worldbody.add_camera(name="c")
    set_intrinsic_camera(cam, K, 700, 520)
    model = spec.compile()
    K_back, size = intrinsic_camera_K(model, 0)
    assert size == (700, 520)
    assert np.allclose(K_back, K, atol=1e-3)
