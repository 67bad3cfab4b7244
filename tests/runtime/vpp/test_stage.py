"""The VPP stage glue: requests on the trigger, answers reconciled, scans partitioned (lockstep)."""
from __future__ import annotations

import numpy as np
import pytest

from calibration.camera_model import CameraModel, transform_points
from calibration.robot_description import load_robot_description
from models.vlm.interface import DetectedObject, VlmAnswer, VlmRequest
from models.vlm.runner import BackendRunner, BackendRunnerConfig
from runtime.common.sensor_data import CameraImage, LidarScan
from runtime.vpp.partition.labels import MOVABLE
from runtime.vpp.config import VppConfig
from runtime.vpp.stage import VppStage

ROBOT = load_robot_description()
W, H = 640, 480
K = ROBOT.sensors.camera.nominal_intrinsics()
CAMERA = CameraModel(K, np.zeros(5), W, H)
T_BASE_CAM = ROBOT.sensors.camera.mount.transform()
T_BASE_LIDAR = ROBOT.sensors.lidar.mount.transform()


def _grid(x0, x1, y0, y1, z0, z1, step):
    g = np.mgrid[x0:x1 + 1e-9:step, y0:y1 + 1e-9:step, z0:z1 + 1e-9:step].reshape(3, -1).T
    return g


def scene_base():
    """A box (0.3 m cube's front face and top) 1.5 m ahead and a wall 3 m ahead, base frame."""
    box = np.concatenate([_grid(1.5, 1.5, -0.15, 0.15, 0.05, 0.3, 0.02), _grid(1.5, 1.8, -0.15, 0.15, 0.3, 0.3, 0.02)])
    wall = _grid(3.0, 3.0, -1.5, 1.5, 0.05, 0.8, 0.03)
    return box, wall


def scan_at(t: float) -> tuple[LidarScan, int]:
    box, wall = scene_base()
    pts_base = np.concatenate([box, wall])
    pts_lidar = transform_points(np.linalg.inv(T_BASE_LIDAR), pts_base).astype(np.float32)
    n = len(pts_lidar)
    return LidarScan(stamp_s=t, points_m=pts_lidar, point_time_offsets_s=np.zeros(n, np.float32),
                     frame_duration_s=0.1), len(box)


def box_mask() -> np.ndarray:
    box, _ = scene_base()
    uv, ok = CAMERA.project(transform_points(np.linalg.inv(T_BASE_CAM), box))
    u0, v0 = np.floor(uv[ok].min(0)).astype(int) - 2
    u1, v1 = np.ceil(uv[ok].max(0)).astype(int) + 2
    m = np.zeros((H, W), bool)
    m[max(v0, 0):v1 + 1, max(u0, 0):u1 + 1] = True
    return m


class FakeVlm:
    """A backend that calls the box movable at the given cost (or fails)."""

    name = "fake"

    def __init__(self, cost: float = 2.0, fail: bool = False) -> None:
        self.cost, self.fail, self.calls = cost, fail, 0

    def query(self, request: VlmRequest) -> VlmAnswer:
        self.calls += 1
        if self.fail:
            return VlmAnswer(request.stamp_s, request.camera_pose_odom, (), self.name, 0.0, error="down")
        obj = DetectedObject(box_mask(), "box", True, self.cost, 0.9)
        return VlmAnswer(request.stamp_s, request.camera_pose_odom, (obj,), self.name, 0.0)


def image_at(t: float) -> CameraImage:
    return CameraImage(stamp_s=t, pixels=np.zeros((H, W, 3), np.uint8), K=K, distortion=np.zeros(5))


def make(backend) -> VppStage:
    runner = BackendRunner(backend, BackendRunnerConfig(clock="lockstep", latency_s=0.5))
    return VppStage(VppConfig(), CAMERA, T_BASE_CAM, T_BASE_LIDAR, runner)


def test_points_are_fixed_until_the_answer_arrives_then_the_box_is_movable():
    backend = FakeVlm(cost=2.0)
    stage = make(backend)
    scan, n_box = scan_at(0.0)
    frame = stage.update(0.0, (0.0, 0.0, 0.0), image_at(0.0), scan)
    assert stage.requests == 1 and frame.movable_count == 0 and frame.fixed.all()
    frame = stage.update(0.3, (0.0, 0.0, 0.0), None, scan_at(0.3)[0])
    assert frame.movable_count == 0  # the answer is due at 0.5 s (simulated latency)
    stage.settle(0.55)
    frame = stage.update(0.55, (0.0, 0.0, 0.0), None, scan_at(0.55)[0])
    assert stage.answers == 1 and frame.masks_used == 1
    label = frame.partition.label
    assert (label[:n_box] == MOVABLE).mean() > 0.9  # the box
    assert not (label[n_box:] == MOVABLE).any()  # the wall behind it, seen through the mask's edge
    assert np.all(frame.partition.cost[:n_box][label[:n_box] == MOVABLE] == 2.0)
    assert backend.calls == 1


