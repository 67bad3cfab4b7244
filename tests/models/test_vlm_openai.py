"""The openai-compatible VLM backend against a local chat-completions server (no real network).

The server is started by the test on 127.0.0.1 (port 0) and scripted per request: a good answer,
garbage, a slow (dripping) server, one that hangs, one that closes the connection, 5xx/429 then
200, 400. Bounds are checked against the config's own worst case plus generous slack for a
noisy machine; nothing here is a performance assertion.
"""
from __future__ import annotations

import json
import socket
import time

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from pydantic import ValidationError

from models.vlm.interface import CandidateRegion, VlmRequest, validate_object
from models.vlm.openai_compatible import (
    OpenAICompatibleBackend,
    OpenAICompatibleConfig,
    answer_schema,
    parse_answer,
)
from models.vlm.set_of_mark import PALETTE, decode_data_url, draw_marks, encode_data_url, mark_anchor
from tests.models import http_fakes
from tests.models.http_fakes import Behaviour, ScriptedServer, close_connection, hang, send

H, W = 120, 160
SLACK_S = 3.0  # scheduling noise on a slow shared machine; the bound itself is the config's


# ------------------------------------------------------------------------------- the fake server

FakeChatServer = ScriptedServer
send_json = send


def chat(content) -> Behaviour:
    """A 200 whose choices[0].message.content is `content` (a dict is sent as its JSON text)."""
    text = content if isinstance(content, str) else json.dumps(content)
    return send_json(200, {"id": "x", "object": "chat.completion",
                           "choices": [{"index": 0, "finish_reason": "stop",
                                        "message": {"role": "assistant", "content": text, "refusal": None}}]})


def drip(server: ScriptedServer, interval_s: float) -> Behaviour:
    return http_fakes.drip(server, interval_s, json.dumps({"choices": [{"message": {"content": '{"objects": []}'}}]}).encode())


@pytest.fixture
def server():
    s = ScriptedServer("/v1")
    yield s
    s.close()


# --------------------------------------------------------------------------------- the request

def make_regions() -> tuple[CandidateRegion, ...]:
    masks = []
    m = np.zeros((H, W), bool)
    m[10:40, 10:50] = True
    masks.append(m)
    m = np.zeros((H, W), bool)  # an L shape: its centroid lies outside it
    m[60:110, 20:35] = True
    m[95:110, 20:90] = True
    masks.append(m)
    m = np.zeros((H, W), bool)
    m[20:70, 100:150] = True
    masks.append(m)
    out = []
    for k, m in enumerate(masks):
        ys, xs = np.nonzero(m)
        out.append(CandidateRegion(mask=m, box_xyxy=(int(xs.min()), int(ys.min()), int(xs.max()) + 1, int(ys.max()) + 1),
                                   score=0.8, label_hint=["box", None, "chair"][k], depth_m=[1.2, None, 2.5][k]))
    return tuple(out)


REGIONS = make_regions()


def make_request(regions=REGIONS) -> VlmRequest:
    rng = np.random.default_rng(0)
    image = rng.integers(0, 255, (H, W, 3), dtype=np.uint8)
    pose = np.eye(4)
    pose[:3, 3] = [1.0, 2.0, 0.3]
    return VlmRequest(image=image, stamp_s=12.5, camera_pose_odom=pose, prompt="reach the red door; what may I push?",
                      regions=regions)


def backend(server: FakeChatServer, **kw) -> OpenAICompatibleBackend:
    cfg = dict(base_url=server.base_url, model="qwen-vl", timeout_s=2.0, max_retries=2, backoff_s=0.02)
    cfg.update(kw)
    return OpenAICompatibleBackend(OpenAICompatibleConfig(**cfg))


def obj(mark, label="cardboard box", movable=True, cost=2, conf=0.9) -> dict:
    return {"mark": mark, "label": label, "movable": movable, "contact_cost": cost, "confidence": conf}


