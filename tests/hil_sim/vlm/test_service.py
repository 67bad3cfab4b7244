"""The sim-oracle served over HTTP (hil_sim.vlm.service), asked by our real clients: the
openai-compatible backend with grounding-http regions (models.vlm.factory), over a real socket.
Its answer about a rendered frame is the lockstep sim-oracle's answer about the same frame
(labels, movability, costs, masks pixel for pixel); bad requests get HTTP 400 naming why."""
from __future__ import annotations

import json
import urllib.error
import urllib.request

import numpy as np
import pytest

from calibration.robot_description import load_robot_description
from hil_sim.episode.faults import FaultInjector, FaultSpec
from hil_sim.vlm.service import STAMP_HEADER, OracleService
from hil_sim.vlm.oracle import oracle_backend, oracle_request
from tests.hil_sim.vlm.test_oracle import _render
from models.vlm.factory import OpenAICompatibleBackendConfig, build_backend
from models.vlm.grounding_http import GroundingHttpConfig, GroundingHttpProposer
from models.vlm.interface import VlmRequest
from models.vlm.sim_oracle import SimOracleConfig

ROBOT = load_robot_description()
ROS_STAMP = 1_700_000_123.25  # the stamp the frame is published with (ROS time)


@pytest.fixture(scope="module")
def frame():
    return _render("case1")  # (world, the rendered CameraImage with segmentation)


def _service(world, image, **oracle) -> OracleService:
    service = OracleService.for_world(world, SimOracleConfig(**{"latency_s": 0.0, **oracle})).start()
    service.record(image, ROS_STAMP)
    return service


def _client(service: OracleService):
    return build_backend(OpenAICompatibleBackendConfig(
        base_url=f"{service.base_url}/v1", model="sim-oracle", timeout_s=10.0, max_retries=0, image_format="png",
        regions={"kind": "grounding-http", "base_url": service.base_url, "return_masks": True, "max_retries": 0,
                 "image_format": "png", "fallback_opencv": False}))


def _request(image, stamp=ROS_STAMP) -> VlmRequest:
    return VlmRequest(image=image.pixels, stamp_s=stamp, camera_pose_odom=np.eye(4), prompt="reach the goal")


def test_http_answer_is_the_lockstep_oracles_answer(frame):
    world, image = frame
    service = _service(world, image)
    try:
        answer = _client(service).query(_request(image))
    finally:
        service.close()
    assert answer.error is None, answer.error
    truth = oracle_backend(world, SimOracleConfig(latency_s=0.0)).query(
        oracle_request(image, np.eye(4))).objects
    assert any(o.movable for o in truth) and any(not o.movable for o in truth)
    got = {o.label: o for o in answer.objects}
    assert sorted(got) == sorted(o.label for o in truth)
    for t in truth:
        o = got[t.label]
        assert (o.movable, o.contact_cost, o.confidence) == (t.movable, t.contact_cost, t.confidence), t.label
        assert np.array_equal(o.mask, t.mask), t.label
    assert service.stats()["chat"] == 1 and service.stats()["detect"] == 1


def test_frame_found_by_image_without_stamp_and_knobs_apply(frame):
    world, image = frame
    service = _service(world, image, recall=0.0, latency_s=0.3)
    try:
        regions = GroundingHttpProposer(GroundingHttpConfig(base_url=service.base_url, return_masks=True)).propose(
            image.pixels, "box .")  # no stamp: the frame is recognised by its image
        assert sorted(r.label_hint for r in regions) == sorted(
            o.label for o in oracle_backend(world).query(oracle_request(image, np.eye(4))).objects)
        answer = _client(service).query(_request(image))
        assert answer.error is None and answer.objects
        assert not any(o.movable for o in answer.objects)  # recall 0: every movable object dropped
        assert answer.latency_s >= 0.3  # the oracle's latency is the service's answer time
    finally:
        service.close()
    failing = _service(world, image, failure_rate=1.0)
    try:
        answer = _client(failing).query(_request(image))
    finally:
        failing.close()
    assert answer.error is not None and "HTTP 503" in answer.error and not answer.objects


def _post(url: str, body, headers=None) -> tuple[int, dict]:
    data = body if isinstance(body, bytes) else json.dumps(body).encode()
    req = urllib.request.Request(url, data=data, headers={"Content-Type": "application/json", **(headers or {})})
    try:
        with urllib.request.urlopen(req, timeout=10) as r:
            return r.status, json.loads(r.read())
    except urllib.error.HTTPError as e:
        return e.code, json.loads(e.read())


