"""Candidate-region proposers: the OpenCV fallback (synthetic and real image) and the grounding
detector client against a scripted local HTTP server (no real network, no model weights).

Time bounds here are hang guards with generous slack for a slow shared machine, never
performance assertions.
"""
from __future__ import annotations

import base64
import json
import time
from pathlib import Path

import cv2
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from pydantic import ValidationError

from models.vlm.grounding_http import (
    GroundingHttpConfig,
    GroundingHttpProposer,
    decode_mask,
    detector_prompt,
    parse_detections,
)
from models.vlm.interface import CandidateRegion
from models.vlm.regions import (
    OpenCvProposer,
    absorb_small_regions,
    depth_edges,
    OpenCvProposerConfig,
    RegionProposalError,
    RegionProposer,
    SparseDepth,
    mask_box,
)
from tests.models import http_fakes
from tests.models.http_fakes import Behaviour, ScriptedServer, close_connection, hang, send

PANDAR = Path(__file__).resolve().parents[1] / "data" / "real" / "pandar64_camera_opencalib"
SLACK_S = 3.0


def iou(a: np.ndarray, b: np.ndarray) -> float:
    return float((a & b).sum()) / float((a | b).sum())


def assert_valid_region(r: CandidateRegion, hw: tuple[int, int]) -> None:
    assert isinstance(r.mask, np.ndarray) and r.mask.dtype == np.bool_ and r.mask.shape == hw
    assert r.mask.any()
    assert r.box_xyxy == mask_box(r.mask)
    x0, y0, x1, y1 = r.box_xyxy
    assert 0 <= x0 < x1 <= hw[1] and 0 <= y0 < y1 <= hw[0]
    assert 0.0 <= r.score <= 1.0
    assert r.depth_m is None or (np.isfinite(r.depth_m) and r.depth_m > 0)


# ----------------------------------------------------------------------------- synthetic scene

H, W = 360, 480
BOXES = [((60, 150, 140, 260), (200, 40, 40)), ((200, 200, 300, 300), (40, 60, 200)), ((340, 120, 420, 240), (40, 170, 60))]
BOX_DEPTH_M = [1.5, 2.0, 3.0]
BACKGROUND_DEPTH_M = 6.0