# ------------------------------------------------------------------------------------- answers

def test_good_answer_maps_marks_to_region_masks_and_sends_schema_image_and_prompt(server, monkeypatch):
    monkeypatch.setenv("DCT_TEST_VLM_KEY", "sk-test-123")
    server.script = [chat({"objects": [obj(3, "chair", False, 6, 0.7), obj(1)]})]
    req = make_request()
    ans = backend(server, api_key_env="DCT_TEST_VLM_KEY").query(req)

    assert ans.error is None and ans.rejected == ()
    assert ans.backend == "openai-compatible" and ans.stamp_s == 12.5
    np.testing.assert_array_equal(ans.camera_pose_odom, req.camera_pose_odom)
    by_region = {o.region_index: o for o in ans.objects}
    assert set(by_region) == {0, 2}
    np.testing.assert_array_equal(by_region[2].mask, REGIONS[2].mask)
    np.testing.assert_array_equal(by_region[0].mask, REGIONS[0].mask)
    assert (by_region[2].label, by_region[2].movable, by_region[2].contact_cost, by_region[2].confidence) == ("chair", False, 6.0, 0.7)
    assert by_region[0].movable is True and by_region[0].contact_cost == 2.0

    assert len(server.requests) == 1
    sent = server.requests[0]
    assert sent["path"] == "/v1/chat/completions"
    assert sent["headers"]["Authorization"] == "Bearer sk-test-123"
    body = sent["body"]
    assert body["model"] == "qwen-vl"
    rf = body["response_format"]
    assert rf["type"] == "json_schema" and rf["json_schema"]["strict"] is True
    assert rf["json_schema"]["schema"] == answer_schema(3)
    item = rf["json_schema"]["schema"]["properties"]["objects"]["items"]
    assert item["properties"]["mark"]["enum"] == [1, 2, 3]
    assert set(item["required"]) == {"mark", "label", "movable", "contact_cost", "confidence", "deformable"}
    assert item["properties"]["deformable"] == {"type": "boolean"}
    assert item["properties"]["contact_cost"] == {"type": "number", "minimum": 0, "maximum": 10}
    system, user = body["messages"]
    assert system["role"] == "system" and "0 to 10" in system["content"] and "never touch" in system["content"]
    assert "deformable" in system["content"] and "curtain" in system["content"]
    text = next(p["text"] for p in user["content"] if p["type"] == "text")
    assert req.prompt in text and "mark 1: 'box'" in text and "mark 3: 'chair'" in text and "2.5 m" in text
    url = next(p["image_url"]["url"] for p in user["content"] if p["type"] == "image_url")
    assert url.startswith("data:image/jpeg;base64,")
    assert decode_data_url(url).shape == (H, W, 3)
    assert "temperature" not in body and "max_tokens" not in body


def test_no_key_header_without_api_key_env_and_optional_fields_when_set(server):
    server.script = [chat({"objects": []})]
    ans = backend(server, temperature=0.0, max_tokens=500, image_format="png").query(make_request())
    assert ans.error is None and ans.objects == ()
    sent = server.requests[0]
    assert "Authorization" not in sent["headers"]
    assert sent["body"]["temperature"] == 0.0 and sent["body"]["max_tokens"] == 500
    url = sent["body"]["messages"][1]["content"][1]["image_url"]["url"]
    assert url.startswith("data:image/png;base64,")


@pytest.mark.parametrize("content", ["this is not json", '{"objects": [', "[1, 2, 3]", '{"things": []}',
                                     '{"objects": {"mark": 1}}', "null"])
def test_garbage_answer_is_an_error_without_objects_and_without_retry(server, content):
    server.script = [chat(content)]
    ans = backend(server).query(make_request())
    assert ans.error is not None and ans.objects == ()
    assert len(server.requests) == 1


