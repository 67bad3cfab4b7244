"""VPP Phase III: point partition (eqs. 7-9), cluster refinement, odom-frame label memory."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from pydantic import ValidationError

from calibration.camera_model import CameraModel, transform_points
from runtime.vpp.partition.config import PartitionConfig
from runtime.vpp.partition.inputs import PartitionInputError
from runtime.vpp.partition.label_memory import LabelMemory
from runtime.vpp.partition.labels import FIXED, IGNORED, MOVABLE
from runtime.vpp.partition.partitioner import PointPartitioner, partition_points

W, H = 640, 480
K = np.array([[500.0, 0, 319.5], [0, 500.0, 239.5], [0, 0, 1]])
CAM = CameraModel(K, np.array([-0.05, 0.01, 0.0005, -0.0003, 0.0]), W, H)
# lidar x forward, y left, z up; camera optical frame 5 cm above the lidar
T_CL = np.eye(4)
T_CL[:3, :3] = np.array([[0, -1, 0], [0, 0, -1], [1, 0, 0]], float)
T_CL[:3, 3] = T_CL[:3, :3] @ np.array([0.0, 0.0, -0.05])
T_BL = np.eye(4)
T_BL[2, 3] = 0.25  # lidar 25 cm above the floor
FLOOR_Z = -0.25  # floor height in the lidar frame


def grid(x, ys, zs):
    y, z = np.meshgrid(ys, zs, indexing="ij")
    return np.column_stack([np.full(y.size, x), y.ravel(), z.ravel()])


def scene():
    """A box face (0.4 x 0.4 m at 2 m) in front of a wall at 4 m, a floor, points behind."""
    box = grid(2.0, np.arange(-0.2, 0.2001, 0.02), np.arange(-0.2, 0.2001, 0.02))
    wall = grid(4.0, np.arange(-2.0, 2.0001, 0.02), np.arange(-0.2, 1.0001, 0.02))
    # the lidar does not see the wall behind the box
    shadow = (np.abs(wall[:, 1]) < 0.41) & (np.abs(wall[:, 2]) < 0.41)
    wall = wall[~shadow]
    fx, fy = np.meshgrid(np.arange(0.5, 3.9, 0.1), np.arange(-1.5, 1.5, 0.1), indexing="ij")
    floor = np.column_stack([fx.ravel(), fy.ravel(), np.full(fx.size, FLOOR_Z)])
    behind = grid(-2.0, np.arange(-1.0, 1.0, 0.05), np.arange(-0.2, 0.5, 0.05))
    pts = np.vstack([box, wall, floor, behind]).astype(np.float32)
    kind = np.repeat([0, 1, 2, 3], [len(box), len(wall), len(floor), len(behind)])
    return pts, kind


def box_mask(pts, kind, margin_px=8, cut_v=None):
    """A rectangle around the box's projected points, margin_px larger each side (a VLM mask's
    edge overlaps the background); cut_v: keep only rows above it."""
    uv, ok = CAM.project_lidar(pts[kind == 0], T_CL)
    assert ok.all()
    u0, v0 = np.floor(uv.min(0)).astype(int) - margin_px
    u1, v1 = np.ceil(uv.max(0)).astype(int) + margin_px
    m = np.zeros((H, W), bool)
    m[v0:v1 + 1, u0:u1 + 1] = True
    if cut_v is not None:
        m[cut_v:] = False
    return m


def pixels(pts):
    uv, ok = CAM.project_lidar(pts, T_CL)
    pix = np.full((len(pts), 2), -1)
    pix[ok] = np.floor(uv[ok] + 0.5).astype(int)
    return pix, ok


# --------------------------------------------------------------------------- exact synthetic scene
def test_box_movable_wall_fixed_ground_removed_behind_unseen():
    pts, kind = scene()
    m = box_mask(pts, kind)
    pix, ok = pixels(pts)
    in_mask = ok.copy()
    in_mask[ok] = m[pix[ok, 1], pix[ok, 0]]
    assert in_mask[kind == 1].sum() > 50  # the mask's edge does see the wall behind the box
    res = partition_points(pts, T_CL, CAM, [m], [7], [3.0], T_base_lidar=T_BL)
    assert (res.label[kind == 0] == MOVABLE).all()
    assert (res.object_id[kind == 0] == 7).all() and (res.cost[kind == 0] == 3.0).all()
    assert (res.label[kind == 1] == FIXED).all()  # wall: also where seen through the mask
    assert (res.label[kind == 2] == IGNORED).all()  # floor, inside the mask or not
    assert not res.in_view[kind == 3].any() and (res.label[kind == 3] == FIXED).all()
    assert (res.object_id[res.label != MOVABLE] == -1).all() and np.isnan(res.cost[res.label != MOVABLE]).all()
    assert res.n_outliers_removed == in_mask[kind == 1].sum()
    assert res.n_completed == 0


def test_without_depth_gate_the_background_strip_stays_movable():
    """The paper's size rule alone keeps the wall strip seen through the mask's edge (it is one
    big connected component): why max_depth_gap_m exists."""
    pts, kind = scene()
    m = box_mask(pts, kind)
    res = partition_points(pts, T_CL, CAM, [m], [7], [3.0], PartitionConfig(max_depth_gap_m=None),
                           T_base_lidar=T_BL)
    assert (res.label[kind == 0] == MOVABLE).all()
    assert (res.label[kind == 1] == MOVABLE).sum() > 50


def test_speckles_below_n_min_are_suppressed_even_without_depth_gate():
    pts, kind = scene()
    m = box_mask(pts, kind, margin_px=0)
    # three isolated points between the camera and the box, inside the mask
    speck = np.array([[1.0, 0.0, 0.0], [1.3, 0.05, 0.05], [0.7, -0.03, 0.02]], np.float32)
    allp = np.vstack([pts, speck])
    res = partition_points(allp, T_CL, CAM, [m], [1], [5.0], PartitionConfig(max_depth_gap_m=None, n_min=5),
                           T_base_lidar=T_BL)
    assert (res.label[-3:] == FIXED).all()
    assert (res.label[:len(pts)][kind == 0] == MOVABLE).all()
    assert res.n_outliers_removed == 3


def test_completion_adds_object_points_next_to_the_mask_only():
    """The mask stops short of the box's bottom rows: box points within eps in 3-D and within
    completion_dilate_px of the mask join; the rest of the box below stays fixed; the wall never joins."""
    pts, kind = scene()
    pix, ok = pixels(pts)
    vb = pix[kind == 0, 1]
    cut = int(np.median(vb))  # rows of the box from here down are outside the mask
    m = box_mask(pts, kind, margin_px=0, cut_v=cut)
    cfg = PartitionConfig(eps_cluster_m=0.05, completion_dilate_px=6)
    res = partition_points(pts, T_CL, CAM, [m], [2], [4.0], cfg, T_base_lidar=T_BL)
    box = np.flatnonzero(kind == 0)
    inside = m[pix[box, 1], pix[box, 0]]
    below = pix[box, 1] - (cut - 1)  # rows below the mask's last row
    expected = inside | (below <= 6)
    # 3-D check of the expectation: a completed point lies within eps of a masked box point
    d = np.linalg.norm(pts[box][~inside & (below <= 6)][:, None] - pts[box][inside][None], axis=2).min(1)
    assert (d <= 0.05).all()
    np.testing.assert_array_equal(res.label[box] == MOVABLE, expected)
    assert res.n_completed == int((expected & ~inside).sum()) > 0
    assert (res.label[kind == 1] == FIXED).all()
    cfg_off = PartitionConfig(eps_cluster_m=0.05, completion=False)
    off = partition_points(pts, T_CL, CAM, [m], [2], [4.0], cfg_off, T_base_lidar=T_BL)
    np.testing.assert_array_equal(off.label[box] == MOVABLE, inside)


def test_overlapping_masks_highest_cost_wins_and_ignore_mask():
    pts, kind = scene()
    m = box_mask(pts, kind)
    left = m.copy()
    left[:, W // 2:] = False
    ignore = np.zeros(len(pts), bool)
    ignore[np.flatnonzero(kind == 0)[:5]] = True
    res = partition_points(pts, T_CL, CAM, np.stack([m, left]), [1, 2], [2.0, 9.0], T_base_lidar=T_BL,
                           ignore=ignore)
    pix, _ = pixels(pts)
    box = (kind == 0) & ~ignore
    in_left = left[pix[:, 1].clip(0), pix[:, 0].clip(0)] & box
    assert (res.object_id[in_left] == 2).all() and (res.cost[in_left] == 9.0).all()
    assert (res.object_id[box & ~in_left] == 1).all()
    assert (res.label[ignore] == IGNORED).all()


def test_no_masks_everything_seen_is_fixed():
    pts, kind = scene()
    res = partition_points(pts, T_CL, CAM, [], [], [], T_base_lidar=T_BL)
    assert (res.label[kind != 2] == FIXED).all() and (res.label[kind == 2] == IGNORED).all()
    res2 = partition_points(pts, T_CL, CAM, np.zeros((0, H, W), bool), np.zeros(0, int), np.zeros(0))
    assert (res2.label == FIXED).all()  # no ground removal without T_base_lidar or ignore


# --------------------------------------------------------------------------- label memory
def _rot_z(deg):
    a = np.radians(deg)
    T = np.eye(4)
    T[:2, :2] = [[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]]
    return T


def test_memory_keeps_labels_out_of_view_and_ages_out():
    cfg = PartitionConfig(memory_max_age_s=2.0)
    part = PointPartitioner(cfg)
    pts, kind = scene()
    m = box_mask(pts, kind)
    T0 = np.eye(4)
    T0[:3, 3] = [0.033, 0.047, 0.021]  # keep the grid's points off the memory's voxel boundaries
    r0 = part.partition(pts, T_CL, CAM, [m], [7], [3.0], T_base_lidar=T_BL, T_odom_lidar=T0, stamp_s=10.0)
    assert (r0.label[kind == 0] == MOVABLE).all() and not r0.from_memory.any()
    # the robot turns 180 degrees in place: the box and the wall are now behind the camera
    T1 = T0 @ _rot_z(180.0)
    pts1 = transform_points(np.linalg.inv(T1) @ T0, pts).astype(np.float32)  # same odom points, new lidar frame
    r1 = part.partition(pts1, T_CL, CAM, [], [], [], T_base_lidar=T_BL, T_odom_lidar=T1, stamp_s=11.0)
    assert not r1.in_view[kind <= 1].any()
    assert (r1.label[kind == 0] == MOVABLE).all() and (r1.object_id[kind == 0] == 7).all()
    assert (r1.cost[kind == 0] == 3.0).all() and r1.from_memory[kind == 0].all()
    wall = kind == 1
    assert (r1.label[wall] == FIXED).all()
    assert r0.in_view[wall].all() and r1.from_memory[wall].all()
    # what was behind at first is now in view: seen, fixed, not from memory
    assert r1.in_view[kind == 3].all() and (r1.label[kind == 3] == FIXED).all()
    assert (r1.label[kind == 2] == IGNORED).all() and not r1.from_memory[kind == 2].any()
    # 2.5 s after the box was last seen: aged out, fixed
    r2 = part.partition(pts1, T_CL, CAM, [], [], [], T_base_lidar=T_BL, T_odom_lidar=T1, stamp_s=12.5)
    assert (r2.label[kind == 0] == FIXED).all() and not r2.from_memory[kind == 0].any()
    # without odometry the memory is not used: unseen points are fixed
    r3 = PointPartitioner(cfg).partition(pts1, T_CL, CAM, [], [], [], T_base_lidar=T_BL)
    assert (r3.label[kind == 0] == FIXED).all()


def test_memory_voxel_merge_fixed_wins_then_highest_cost():
    mem = LabelMemory(voxel_m=0.1, max_age_s=5.0, initial_slots=64)
    p = np.array([[0.01, 0.01, 0.01], [0.02, 0.02, 0.02], [1.01, 0, 0], [1.02, 0, 0], [1.03, 0, 0]])
    lab = np.array([MOVABLE, FIXED, MOVABLE, MOVABLE, MOVABLE], np.int8)
    obj = np.array([1, -1, 4, 3, 5], np.int32)
    cost = np.array([2.0, np.nan, 6.0, 6.0, 1.0], np.float32)
    mem.write(p, np.ones(5, bool), lab, obj, cost, 1.0)
    found, l2, o2, c2 = mem.read(p, np.ones(5, bool), 1.5)
    assert found.all()
    assert l2[0] == FIXED and l2[1] == FIXED
    assert (l2[2:] == MOVABLE).all() and (o2[2:] == 3).all() and (c2[2:] == 6.0).all()  # max cost, tie: lower id
    # a later scan overwrites
    mem.write(p[:1], np.ones(1, bool), lab[:1], obj[:1], cost[:1], 2.0)
    assert mem.read(p[:1], np.ones(1, bool), 2.0)[1][0] == MOVABLE


def test_memory_grows_and_drops_expired_entries():
    mem = LabelMemory(voxel_m=0.1, max_age_s=1.0, initial_slots=64)
    rng = np.random.default_rng(1)
    for s in range(20):
        p = rng.uniform(-50, 50, (500, 3))
        mem.write(p, np.ones(500, bool), np.full(500, MOVABLE, np.int8), np.full(500, s, np.int32),
                  np.full(500, 1.0, np.float32), float(s))
        found, _, obj, _ = mem.read(p, np.ones(500, bool), float(s))
        assert found.all() and (obj == s).all()
    # stale entries are dropped at rebuilds: the table holds about the last two scans, not 20
    assert len(mem) <= 4 * 500
    old = rng.uniform(-50, 50, (10, 3))
    assert not mem.read(old, np.ones(10, bool), 19.0)[0].any()


# --------------------------------------------------------------------------- bad inputs
@pytest.mark.parametrize("kwargs, field", [
    (dict(points_lidar=np.zeros((5, 2), np.float32)), "points_lidar"),
    (dict(points_lidar=np.array([[1, 2, np.nan]], np.float32)), "points_lidar"),
    (dict(points_lidar=np.zeros((5, 3), np.int32)), "points_lidar"),
    (dict(T_cam_lidar=np.eye(3)), "T_cam_lidar"),
    (dict(T_cam_lidar=np.diag([2.0, 1, 1, 1])), "T_cam_lidar"),
    (dict(masks=[np.zeros((480, 641), bool)]), "masks"),
    (dict(masks=[np.zeros((480, 640), np.uint8)]), "masks"),
    (dict(masks=np.zeros((480, 640), bool)), "masks"),
    (dict(object_ids=[1, 2]), "object_ids"),
    (dict(object_ids=[-1]), "object_ids"),
    (dict(costs=[11.0]), "costs"),
    (dict(costs=[np.nan]), "costs"),
    (dict(ignore=np.zeros(4, bool)), "ignore"),
    (dict(T_base_lidar=np.full((4, 4), np.nan)), "T_base_lidar"),
    (dict(stamp_s=1.0), "T_odom_lidar"),
    (dict(T_odom_lidar=np.eye(4)), "stamp_s"),
    (dict(T_odom_lidar=np.eye(4), stamp_s=float("nan")), "stamp_s"),
    (dict(camera="cam"), "camera"),
])
def test_bad_inputs_name_the_field(kwargs, field):
    args = dict(points_lidar=np.zeros((5, 3), np.float32), T_cam_lidar=T_CL, camera=CAM,
                masks=[np.zeros((H, W), bool)], object_ids=[1], costs=[1.0])
    args.update({k: v for k, v in kwargs.items() if k in args})
    extra = {k: v for k, v in kwargs.items() if k not in args}
    with pytest.raises(PartitionInputError, match=f"^{field}:"):
        PointPartitioner().partition(**args, **extra)


def test_config_forbids_unknown_fields():
    with pytest.raises(ValidationError):
        PartitionConfig(eps=0.1)
    with pytest.raises(ValidationError):
        PartitionConfig(eps_cluster_m=-1.0)


# --------------------------------------------------------------------------- invariants
@st.composite
def random_case(draw):
    seed = draw(st.integers(0, 2**31 - 1))
    rng = np.random.default_rng(seed)
    n = draw(st.integers(0, 400))
    pts = rng.uniform([-3, -3, -0.5], [6, 3, 1.5], (n, 3)).astype(np.float32)
    n_masks = draw(st.integers(0, 4))
    masks = np.zeros((n_masks, H, W), bool)
    for k in range(n_masks):
        u0, v0 = rng.integers(0, W - 1), rng.integers(0, H - 1)
        masks[k, v0:v0 + rng.integers(1, 300), u0:u0 + rng.integers(1, 300)] = True
    costs = rng.choice([0.0, 2.5, 5.0, 10.0], n_masks)
    return pts, masks, costs


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(random_case(), st.booleans())
def test_movable_only_where_a_mask_is(case, refine):
    """Eq. 8 exactly with refinement off (n_min 1, no gate, no completion); with refinement on a
    point is movable only if its pixel lies in its mask dilated by completion_dilate_px. Unseen
    or ground points are never movable (no memory), and id/cost belong to the same mask."""
    pts, masks, costs = case
    ids = np.arange(len(costs)) + 10
    cfg = (PartitionConfig(eps_cluster_m=0.3, n_min=3, completion_dilate_px=5) if refine else
           PartitionConfig(n_min=1, max_depth_gap_m=None, completion=False))
    res = partition_points(pts, T_CL, CAM, masks, ids, costs, cfg, T_base_lidar=T_BL)
    pix, ok = pixels(pts)
    ground = pts[:, 2] + 0.25 < cfg.ground_max_z_m
    np.testing.assert_array_equal(res.in_view, ok)
    assert (res.label[ground] == IGNORED).all()
    mov = res.label == MOVABLE
    assert not (mov & (~ok | ground)).any()
    k = res.object_id[mov] - 10
    np.testing.assert_array_equal(res.cost[mov], costs[k])
    hit = np.zeros((len(costs), len(pts)), bool)
    if ok.any():
        hit[:, ok] = masks[:, pix[ok, 1], pix[ok, 0]]
    if not refine:
        expected = hit.any(axis=0) & ok & ~ground
        np.testing.assert_array_equal(mov, expected)
        best = np.where(hit, costs[:, None], -1.0).max(axis=0, initial=-1.0)
        np.testing.assert_array_equal(res.cost[mov], best[mov])
    else:
        r = cfg.completion_dilate_px
        for i in np.flatnonzero(mov):
            u, v = pix[i]
            assert masks[k[list(np.flatnonzero(mov)).index(i)], max(v - r, 0):v + r + 1, max(u - r, 0):u + r + 1].any()


# --------------------------------------------------------------------------- real data
PANDAR = Path(__file__).resolve().parents[2] / "data" / "real" / "pandar64_camera_opencalib"
#: The car ahead in 0.png (about 40 m), outlined by hand in full-resolution pixels (u, v);
#: 0_car_mask.png is cv2.fillPoly of this polygon.
CAR_POLYGON = [(962, 603), (1020, 603), (1032, 618), (1040, 632), (1041, 672), (1035, 680), (946, 680),
               (941, 672), (942, 632), (950, 618)]


@pytest.fixture(scope="module")
def pandar():
    import cv2

    from calibration.calibration_file import calibration_from_opencalib
    from calibration.pointcloud_io import load_point_cloud

    cal = calibration_from_opencalib(PANDAR / "center_camera-intrinsic.json",
                                     PANDAR / "top_center_lidar-to-center_camera-extrinsic.json", 1920, 1200)
    xyz = load_point_cloud(PANDAR / "0.pcd").xyz.astype(np.float32)
    mask = cv2.imread(str(PANDAR / "0_car_mask.png"), cv2.IMREAD_GRAYSCALE)
    assert mask is not None
    ref = np.zeros_like(mask)
    cv2.fillPoly(ref, [np.array(CAR_POLYGON, np.int32)], 255)
    np.testing.assert_array_equal(mask, ref)
    return cal.camera_model(), cal.T_cam_lidar(), xyz, mask > 0


#: A car at 40 m: ring spacing ~0.12 m there, so eps 0.5 m; the lidar sits ~2 m above the road.
CAR_CFG = PartitionConfig(eps_cluster_m=0.5, n_min=10, max_depth_gap_m=2.0, completion_dilate_px=10,
                          ground_max_z_m=0.12)
T_BASE_PANDAR = np.eye(4)
T_BASE_PANDAR[2, 3] = 2.0


@pytest.mark.parametrize("sloppy_px", [0, 60])
def test_real_car_points_are_the_car(pandar, sloppy_px):
    """The hand-drawn mask (and the same mask grown by 60 px, as a sloppy VLM mask that takes in
    road, background and the car beside) picks out the car: one compact cluster at ~40 m, nothing
    from elsewhere, and nearly all lidar points that fall on the car in the image."""
    import cv2

    cam, T, xyz, mask = pandar
    if sloppy_px:
        k = 2 * sloppy_px + 1
        mask = cv2.dilate(mask.astype(np.uint8), np.ones((k, k), np.uint8)) > 0
    res = partition_points(xyz, T, cam, [mask], [1], [2.0], CAR_CFG, T_base_lidar=T_BASE_PANDAR)
    uv, ok, depth = cam.depths_and_project_lidar(xyz, T)
    pix = np.floor(uv[ok] + 0.5).astype(int)
    in_mask = np.zeros(len(xyz), bool)
    in_mask[ok] = mask[pix[:, 1], pix[:, 0]]
    mov = res.label == MOVABLE
    car_depth = np.median(depth[mov])
    print(f"sloppy {sloppy_px}px: {in_mask.sum()} points in the mask, {mov.sum()} movable, "
          f"removed {res.n_outliers_removed}, completed {res.n_completed}, median depth {car_depth:.1f} m, "
          f"depth range {depth[mov].min():.1f}..{depth[mov].max():.1f} m")
    assert 39.0 < car_depth < 42.0
    # compact: a car's extent, nothing from the background or the road
    assert np.ptp(depth[mov]) < 4.5
    assert np.ptp(xyz[mov, 1]) < 2.5 and np.ptp(xyz[mov, 2]) < 1.8
    assert (xyz[mov, 2] > -2.0 + 0.12).all()
    if sloppy_px:
        far = in_mask & (np.abs(depth - car_depth) > 3.0) & (res.label != IGNORED)
        print(f"  {far.sum()} non-ground points in the mask more than 3 m from the car's depth")
        assert far.sum() > 10 and not mov[far].any()  # the background through the mask was there, and dropped
    # recall: the points on the car in the hand-drawn mask at its depth
    ref = np.zeros((cam.height_px, cam.width_px), np.uint8)
    cv2.fillPoly(ref, [np.array(CAR_POLYGON, np.int32)], 255)
    on_car = np.zeros(len(xyz), bool)
    on_car[ok] = ref[pix[:, 1], pix[:, 0]] > 0
    on_car &= (np.abs(depth - car_depth) < 2.0) & (xyz[:, 2] > -2.0 + 0.12)
    assert on_car.sum() > 100
    assert mov[on_car].mean() >= 0.95, mov[on_car].mean()


def test_float16_and_strided_points_give_the_same_labels():
    pts, kind = scene()
    m = box_mask(pts, kind)
    ref = partition_points(pts, T_CL, CAM, [m], [7], [3.0], T_base_lidar=T_BL)
    wide = np.zeros((len(pts), 4), np.float32)
    wide[:, :3] = pts
    strided = partition_points(wide[:, :3], T_CL, CAM, [m], [7], [3.0], T_base_lidar=T_BL)
    np.testing.assert_array_equal(strided.label, ref.label)
    half = partition_points(pts.astype(np.float16), T_CL, CAM, [m], [7], [3.0], T_base_lidar=T_BL)
    assert (half.label[kind == 0] == MOVABLE).mean() > 0.95


@settings(max_examples=80, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), n=st.integers(0, 3000), spread=st.floats(0.02, 30.0),
       masks=st.integers(1, 16), eps=st.floats(0.01, 1.0))
def test_cluster_cells_are_a_stable_sort_of_the_keys(seed, n, spread, masks, eps):
    """The refinement's cells (bucketed through a hash table, only the distinct keys sorted) are
    exactly what numpy's stable argsort of the per-point keys gives: keys ascending, and the
    points of one cell in scan order; only the movable points among the rows given (the seen)."""
    from runtime.vpp.partition.clustering import _movable_keys, cell_keys

    rng = np.random.default_rng(seed)
    pts = rng.normal(0.0, spread, (n, 3))
    pts[: n // 4] = pts[: n // 4].round(1)  # many points sharing cells
    midx = rng.integers(-1, masks, n).astype(np.int32)
    rows = np.flatnonzero(rng.random(n) < 0.7)
    keys, mv = _movable_keys(pts, midx, np.arange(n), 2.0 / eps)
    keys, mv = keys[np.isin(mv, rows)], mv[np.isin(mv, rows)]
    order = np.argsort(keys, kind="stable")
    got_keys, got_points = cell_keys(pts, midx, rows, eps)
    np.testing.assert_array_equal(got_keys, keys[order])
    np.testing.assert_array_equal(got_points, mv[order])


def test_after_construction_the_partition_compiles_nothing_whatever_its_inputs_flags():
    """Every kernel signature the partition uses is compiled (or loaded from numba's cache) at
    construction: read-only points, masks and transforms (a calibration's) in a scan add no
    signature, which would be compiled in the tick that first met it."""
    import importlib

    from numba.core.registry import CPUDispatcher

    from hil_sim.bench.vpp import synthetic_frame
    from runtime.vpp.homography.lookup import warp_lookup
    from runtime.vpp.homography.plane import Plane

    pts, T, cam, masks, ids, costs, T_base = synthetic_frame(4000, 2)
    part = PointPartitioner()
    lk = warp_lookup(cam, masks, np.stack([np.eye(4)] * 2), [Plane(np.array([0.0, 0.0, 1.0]), 1.5)] * 2, np.eye(4))
    modules = [importlib.import_module(f"runtime.vpp.partition.{m}")
               for m in ("clustering", "gating", "label_memory", "projection")]
    kernels = {f"{m.__name__}.{k}": v for m in modules for k, v in vars(m).items() if isinstance(v, CPUDispatcher)}

    def signatures():
        return {k: set(v.overloads) for k, v in kernels.items()}

    def frozen(a):
        a = np.array(a)
        a.flags.writeable = False
        return a

    before = signatures()
    for ro in (False, True):
        f = frozen if ro else np.array
        for m in (f(masks), lk):
            part.partition(f(pts), f(T), cam, m, ids, costs, T_base_lidar=f(T_base), T_odom_lidar=f(np.eye(4)),
                           stamp_s=1.0)
    after = signatures()
    assert {k: after[k] - before[k] for k in kernels if after[k] != before[k]} == {}