def synthetic_scene(seed: int = 0) -> tuple[np.ndarray, list[np.ndarray]]:
    """A noisy wall over a noisy floor with dark floorboard lines, three coloured boxes on it."""
    rng = np.random.default_rng(seed)
    img = np.zeros((H, W, 3), np.int64)
    img[: H // 2] = (200, 195, 185)
    img[H // 2:] = (120, 100, 80)
    img += rng.integers(-25, 26, (H, W, 1))
    for x in range(0, W, 40):
        img[H // 2:, x:x + 2] = (90, 75, 60)
    masks = []
    for (x0, y0, x1, y1), c in BOXES:
        img[y0:y1, x0:x1] = np.array(c) + rng.integers(-10, 11, (y1 - y0, x1 - x0, 1))
        m = np.zeros((H, W), bool)
        m[y0:y1, x0:x1] = True
        masks.append(m)
    return np.clip(img, 0, 255).astype(np.uint8), masks


def synthetic_depth(masks: list[np.ndarray], step: int = 6, depths=BOX_DEPTH_M) -> SparseDepth:
    """A lidar-like grid of points: each box at its depth, the rest at the background depth."""
    v, u = np.mgrid[1:H:step, 2:W:step]
    u, v = u.ravel().astype(float), v.ravel().astype(float)
    d = np.full(u.shape, BACKGROUND_DEPTH_M)
    for m, z in zip(masks, depths, strict=True):
        d[m[v.astype(int), u.astype(int)]] = z
    # A few points that must be ignored: behind the camera, NaN, outside the image.
    u = np.concatenate([u, [10.0, np.nan, -50.0, W + 40.0]])
    v = np.concatenate([v, [10.0, 10.0, 10.0, 10.0]])
    d = np.concatenate([d, [-1.0, 2.0, 2.0, 2.0]])
    return SparseDepth(uv=np.stack([u, v], axis=1), depth_m=d)


def test_opencv_proposer_finds_each_box_as_one_region_with_its_depth():
    img, masks = synthetic_scene()
    regions = OpenCvProposer().propose(img, "what may the robot push?", synthetic_depth(masks))
    assert 3 <= len(regions) <= OpenCvProposerConfig().max_regions
    for r in regions:
        assert_valid_region(r, (H, W))
    for m, z in zip(masks, BOX_DEPTH_M):
        ious = [iou(r.mask, m) for r in regions]
        best = int(np.argmax(ious))
        assert ious[best] >= 0.8, ious
        # one region per box: no other region covers a noticeable part of it
        assert sorted(ious)[-2] < 0.1 if len(ious) > 1 else True
        assert regions[best].depth_m == pytest.approx(z)
        assert regions[best].label_hint is None
    # The three boxes are the largest compact regions: they rank first.
    top3 = {int(np.argmax([iou(r.mask, m) for r in regions])) for m in masks}
    assert top3 == {0, 1, 2}


def test_lidar_depth_jumps_separate_a_box_the_colour_of_the_floor():
    img, masks = synthetic_scene()
    x0, y0, x1, y1 = 370, 250, 450, 330  # a floor-coloured box on the floor, no lines across it
    rng = np.random.default_rng(5)
    img[y0:y1, x0:x1] = np.clip(np.array((120, 100, 80)) + rng.integers(-25, 26, (y1 - y0, x1 - x0, 1)), 0, 255)
    hidden = np.zeros((H, W), bool)
    hidden[y0:y1, x0:x1] = True
    depth = synthetic_depth(masks + [hidden], depths=[*BOX_DEPTH_M, 2.5])

    def best(regions, m):
        ious = [iou(r.mask, m) for r in regions]
        return max(ious), regions[int(np.argmax(ious))]

    without, _ = best(OpenCvProposer().propose(img, ""), hidden)
    regions = OpenCvProposer().propose(img, "", depth)
    with_depth, r = best(regions, hidden)
    assert without < 0.6 and with_depth >= 0.75, (without, with_depth)
    assert r.depth_m == pytest.approx(2.5)
    for m in masks:  # the coloured boxes are still found
        assert best(regions, m)[0] >= 0.8
    off = OpenCvProposer(OpenCvProposerConfig(depth_jump_frac=None)).propose(img, "", depth)
    assert best(off, hidden)[0] == pytest.approx(without)

    e = depth_edges(depth, (H, W), (H // 2, W // 2), 0.25, 10.0)
    assert e.shape == (H // 2, W // 2) and e.any()
    assert not e[5:55, 5:235].any()  # the wall above the boxes has no jump
    assert e[125:165, 183:187].any()  # the left side of the hidden box (x = 370 at full size) has one


def test_absorb_small_regions_merges_fragments_into_the_closest_coloured_neighbour():
    labels = np.ones((10, 12), np.int32)
    labels[:, 6:] = 2
    labels[4:6, 4:6] = 3  # a fragment touching 1 and 2 (4 border pixels with 1, 2 with 2)
    labels[0, 0] = 0  # "no region" stays
    feats = np.zeros((10, 12, 1))
    feats[:, 6:] = 10.0
    feats[4:6, 4:6] = 9.0  # coloured like region 2
    out = absorb_small_regions(labels, min_area=5, features=feats)
    assert (out[4:6, 4:6] == 2).all() and out[0, 0] == 0 and set(np.unique(out)) == {0, 1, 2}
    out = absorb_small_regions(labels, min_area=5)  # no colours: the longest border wins
    assert (out[4:6, 4:6] == 1).all()
    np.testing.assert_array_equal(absorb_small_regions(labels, min_area=1), labels)


def test_opencv_proposer_is_deterministic_and_honours_max_regions_and_depth_pairs():
    img, masks = synthetic_scene(seed=3)
    a = OpenCvProposer().propose(img, "")
    b = OpenCvProposer().propose(img.copy(), "")
    assert len(a) == len(b)
    for ra, rb in zip(a, b):
        np.testing.assert_array_equal(ra.mask, rb.mask)
        assert ra.box_xyxy == rb.box_xyxy and ra.score == rb.score
    assert all(r.depth_m is None for r in a)

    two = OpenCvProposer(OpenCvProposerConfig(max_regions=2)).propose(img, "")
    assert len(two) == 2
    for r, r_full in zip(two, a):
        np.testing.assert_array_equal(r.mask, r_full.mask)

    sd = synthetic_depth(masks)
    as_pair = OpenCvProposer().propose(img, "", (sd.uv, sd.depth_m))
    assert [r.depth_m for r in as_pair] == [r.depth_m for r in OpenCvProposer().propose(img, "", sd)]


def test_opencv_proposer_on_a_blank_image_proposes_nothing_and_rejects_bad_input():
    assert OpenCvProposer().propose(np.full((100, 120, 3), 128, np.uint8), "") == ()
    with pytest.raises(RegionProposalError, match="image"):
        OpenCvProposer().propose(np.zeros((100, 120), np.uint8), "")
    with pytest.raises(RegionProposalError, match="image"):
        OpenCvProposer().propose(np.zeros((100, 120, 3), np.float32), "")
    img, _ = synthetic_scene()
    with pytest.raises(RegionProposalError, match="depth"):
        OpenCvProposer().propose(img, "", (np.zeros((5, 3)), np.zeros(5)))
    with pytest.raises(RegionProposalError, match="depth_m"):
        OpenCvProposer().propose(img, "", SparseDepth(uv=np.zeros((5, 2)), depth_m=np.zeros(4)))


def test_opencv_config_is_strict():
    with pytest.raises(ValidationError, match="extra"):
        OpenCvProposerConfig(n_clusters=4)
    with pytest.raises(ValidationError, match="odd"):
        OpenCvProposerConfig(blur_px=4)
    with pytest.raises(ValidationError, match="min_area_frac"):
        OpenCvProposerConfig(min_area_frac=0.3, max_area_frac=0.2)
    with pytest.raises(ValidationError, match="canny_low"):
        OpenCvProposerConfig(canny_low=200, canny_high=100)


def test_proposers_satisfy_the_protocol():
    def use(p: RegionProposer) -> str:
        return p.name

    assert use(OpenCvProposer()) == "opencv"
    assert use(GroundingHttpProposer(GroundingHttpConfig(base_url="http://127.0.0.1:9"))) == "grounding-http"


# ---------------------------------------------------------------------------------- real image

@pytest.fixture(scope="module")
def real_image_and_depth():
    from calibration.calibration_file import calibration_from_opencalib
    from calibration.pointcloud_io import load_point_cloud

    bgr = cv2.imread(str(PANDAR / "0.png"), cv2.IMREAD_COLOR)
    assert bgr is not None
    calib = calibration_from_opencalib(PANDAR / "center_camera-intrinsic.json",
                                       PANDAR / "top_center_lidar-to-center_camera-extrinsic.json", 1920, 1200)
    depth = SparseDepth.from_lidar(calib.camera_model(), load_point_cloud(PANDAR / "0.pcd").xyz, calib.T_cam_lidar())
    return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB), depth


def test_opencv_proposer_on_the_real_image_with_real_lidar_depth(real_image_and_depth):
    img, depth = real_image_and_depth
    assert 5000 < len(depth.depth_m) < 10_000  # README: 9,954 points project inside the image
    cfg = OpenCvProposerConfig()
    t0 = time.monotonic()
    regions = OpenCvProposer(cfg).propose(img, "drive to the crossing", depth)
    elapsed = time.monotonic() - t0
    print(f"opencv proposer on 1920x1200: {len(regions)} regions in {elapsed:.2f} s")
    assert elapsed < 60.0  # hang guard only (about 0.2 s on a quiet machine)
    assert 1 <= len(regions) <= cfg.max_regions
    for r in regions:
        assert_valid_region(r, img.shape[:2])
        assert cfg.min_area_frac * 0.9 <= r.mask.mean() <= cfg.max_area_frac * 1.1
    with_depth = [r.depth_m for r in regions if r.depth_m is not None]
    assert with_depth and all(0.5 < z < 250.0 for z in with_depth)


# ----------------------------------------------------------------------------- the fake server

FakeDetector = ScriptedServer


def drip(server: ScriptedServer, interval_s: float) -> Behaviour:
    return http_fakes.drip(server, interval_s, json.dumps({"detections": []}).encode() + b" " * 40)


@pytest.fixture
def server():
    s = ScriptedServer("/gd")
    yield s
    s.close()


def proposer(server: FakeDetector, **kw) -> GroundingHttpProposer:
    cfg = dict(base_url=server.base_url, timeout_s=2.0, max_retries=2, backoff_s=0.02)
    cfg.update(kw)
    return GroundingHttpProposer(GroundingHttpConfig(**cfg))


def png_b64(mask: np.ndarray) -> str:
    ok, buf = cv2.imencode(".png", mask.astype(np.uint8) * 255)
    assert ok
    return base64.b64encode(buf.tobytes()).decode()


def coco_rle(mask: np.ndarray) -> dict:
    flat = mask.T.ravel().astype(np.int8)  # column-major
    change = np.flatnonzero(np.diff(flat)) + 1
    bounds = np.concatenate([[0], change, [flat.size]])
    counts = np.diff(bounds).tolist()
    if flat[0]:
        counts = [0] + counts
    return {"size": list(mask.shape), "counts": counts}


# ---------------------------------------------------------------------------- detector answers

def test_good_answer_scales_boxes_and_masks_back_and_sends_the_documented_request(server):
    img, masks = synthetic_scene()
    sent_hw = (H // 2, W // 2)  # max_image_side_px = W / 2 halves the image
    small = [cv2.resize(m.astype(np.uint8), sent_hw[::-1], interpolation=cv2.INTER_NEAREST).astype(bool) for m in masks]
    dets = [
        {"box_xyxy": [30, 75, 70, 130], "score": 0.5, "label": "red box"},  # box only
        {"box_xyxy": [100.0, 100.0, 150.0, 150.0], "score": 0.9, "label": "blue box", "mask": png_b64(small[1])},
        {"box_xyxy": [170, 60, 210, 120], "score": 0.7, "label": None, "mask": coco_rle(small[2]), "extra": 1},
    ]
    server.script = [send(200, {"detections": dets})]
    p = proposer(server, max_image_side_px=W // 2, image_format="png", box_threshold=0.3, text_threshold=0.2)
    got = p.detect(img, "red box . blue box . green box .", synthetic_depth(masks))
    assert got.rejected == () and got.attempts == 1
    regions = got.regions
    assert [r.label_hint for r in regions] == ["blue box", None, "red box"]  # by score
    assert [r.score for r in regions] == [0.9, 0.7, 0.5]
    for r in regions:
        assert_valid_region(r, (H, W))
    assert iou(regions[0].mask, masks[1]) >= 0.95 and iou(regions[1].mask, masks[2]) >= 0.95
    assert regions[2].box_xyxy == (60, 150, 140, 260) and regions[2].mask.sum() == 80 * 110
    assert [r.depth_m for r in regions] == pytest.approx([2.0, 3.0, 1.5])

    sent = server.requests[0]
    assert sent["path"] == "/gd/detect"
    body = sent["body"]
    assert body["prompt"] == "red box . blue box . green box ."
    assert (body["box_threshold"], body["text_threshold"], body["return_masks"]) == (0.3, 0.2, False)
    assert (body["height"], body["width"], body["image_format"]) == (*sent_hw, "png")
    decoded = cv2.imdecode(np.frombuffer(base64.b64decode(body["image"]), np.uint8), cv2.IMREAD_COLOR)
    assert decoded.shape == (*sent_hw, 3)
    np.testing.assert_array_equal(decoded[..., ::-1], cv2.resize(img, sent_hw[::-1], interpolation=cv2.INTER_AREA))


def test_bad_detections_are_dropped_and_named_good_ones_kept(server):
    img, masks = synthetic_scene()
    wrong_size = np.zeros((10, 10), bool)
    wrong_size[2:5, 2:5] = True
    dets = [
        {"box_xyxy": [60, 150, 140, 260], "score": 0.8, "label": "red"},  # good
        {"box_xyxy": [-4, -3, 50, 50], "score": 0.6},  # slightly outside: clipped, kept
        {"box_xyxy": [0.1, 0.2, 0.5, 0.6], "score": 0.7},  # normalised coordinates: under a pixel
        {"box_xyxy": [100, 100, 900, 200], "score": 0.6},  # far outside
        {"box_xyxy": [100, 100, 50, 200], "score": 0.6},  # x0 > x1
        {"box_xyxy": [1, 2, 3], "score": 0.6},
        {"box_xyxy": [1, 2, 30, True], "score": 0.6},
        {"box_xyxy": [10, 10, 40, 40], "score": 1.5},
        {"box_xyxy": [10, 10, 40, 40], "score": "0.5"},
        {"box_xyxy": [10, 10, 40, 40], "score": True},
        {"box_xyxy": [10, 10, 40, 40], "score": 0.5, "label": 5},
        {"box_xyxy": [10, 10, 40, 40], "score": 0.5, "mask": png_b64(wrong_size)},
        {"box_xyxy": [10, 10, 40, 40], "score": 0.5, "mask": "%%%not base64"},
        {"box_xyxy": [10, 10, 40, 40], "score": 0.5, "mask": {"size": [H, W], "counts": "abc"}},
        {"box_xyxy": [10, 10, 40, 40], "score": 0.5, "mask": {"size": [H, W], "counts": [5, 5]}},
        {"box_xyxy": [10, 10, 40, 40], "score": 0.5, "mask": png_b64(np.zeros((H, W), bool))},
        {"box_xyxy": [10, 10, 40, 40]},
        "a string",
    ]
    server.script = [send(200, {"detections": dets})]
    got = proposer(server).detect(img, "box .")
    assert [r.score for r in got.regions] == [0.8, 0.6]
    assert got.regions[1].box_xyxy == (0, 0, 50, 50)
    joined = "\n".join(got.rejected)
    assert len(got.rejected) == 16, joined
    for needle in ("detection 2: box_xyxy", "smaller than a pixel", "detection 3: box_xyxy", "outside the 480x360 image", "detection 4:", "not x0 < x1",
                   "detection 5: box_xyxy must be a list of 4 numbers", "detection 6:", "detection 7: score must be in 0..1",
                   "detection 8: score must be a number", "detection 9:", "detection 10: label",
                   "detection 11: mask PNG is 10x10", "detection 12: mask is not valid base64",
                   "detection 13: mask RLE counts", "detection 14: mask RLE counts sum", "detection 15: mask is empty",
                   "detection 16: missing score", "detection 17: expected an object"):
        assert needle in joined, needle


def test_max_detections_keeps_the_best_scores(server):
    img, _ = synthetic_scene()
    dets = [{"box_xyxy": [10 * i, 10, 10 * i + 8, 30], "score": s} for i, s in enumerate([0.1, 0.9, 0.5, 0.7])]
    server.script = [send(200, {"detections": dets})]
    got = proposer(server, max_detections=2).detect(img, "thing .")
    assert [r.score for r in got.regions] == [0.9, 0.7]
    assert len(got.rejected) == 1 and "max_detections" in got.rejected[0] and "[2, 0]" in got.rejected[0]


def test_grabcut_refines_a_loose_box_to_the_object(server):
    img, masks = synthetic_scene()
    server.script = [send(200, {"detections": [{"box_xyxy": [190, 190, 310, 310], "score": 0.8, "label": "blue box"}]})]
    (loose,) = proposer(server).propose(img, "box .")
    (refined,) = proposer(server, refine="grabcut").propose(img, "box .")
    assert iou(refined.mask, masks[1]) >= 0.8
    assert iou(refined.mask, masks[1]) > iou(loose.mask, masks[1])
    # A box over the whole image leaves GrabCut no background to learn from: the box mask.
    server.script = [send(200, {"detections": [{"box_xyxy": [0, 0, W, H], "score": 0.8}]})]
    (whole,) = proposer(server, refine="grabcut").propose(img, "box .")
    assert whole.mask.all()


@pytest.mark.parametrize("payload", [b"<html>oops", b'{"detections": [', b"[1, 2]", b'{"boxes": []}',
                                     b'{"detections": {"box_xyxy": [1, 2, 3, 4]}}', b"\xff\xfe", b"null"])
def test_garbage_answer_is_an_error_without_retry(server, payload):
    img, _ = synthetic_scene()
    server.script = [send(200, payload)]
    with pytest.raises(RegionProposalError, match="grounding-http: response"):
        proposer(server).propose(img, "box .")
    assert len(server.requests) == 1


def test_empty_detections_are_no_regions_not_an_error(server):
    img, _ = synthetic_scene()
    server.script = [send(200, {"detections": []})]
    assert proposer(server).propose(img, "unicorn .") == ()


def test_bad_prompt_or_image_raises_without_a_request(server):
    img, _ = synthetic_scene()
    server.script = [send(200, {"detections": []})]
    with pytest.raises(RegionProposalError, match="prompt"):
        proposer(server).propose(img, "  ")
    with pytest.raises(RegionProposalError, match="image"):
        proposer(server).propose(img[..., :2], "box .")
    assert server.requests == []


# ---------------------------------------------------------------------------- transport faults

def test_hanging_server_is_bounded(server):
    img, _ = synthetic_scene()
    server.script = [hang(server)]
    p = proposer(server, timeout_s=0.4, max_retries=1, backoff_s=0.05)
    t0 = time.monotonic()
    with pytest.raises(RegionProposalError, match="2 attempts"):
        p.propose(img, "box .")
    assert time.monotonic() - t0 < p.config.worst_case_s() + SLACK_S
    assert len(server.requests) == 2


def test_slow_server_beyond_the_timeout_is_bounded(server):
    img, _ = synthetic_scene()
    server.script = [drip(server, interval_s=0.05)]  # ~60 bytes, ~3 s; each read is quick
    p = proposer(server, timeout_s=0.5, max_retries=0)
    t0 = time.monotonic()
    with pytest.raises(RegionProposalError, match="within 0.5 s"):
        p.propose(img, "box .")
    assert time.monotonic() - t0 < p.config.worst_case_s() + SLACK_S


def test_closed_connection_is_retried_then_an_error(server):
    img, _ = synthetic_scene()
    server.script = [close_connection]
    with pytest.raises(RegionProposalError, match="connection failed.*3 attempts"):
        proposer(server).propose(img, "box .")
    assert len(server.requests) == 3


def test_transient_status_then_success_and_client_error_not_retried(server):
    img, _ = synthetic_scene()
    server.script = [send(503, {"error": {"message": "warming up"}}), send(200, {"detections": [
        {"box_xyxy": [10, 10, 40, 40], "score": 0.4, "label": "box"}]})]
    got = proposer(server).detect(img, "box .")
    assert got.attempts == 2 and len(got.regions) == 1
    server.requests.clear()
    server.script = [send(400, {"error": {"message": "prompt too long"}})]
    with pytest.raises(RegionProposalError, match="HTTP 400: prompt too long"):
        proposer(server).propose(img, "box .")
    assert len(server.requests) == 1


def test_oversized_answer_is_an_error(server):
    img, _ = synthetic_scene()
    server.script = [send(200, {"detections": [], "pad": "x" * 5000})]
    with pytest.raises(RegionProposalError, match="larger than 1024 bytes"):
        proposer(server, max_response_bytes=1024).propose(img, "box .")


# ------------------------------------------------------------------------------ config, helpers

def test_config_is_strict_and_helpers():
    with pytest.raises(ValidationError, match="extra"):
        GroundingHttpConfig(base_url="http://h:1", threshold=0.3)
    with pytest.raises(ValidationError, match="base_url"):
        GroundingHttpConfig(base_url="ftp://h")
    with pytest.raises(ValidationError):
        GroundingHttpConfig(base_url="http://h", box_threshold=1.5)
    cfg = GroundingHttpConfig(base_url="http://h:8010/", timeout_s=2, max_retries=2, backoff_s=0.5)
    assert cfg.base_url == "http://h:8010" and cfg.worst_case_s() == pytest.approx(3 * 2 + 0.5 + 1.0)
    assert detector_prompt(["Chair", "cardboard  box.", "", "curtain"]) == "chair . cardboard box . curtain ."
    m = np.zeros((7, 5), bool)
    m[0, 0] = m[3, 1:4] = m[6, 4] = True
    np.testing.assert_array_equal(decode_mask(coco_rle(m), (7, 5)), m)
    np.testing.assert_array_equal(decode_mask(png_b64(m), (7, 5)), m)


# ------------------------------------------------------------------------------- parser fuzzing

json_values = st.recursive(
    st.none() | st.booleans() | st.integers() | st.floats(allow_nan=True, allow_infinity=True) | st.text(max_size=20),
    lambda children: st.lists(children, max_size=4) | st.dictionaries(st.text(max_size=8), children, max_size=4),
    max_leaves=20,
)
# Mostly coordinates near the 8x6 image sent (so many boxes are valid), some wild ones.
coords = st.one_of(st.integers(-1, 9), st.floats(-1, 9), st.integers(-1, 9), st.floats(-1, 9), st.integers(-50, 120),
                   st.integers(min_value=10**300, max_value=10**400), st.floats(allow_nan=True, allow_infinity=True),
                   st.booleans(), st.text(max_size=3))
small_mask = st.lists(st.booleans(), min_size=48, max_size=48).map(lambda b: np.array(b).reshape(6, 8))
masks = st.one_of(json_values, small_mask.map(png_b64), small_mask.map(coco_rle),
                  st.fixed_dictionaries({"size": st.lists(st.integers(-2, 10), max_size=3),
                                         "counts": st.lists(st.integers(-3, 60), max_size=6)}))
near = st.integers(-1, 9) | st.floats(-1, 9)
plausible = st.fixed_dictionaries(
    {"box_xyxy": st.tuples(near, near, near, near).map(lambda b: [min(b[0], b[2]), min(b[1], b[3]), max(b[0], b[2]) + 1,
                                                                 max(b[1], b[3]) + 1]),
     "score": st.floats(0, 1)},
    optional={"label": st.one_of(st.none(), st.sampled_from(["box", "", "chair"])), "mask": masks},
)
detections = st.one_of(
    plausible,
    json_values,
    st.fixed_dictionaries({}, optional={
        "box_xyxy": st.one_of(st.lists(coords, min_size=4, max_size=4), st.lists(coords, min_size=3, max_size=5),
                              json_values),
        "score": st.one_of(st.floats(-0.5, 1.5), json_values),
        "label": st.one_of(json_values, st.sampled_from(["box", "", " ", "x" * 300])),
        "mask": masks,
    }),
)
bodies = st.one_of(
    st.lists(detections, max_size=6).map(lambda d: json.dumps({"detections": d}, default=str).encode()),
    st.binary(max_size=40),
    json_values.map(lambda v: json.dumps(v).encode()),
)


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(body=bodies, refine=st.sampled_from(["box", "grabcut"]))
def test_parser_never_raises_and_returns_only_valid_regions(body, refine):
    cfg = GroundingHttpConfig(base_url="http://h", refine=refine, max_detections=4)
    full_hw, sent_hw = (12, 16), (6, 8)
    sent = np.random.default_rng(0).integers(0, 255, (*sent_hw, 3), dtype=np.uint8)
    depth = SparseDepth(uv=np.array([[3.0, 4.0], [10.0, 8.0], [15.0, 11.0]]), depth_m=np.array([1.0, 2.0, 3.0]))
    parsed = parse_detections(body, full_hw, sent_hw, cfg, sent, depth)
    if parsed.error is not None:
        assert parsed.regions == ()
    assert len(parsed.regions) <= 4
    for r in parsed.regions:
        assert_valid_region(r, full_hw)
    assert [r.score for r in parsed.regions] == sorted((r.score for r in parsed.regions), reverse=True)