def test_garbage_response_body_and_refusal_are_errors(server):
    def raw(h):
        h.send_response(200)
        h.send_header("Content-Length", "9")
        h.end_headers()
        h.wfile.write(b"<html>hi<")

    server.script = [raw]
    ans = backend(server).query(make_request())
    assert ans.error is not None and "not JSON" in ans.error and ans.objects == ()

    server.requests.clear()
    server.script = [send_json(200, {"choices": [{"message": {"content": None, "refusal": "I cannot help"}}]})]
    ans = backend(server).query(make_request())
    assert ans.error is not None and "refused" in ans.error


def test_bad_objects_are_dropped_and_named_good_ones_kept(server):
    bad_missing = obj(2)
    del bad_missing["confidence"]
    server.script = [chat({"objects": [obj(7), obj(1, cost=12), bad_missing, obj(3, "chair", False, 6, 0.8),
                                       obj(2, movable="yes"), obj(2, cost="3"), obj(2.0), obj(2, conf=1.5), "x"]})]
    ans = backend(server).query(make_request())
    assert ans.error is None
    assert [o.region_index for o in ans.objects] == [2]
    assert len(ans.rejected) == 8
    joined = "\n".join(ans.rejected)
    assert "unknown mark 7" in joined
    assert "mark 1" in joined and "contact_cost" in joined and "12" in joined
    assert "missing confidence" in joined
    assert "movable" in joined and "mark must be an integer" in joined and "confidence must be a number in 0..1" in joined


def test_deformable_is_read_missing_means_rigid_and_a_bad_one_is_dropped(server):
    """`deformable` is in the schema we send; a server that does not enforce it may leave it out
    (rigid: the safe reading). A non-boolean, or a deformable object that may not be moved, is
    dropped and named."""
    curtain = {**obj(1, "curtain", True, 0, 0.9), "deformable": True}
    server.script = [chat({"objects": [curtain, obj(2), {**obj(3), "deformable": "yes"}]})]
    ans = backend(server).query(make_request())
    by_region = {o.region_index: o for o in ans.objects}
    assert by_region[0].deformable is True and by_region[1].deformable is False and set(by_region) == {0, 1}
    assert len(ans.rejected) == 1 and "deformable must be true or false" in ans.rejected[0]
    server.requests.clear()
    server.script = [chat({"objects": [{**obj(1, "wall", False, 10, 0.9), "deformable": True}]})]
    ans = backend(server).query(make_request())
    assert ans.objects == () and "deformable but not movable" in ans.rejected[0]


def test_duplicate_marks_drop_every_entry_of_that_mark(server):
    server.script = [chat({"objects": [obj(1, cost=1), obj(2), obj(1, cost=9)]})]
    ans = backend(server).query(make_request())
    assert [o.region_index for o in ans.objects] == [1]
    assert len(ans.rejected) == 2 and all("mark 1 answered 2 times" in r for r in ans.rejected)


def test_no_regions_is_an_error_without_a_request(server):
    server.script = [chat({"objects": []})]
    ans = backend(server).query(make_request(regions=()))
    assert ans.error is not None and "no candidate regions" in ans.error
    assert server.requests == []


def test_bad_request_is_an_error_answer_not_an_exception(server):
    server.script = [chat({"objects": []})]
    req = make_request()
    bad = VlmRequest(image=req.image[..., :2].copy(), stamp_s=1.0, camera_pose_odom=np.eye(4), prompt="p", regions=REGIONS)
    ans = backend(server).query(bad)
    assert ans.error is not None and "request image" in ans.error and server.requests == []


# ---------------------------------------------------------------------------- transport faults

def test_slow_server_beyond_the_timeout_gives_an_error_within_the_bound(server):
    server.script = [drip(server, interval_s=0.05)]  # ~60 bytes -> ~3 s per answer, each read quick
    b = backend(server, timeout_s=0.5, max_retries=1, backoff_s=0.05)
    t0 = time.monotonic()
    ans = b.query(make_request())
    elapsed = time.monotonic() - t0
    assert ans.error is not None and "within 0.5 s" in ans.error and "2 attempts" in ans.error
    assert ans.objects == ()
    assert len(server.requests) == 2
    assert elapsed < b.config.worst_case_s() + SLACK_S