def test_a_fragile_object_stays_fixed_and_a_failing_backend_leaves_everything_fixed():
    for backend in (FakeVlm(cost=9.0), FakeVlm(fail=True)):
        stage = make(backend)
        stage.update(0.0, (0.0, 0.0, 0.0), image_at(0.0), scan_at(0.0)[0])
        stage.settle(0.6)
        frame = stage.update(0.6, (0.0, 0.0, 0.0), None, scan_at(0.6)[0])
        assert frame.movable_count == 0 and frame.fixed.all()
    assert stage.failed_answers == 1


def test_no_new_request_while_one_is_in_flight_or_before_the_trigger():
    backend = FakeVlm()
    stage = make(backend)
    stage.update(0.0, (0.0, 0.0, 0.0), image_at(0.0), scan_at(0.0)[0])
    stage.update(0.2, (0.0, 0.0, 0.0), image_at(0.2), None)  # in flight: not sent
    assert stage.requests == 1
    stage.settle(0.6)
    stage.update(0.6, (0.0, 0.0, 0.0), image_at(0.6), None)  # memory not empty, not moved, t < t_thres
    assert stage.requests == 1
    stage.update(1.0, (0.6, 0.0, 0.0), image_at(1.0), None)  # moved 0.6 m > d_thres 0.5 m
    assert stage.requests == 2


def test_an_image_from_another_camera_is_refused_naming_it_and_the_tick_goes_on():
    stage = make(FakeVlm())
    other = CameraImage(stamp_s=0.0, pixels=np.zeros((H, W, 3), np.uint8), K=K * np.array([[2, 1, 1], [1, 2, 1], [1, 1, 1]]))
    frame = stage.update(0.0, (0.0, 0.0, 0.0), other, scan_at(0.0)[0])
    assert frame is not None and frame.fixed.all() and stage.requests == 0
    assert stage.images_refused == 1 and "does not match the calibrated camera" in stage.last_rejection


def test_without_any_answer_the_wait_ends_after_the_timeout_and_says_so():
    stage = make(FakeVlm())  # no image ever: no request, no answer
    assert not stage.ready(0.0) and not stage.ready(4.9)
    assert stage.ready(5.1) and stage.gave_up_waiting


def test_the_plane_points_of_a_request_are_the_scan_in_the_capture_camera_frame():
    """The scan placed in the odom frame with its own pose, then in the camera at capture: a scan
    taken 0.3 m further on still lands where the capture camera sees those points."""
    stage = make(FakeVlm())
    scan, n_box = scan_at(0.0)
    stage.update(0.0, (0.3, 0.0, 0.0), None, scan)  # the scan, from 0.3 m ahead
    stage.update(0.05, (0.0, 0.0, 0.0), image_at(0.05), None)  # the image, captured at 0
    (pts,) = stage._points_cam_at.values()
    from calibration.camera_model import transform_points

    box, _ = scene_base()
    expect = transform_points(np.linalg.inv(T_BASE_CAM), box + [0.3, 0.0, 0.0])
    np.testing.assert_allclose(pts[:n_box], expect, atol=1e-5)


def test_a_mask_the_warp_swells_is_not_trusted():
    """Driving up to the box (1.5 m ahead) the plane warp enlarges its mask as the box nears; past
    max_mask_growth (2.5x the captured area, about 0.9 m closer) its points go back to P_fix,
    before the mask can swell over the image and gate fixed points as movable."""
    stage = make(FakeVlm())
    stage.update(0.0, (0.0, 0.0, 0.0), image_at(0.0), scan_at(0.0)[0])
    stage.settle(0.6)
    near = stage.update(0.6, (0.3, 0.0, 0.0), None, scan_at(0.6)[0])
    assert near.masks_used == 1 and stage.masks_distrusted == 0
    close = stage.update(0.7, (1.0, 0.0, 0.0), None, scan_at(0.7)[0])
    assert close.masks_used == 0 and stage.masks_distrusted == 1