def test_bad_requests_are_400_with_a_message(frame):
    world, image = frame
    service = _service(world, image)
    base = service.base_url
    try:
        good_detect, _ = GroundingHttpProposer(GroundingHttpConfig(base_url=base)).build_body(image.pixels, "box .")
        cases = [
            (f"{base}/detect", b"{not json", None, "not JSON"),
            (f"{base}/detect", [1, 2], None, "JSON object"),
            (f"{base}/detect", {k: v for k, v in good_detect.items() if k != "image"}, None, "missing 'image'"),
            (f"{base}/detect", {**good_detect, "width": 3}, None, "is not the image's"),
            (f"{base}/detect", {**good_detect, "image": "%%%"}, None, "base64"),
            (f"{base}/detect", good_detect, {STAMP_HEADER: "12.5"}, "no kept frame has that stamp"),
            (f"{base}/detect", good_detect, {STAMP_HEADER: "soon"}, "is not a number"),
            (f"{base}/v1/chat/completions", {"model": "x", "messages": []}, None, "'messages'"),
            (f"{base}/v1/chat/completions", {"model": "x", "messages": [{"role": "user", "content": "hi"}]}, None,
             "image_url"),
        ]
        for url, body, headers, why in cases:
            status, payload = _post(url, body, headers)
            assert status == 400 and why in payload["error"]["message"], (why, payload)
        # A mark whose hint names no object of the simulator (regions the oracle did not propose).
        from models.vlm.interface import CandidateRegion
        from models.vlm.openai_compatible import OpenAICompatibleConfig, build_body
        from models.vlm.set_of_mark import draw_marks, encode_data_url

        m = np.zeros(image.pixels.shape[:2], bool)
        m[10:40, 10:50] = True
        req = VlmRequest(image=image.pixels, stamp_s=ROS_STAMP, camera_pose_odom=np.eye(4), prompt="p",
                         regions=(CandidateRegion(mask=m, box_xyxy=(10, 10, 50, 40), score=0.5, label_hint="chair"),))
        body = build_body(OpenAICompatibleConfig(base_url=f"{base}/v1", model="x"), req,
                          encode_data_url(draw_marks(image.pixels, req.regions), "png", 90))
        status, payload = _post(f"{base}/v1/chat/completions", body, {STAMP_HEADER: repr(ROS_STAMP)})
        assert status == 400 and "mark 1" in payload["error"]["message"] and "'chair'" in payload["error"]["message"]
        status, payload = _post(f"{base}/v1/embeddings", {"input": "x"})
        assert status == 404 and "no such endpoint" in payload["error"]["message"]
        assert service.stats()["bad_request"] == len(cases) + 1
    finally:
        service.close()


def _faulty(service: OracleService, name: str) -> FaultInjector:
    """The simulator's injector with `name` on from the start (as `dct hil serve --fault` gives it)."""
    service.faults = FaultInjector((FaultSpec(name, 0.0, 10.0),), None, None, start_s=0.0, far_m=10.0)
    return service.faults


def test_the_vlm_faults_go_over_the_wire_and_our_client_names_them(frame, caplog):
    """vlm-error answers 503 on both endpoints; vlm-garbage sends masks the wrong size for the image,
    which our client drops, naming why; each request the fault acted on is counted."""
    world, image = frame
    service = _service(world, image)
    try:
        inj = _faulty(service, "vlm-error")
        status, body = _post(f"{service.base_url}/detect", {"image": "", "prompt": "x", "width": 1, "height": 1})
        assert status == 503 and "vlm-error" in body["error"]["message"]
        answer = _client(service).query(_request(image))
        assert answer.error is not None and "503" in answer.error and not answer.objects
        assert inj.applied["vlm-error"] >= 2
        inj = _faulty(service, "vlm-garbage")
        answer = _client(service).query(_request(image))
        assert not answer.objects and answer.error == "no candidate regions to ask about", answer.error
        assert "mask PNG is" in caplog.text and "the sent image is" in caplog.text
        assert inj.applied["vlm-garbage"] == 1
        service.faults = None
        assert _client(service).query(_request(image)).objects  # the fault off: answers again
    finally:
        service.close()


def test_vlm_stale_answers_about_a_frame_five_seconds_older(frame):
    world, image = frame
    service = _service(world, image)
    try:
        asked = service.ring.find(ROS_STAMP, image.pixels)
        assert service.ring.older(asked, 5.0) is asked  # only one frame kept: the oldest there is
        service.record(image, ROS_STAMP + 6.0)
        newest = service.ring.find(ROS_STAMP + 6.0, image.pixels)
        assert service.ring.older(newest, 5.0).stamp_s == pytest.approx(ROS_STAMP)
        inj = _faulty(service, "vlm-stale")
        answer = _client(service).query(_request(image, stamp=ROS_STAMP + 6.0))
        assert answer.error is None and answer.objects and inj.applied["vlm-stale"] == 2  # /detect and chat
    finally:
        service.close()