def test_hanging_server_is_bounded(server):
    server.script = [hang(server)]
    b = backend(server, timeout_s=0.4, max_retries=2, backoff_s=0.05)
    t0 = time.monotonic()
    ans = b.query(make_request())
    elapsed = time.monotonic() - t0
    assert ans.error is not None and "3 attempts" in ans.error
    assert len(server.requests) == 3
    assert elapsed < b.config.worst_case_s() + SLACK_S


def test_server_closing_the_connection_is_retried_then_an_error(server):
    server.script = [close_connection]
    ans = backend(server, max_retries=2).query(make_request())
    assert ans.error is not None and "connection failed" in ans.error and "3 attempts" in ans.error
    assert len(server.requests) == 3


def test_connection_refused_is_retried_then_an_error():
    s = socket.socket()
    s.bind(("127.0.0.1", 0))
    port = s.getsockname()[1]
    s.close()  # nothing listens there now
    b = OpenAICompatibleBackend(OpenAICompatibleConfig(base_url=f"http://127.0.0.1:{port}/v1", model="m",
                                                       timeout_s=1.0, max_retries=1, backoff_s=0.01))
    ans = b.query(make_request())
    assert ans.error is not None and "2 attempts" in ans.error


@pytest.mark.parametrize("status", [500, 503, 429])
def test_transient_status_then_200_succeeds_on_retry(server, status):
    server.script = [send_json(status, {"error": {"message": "busy"}}), chat({"objects": [obj(2)]})]
    ans = backend(server).query(make_request())
    assert ans.error is None and [o.region_index for o in ans.objects] == [1]
    assert len(server.requests) == 2


def test_persistent_500_gives_up_with_the_servers_message(server):
    server.script = [send_json(500, {"error": {"message": "model crashed"}})]
    ans = backend(server, max_retries=1).query(make_request())
    assert ans.error is not None and "HTTP 500: model crashed" in ans.error and "2 attempts" in ans.error
    assert len(server.requests) == 2


@pytest.mark.parametrize("status", [400, 401, 404])
def test_client_error_is_not_retried(server, status):
    server.script = [send_json(status, {"error": {"message": "bad thing"}}), chat({"objects": [obj(1)]})]
    ans = backend(server).query(make_request())
    assert ans.error == f"HTTP {status}: bad thing" and ans.objects == ()
    assert len(server.requests) == 1


def test_oversized_response_is_an_error(server):
    server.script = [chat("x" * 5000)]
    ans = backend(server, max_response_bytes=1024).query(make_request())
    assert ans.error is not None and "larger than 1024 bytes" in ans.error and len(server.requests) == 1


# -------------------------------------------------------------------------------------- config

def test_config_rejects_unknown_fields_and_bad_urls(monkeypatch):
    with pytest.raises(ValidationError, match="extra"):
        OpenAICompatibleConfig(base_url="http://h/v1", model="m", retries=3)
    with pytest.raises(ValidationError, match="base_url"):
        OpenAICompatibleConfig(base_url="ftp://h/v1", model="m")
    with pytest.raises(ValidationError):
        OpenAICompatibleConfig(base_url="http://h/v1", model="m", timeout_s=0)
    monkeypatch.delenv("DCT_TEST_NO_SUCH_KEY", raising=False)
    with pytest.raises(ValueError, match="DCT_TEST_NO_SUCH_KEY"):
        OpenAICompatibleBackend(OpenAICompatibleConfig(base_url="http://h/v1", model="m", api_key_env="DCT_TEST_NO_SUCH_KEY"))
    cfg = OpenAICompatibleConfig(base_url="http://h:8000/v1/", model="m", timeout_s=2, max_retries=2, backoff_s=0.5)
    assert cfg.base_url == "http://h:8000/v1"
    assert cfg.worst_case_s() == pytest.approx(3 * 2 + 0.5 + 1.0)


