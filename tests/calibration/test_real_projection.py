"""The real Pandar64 scan projected into its real image with the provided calibration (OpenCalib)."""
import numpy as np
import pytest

from calibration.extrinsics import (edge_alignment_score, image_edge_map, intensity_mutual_information,
                                    perturb_transform)

README_IN_IMAGE = 9954  # tests/data/real/pandar64_camera_opencalib/README.md


def test_projected_count_matches_readme(pandar_calibration, pandar_cloud):
    cam = pandar_calibration.camera_model()
    assert (cam.width_px, cam.height_px) == (1920, 1200)
    assert len(pandar_calibration.camera.distortion) == 4  # k1 k2 p1 p2, distortion is applied
    _, valid = cam.project_lidar(pandar_cloud.xyz, pandar_calibration.T_cam_lidar())
    assert abs(int(valid.sum()) - README_IN_IMAGE) <= 0.01 * README_IN_IMAGE, int(valid.sum())


def test_distortion_matters(pandar_calibration, pandar_cloud):
    """Without distortion the projection differs by pixels near the image border."""
    from calibration.camera_model import CameraModel

    cam = pandar_calibration.camera_model()
    flat = CameraModel(cam.K, np.zeros(4), cam.width_px, cam.height_px)
    T = pandar_calibration.T_cam_lidar()
    uv, valid = cam.project_lidar(pandar_cloud.xyz, T)
    uv0, valid0 = flat.project_lidar(pandar_cloud.xyz, T)
    both = valid & valid0
    assert np.max(np.linalg.norm(uv[both] - uv0[both], axis=1)) > 10.0


@pytest.fixture(scope="module")
def edge_map(pandar_image):
    return image_edge_map(pandar_image)


# A 2 deg rotation about each camera axis (both signs) combined with a 5 cm shift along it.
PERTURBATIONS = [
    (tuple(0.05 * s * np.eye(3)[a]), tuple(2.0 * s * np.eye(3)[a])) for a in range(3) for s in (1, -1)
]


def test_depth_edges_line_up_with_image_edges(pandar_calibration, pandar_cloud, edge_map):
    """Depth-discontinuity points land on image edges far above chance, and a wrong yaw/shift lowers it.

    On this road scene the depth edges are mostly vertical (poles, trunks, car), so they pin the
    horizontal placement: yaw about the camera's y axis and x shifts. (They do not pin pitch:
    horizontal image edges are everywhere on the road; intensity MI below covers all axes.)
    """
    cam = pandar_calibration.camera_model()
    T = pandar_calibration.T_cam_lidar()
    xyz = pandar_cloud.xyz
    s_true = edge_alignment_score(cam, xyz, T, edge_map)
    # chance level: the same depth edges scattered by a gross error
    s_gross = np.mean([edge_alignment_score(cam, xyz, perturb_transform(T, drpy_deg=d), edge_map)
                       for d in [(0, 6, 0), (0, -6, 0), (0, 0, 6), (0, 0, -6)]])
    assert s_true > 1.1 * s_gross, (s_true, s_gross)
    for sign in (1, -1):
        s = edge_alignment_score(cam, xyz, perturb_transform(T, (0.05 * sign, 0, 0), (0, 2.0 * sign, 0)), edge_map)
        print(f"edge score true {s_true:.3f}, perturbed {s:.3f}, gross {s_gross:.3f}")
        assert s < 0.97 * s_true, (sign, s, s_true)


@pytest.mark.parametrize("dxyz,drpy", PERTURBATIONS)
def test_wrong_extrinsic_lowers_intensity_alignment(pandar_calibration, pandar_cloud, pandar_image, dxyz, drpy):
    """Lidar intensity vs image grey level (mutual information) peaks at the given extrinsic."""
    cam = pandar_calibration.camera_model()
    T = pandar_calibration.T_cam_lidar()
    inten = pandar_cloud.fields["intensity"].astype(float)
    mi_true = intensity_mutual_information(cam, pandar_cloud.xyz, inten, T, pandar_image)
    mi_bad = intensity_mutual_information(cam, pandar_cloud.xyz, inten, perturb_transform(T, dxyz, drpy), pandar_image)
    print(f"MI true {mi_true:.4f}, perturbed {mi_bad:.4f}")
    assert mi_bad < 0.95 * mi_true, (mi_bad, mi_true)