def test_phase_two_image_work_runs_beside_the_tick_and_the_tick_only_applies_it(monkeypatch):
    """The planes, warps and IoU of an answer are computed where the backend ran (lockstep: in
    settle, the simulator's barrier; real time: the runner's worker), never in update; an answer
    for a memory that already holds the box matches it (same id) after a second answer."""
    from runtime.vpp import mask_memory

    stage = make(FakeVlm(cost=2.0))
    in_update, prepared_in = [False], []
    real_prepare, real_update = mask_memory.AnswerPreparer.prepare, VppStage.update

    def prepare(self, *a, **k):
        prepared_in.append("update" if in_update[0] else "beside")
        return real_prepare(self, *a, **k)

    def update(self, *a, **k):
        in_update[0] = True
        try:
            return real_update(self, *a, **k)
        finally:
            in_update[0] = False

    monkeypatch.setattr(mask_memory.AnswerPreparer, "prepare", prepare)
    monkeypatch.setattr(VppStage, "update", update)
    stage.update(0.0, (0.0, 0.0, 0.0), image_at(0.0), scan_at(0.0)[0])
    stage.settle(0.55)
    assert prepared_in == ["beside"]
    frame = stage.update(0.55, (0.0, 0.0, 0.0), image_at(0.55), scan_at(0.55)[0])
    assert stage.answers == 1 and frame.masks_used == 1
    first_id = stage.memory.entries[0].object_id
    stage.update(2.7, (0.0, 0.0, 0.0), image_at(2.7), scan_at(2.7)[0])  # t_thres passed: asks again
    stage.settle(3.25)
    stage.update(3.25, (0.0, 0.0, 0.0), None, scan_at(3.25)[0])
    assert stage.answers == 2 and prepared_in == ["beside", "beside"]
    assert [e.object_id for e in stage.memory.entries] == [first_id]  # matched by IoU, not re-inserted
    assert stage.last_reconcile.matched and not stage.last_reconcile.inserted


def test_the_real_time_runner_prepares_phase_two_in_its_worker_thread():
    import threading
    import time

    seen = []

    runner = BackendRunner(FakeVlm(), BackendRunnerConfig(clock="realtime", latency_s=0.0, timeout_s=5.0))
    stage = VppStage(VppConfig(), CAMERA, T_BASE_CAM, T_BASE_LIDAR, runner)
    real = stage._preparer.prepare

    def prepare(*a, **k):
        seen.append(threading.current_thread() is threading.main_thread())
        return real(*a, **k)

    stage._preparer.prepare = prepare
    stage.update(0.0, (0.0, 0.0, 0.0), image_at(0.0), scan_at(0.0)[0])
    deadline = time.monotonic() + 10.0
    while stage.answers == 0 and time.monotonic() < deadline:
        time.sleep(0.02)
        stage.update(0.1, (0.0, 0.0, 0.0), None, scan_at(0.1)[0])
    stage.close()
    assert stage.answers == 1 and stage.rejected_answers == 0
    assert seen == [False]  # in the worker, not in the tick's thread
    assert len(stage.memory.entries) == 1


def test_a_frame_that_arrives_a_tick_after_its_capture_carries_the_capture_pose():
    """The camera frame captured at 0 reaches the tick at 0.05, when the robot is 5 cm further on:
    its request (and so its masks' warp) is tagged with the pose at capture the caller gives
    (image_pose), not the tick's; without one, the tick's."""
    from runtime.vpp.stage import pose_matrix

    for image_pose, expect_x in (((0.0, 0.0, 0.0), 0.0), (None, 0.05)):
        backend = FakeVlm()
        stage = make(backend)
        seen = []
        backend.query = lambda request, q=backend.query: (seen.append(request.camera_pose_odom), q(request))[1]
        stage.update(0.05, (0.05, 0.0, 0.0), image_at(0.0), scan_at(0.05)[0], image_pose)
        stage.settle(0.6)
        stage.update(0.6, (0.05, 0.0, 0.0), None, scan_at(0.6)[0])
        (T,) = seen
        np.testing.assert_allclose(T, pose_matrix(expect_x, 0.0, 0.0) @ T_BASE_CAM, atol=1e-12)


@pytest.mark.parametrize("follow", [True, False])
def test_a_box_pushed_between_two_answers_keeps_its_entry(follow, monkeypatch):
    """The robot stands (two answers: the tracker follows the box), then pushes it at 1 m/s (the
    scan the same in the base frame: the box moves with the robot) until the next capture. The
    tracker's motion of the box moves its remembered mask with it, so the next answer's mask of
    it matches its entry; warped as a still plane it would not."""
    stage = make(FakeVlm())
    if not follow:
        monkeypatch.setattr(stage.tracker, "moved_objects", lambda since, t1_s: {})
    reconciles = []
    for k in range(80):  # 4 s of ticks at 20 Hz, a scan every other tick, an image every tick
        t = 0.05 * k
        stage.settle(t)
        answers = stage.answers
        x = max(0.0, t - 2.0)
        stage.update(t, (x, 0.0, 0.0), image_at(t), scan_at(t)[0] if k % 2 == 0 else None)
        if stage.answers > answers:  # (how far the box was pushed at the capture, the reconcile)
            reconciles.append((max(0.0, stage.delivered[-1].stamp_s - 2.0), stage.last_reconcile))
    pushed = [r for x, r in reconciles if x > 0.5]
    assert len(reconciles) >= 3 and pushed  # answers standing, and one captured after 0.5 m of pushing
    r = pushed[0]
    if follow:
        assert len(r.matched) == 1 and r.inserted == () and r.dropped == ()
    else:
        assert r.matched == () and len(r.inserted) == 1