# ------------------------------------------------------------------------------- parser fuzzing

json_values = st.recursive(
    st.none() | st.booleans() | st.integers() | st.floats(allow_nan=True, allow_infinity=True) | st.text(max_size=20),
    lambda children: st.lists(children, max_size=4) | st.dictionaries(st.text(max_size=8), children, max_size=4),
    max_leaves=20,
)
field_values = st.one_of(
    json_values,
    st.integers(-3, 6),
    st.integers(min_value=10**300, max_value=10**400),
    st.floats(-1, 12),
    st.sampled_from(["box", "", " ", "x" * 300]),
)
items = st.one_of(
    json_values,
    st.fixed_dictionaries({}, optional={f: field_values for f in ("mark", "label", "movable", "contact_cost", "confidence")}),
)


def _check_parsed(parsed, n_items: int | None) -> None:
    for o in parsed.objects:
        validate_object(o, (H, W), "parsed")  # whatever is kept is sound
        np.testing.assert_array_equal(o.mask, REGIONS[o.region_index].mask)
    if parsed.error is not None:
        assert parsed.objects == () and parsed.rejected == ()
    elif n_items is not None:
        assert len(parsed.objects) + len(parsed.rejected) == n_items
    marks = [o.region_index for o in parsed.objects]
    assert len(marks) == len(set(marks))


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(json_values)
def test_parser_never_raises_on_any_json_value(value):
    _check_parsed(parse_answer(json.dumps(value), REGIONS, (H, W)), None)


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.lists(items, max_size=6))
def test_parser_never_raises_on_any_objects_list(objects):
    _check_parsed(parse_answer(json.dumps({"objects": objects}), REGIONS, (H, W)), len(objects))


@settings(max_examples=200, deadline=None)
@given(st.one_of(st.text(max_size=50), st.binary(max_size=30), json_values))
def test_parser_never_raises_on_raw_text_or_non_text(content):
    _check_parsed(parse_answer(content, REGIONS, (H, W)), None)


def test_parser_survives_deep_nesting():
    parsed = parse_answer("[" * 100_000 + "]" * 100_000, REGIONS, (H, W))
    assert parsed.error is not None


# ---------------------------------------------------------------------------------- set of mark

def test_draw_marks_copies_numbers_and_downscales():
    req = make_request()
    before = req.image.copy()
    marked = draw_marks(req.image, REGIONS)
    np.testing.assert_array_equal(req.image, before)  # input untouched
    assert marked.shape == (H, W, 3) and marked.dtype == np.uint8
    assert not np.array_equal(marked, req.image)
    for k in range(len(REGIONS)):  # each region's outline colour is drawn
        assert (marked == PALETTE[k]).all(axis=2).any()
    small = draw_marks(req.image, REGIONS, max_side_px=80)
    assert max(small.shape[:2]) == 80 and small.shape[:2] == (60, 80)


def test_mark_anchor_lies_inside_a_non_convex_region():
    l_shape = REGIONS[1].mask
    ys, xs = np.nonzero(l_shape)
    assert not l_shape[int(ys.mean()), int(xs.mean())]  # the centroid misses the L
    x, y = mark_anchor(l_shape)
    assert l_shape[y, x]
    assert mark_anchor(np.zeros((5, 5), bool)) is None


def test_data_url_round_trip():
    img = draw_marks(make_request().image, REGIONS)
    png = decode_data_url(encode_data_url(img, "png"))
    np.testing.assert_array_equal(png, img)  # lossless, and RGB stays RGB
    jpg = decode_data_url(encode_data_url(img, "jpeg", 95))
    assert jpg.shape == img.shape
    with pytest.raises(ValueError, match="uint8"):
        encode_data_url(img.astype(np.float32))
