"""The `/dct/vpp/backend_answer` codec: an answer reads back exactly as it was written, and a
damaged one is refused with a one-line error naming the field."""
from __future__ import annotations

import json

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from models.vlm.interface import DetectedObject, VlmAnswer
from runtime.io.recording.backend_answers import RecordedAnswerError, answer_from_json, answer_json

_FLOAT = st.floats(-1e6, 1e6, allow_nan=False)


@st.composite
def _answers(draw):
    h, w = draw(st.integers(1, 40)), draw(st.integers(1, 40))
    failed = draw(st.booleans())
    objects = []
    for _ in range(0 if failed else draw(st.integers(0, 3))):
        mask = draw(arrays(bool, (h, w)))
        mask[draw(st.integers(0, h - 1)), draw(st.integers(0, w - 1))] = True  # never empty
        movable = draw(st.booleans())
        objects.append(DetectedObject(
            mask=mask, label=draw(st.text(min_size=1, max_size=20).filter(str.strip)), movable=movable,
            contact_cost=draw(st.floats(0, 10)), confidence=draw(st.floats(0, 1)),
            region_index=draw(st.none() | st.integers(0, 50)), deformable=movable and draw(st.booleans())))
    return VlmAnswer(stamp_s=draw(_FLOAT), camera_pose_odom=np.array(draw(st.lists(_FLOAT, min_size=16, max_size=16)))
                     .reshape(4, 4), objects=tuple(objects), backend=draw(st.text(max_size=10)),
                     latency_s=draw(st.floats(0, 100)), error="down" if failed else None,
                     rejected=tuple(draw(st.lists(st.text(max_size=10), max_size=2))),
                     sent_s=draw(st.none() | _FLOAT), answered_s=draw(st.none() | _FLOAT))


@settings(max_examples=60, deadline=None)
@given(_answers())
def test_an_answer_reads_back_exactly(a):
    b = answer_from_json(json.loads(json.dumps(answer_json(a), allow_nan=False)))
    assert (b.stamp_s, b.backend, b.latency_s, b.error, b.rejected) == (a.stamp_s, a.backend, a.latency_s, a.error,
                                                                       a.rejected)
    assert (b.sent_s, b.answered_s) == (a.sent_s, a.answered_s)
    assert np.array_equal(b.camera_pose_odom, a.camera_pose_odom)
    assert len(b.objects) == len(a.objects)
    for p, q in zip(a.objects, b.objects):
        assert np.array_equal(p.mask, q.mask) and q.mask.dtype == bool
        assert (p.label, p.movable, p.contact_cost, p.confidence, p.region_index, p.deformable) == \
               (q.label, q.movable, q.contact_cost, q.confidence, q.region_index, q.deformable)


def _good() -> dict:
    mask = np.zeros((3, 5), bool)
    mask[1, 1:4] = True
    return answer_json(VlmAnswer(stamp_s=1.0, camera_pose_odom=np.eye(4), backend="b", latency_s=0.5, objects=(
        DetectedObject(mask=mask, label="box", movable=True, contact_cost=1.0, confidence=0.5),)))


def test_an_answer_recorded_before_its_send_time_was_kept_reads_without_it():
    d = _good()
    del d["sent_s"], d["answered_s"]
    a = answer_from_json(d)
    assert (a.sent_s, a.answered_s) == (None, None) and a.latency_s == 0.5


@pytest.mark.parametrize("damage, field", [
    (lambda d: d.pop("stamp_s"), "stamp_s: missing"),
    (lambda d: d.update(latency_s="fast"), "latency_s: expected"),
    (lambda d: d.update(camera_pose_odom=[0.0] * 15), "camera_pose_odom: expected 16"),
    (lambda d: d.update(error="down"), "objects: a failed answer carries no objects"),
    (lambda d: d["objects"][0].update(movable=1), "movable: expected bool"),
    (lambda d: d["objects"][0].update(contact_cost=11.0), "contact_cost must be a number in 0..10"),
    (lambda d: d["objects"][0]["mask"].update(bits_zlib_b64="%%%"), "mask.bits_zlib_b64: not base64"),
    (lambda d: d["objects"][0]["mask"].update(width=6), "mask.bits_zlib_b64: 2 bytes, a 6x3 mask packs into 3"),
    (lambda d: d["objects"][0]["mask"].update(height=0), "mask: size 5x0"),
    (lambda d: d.update(sent_s="soon"), "sent_s: expected a finite number or null"),
    (lambda d: d.update(answered_s=True), "answered_s: expected a finite number or null"),
])
def test_a_damaged_answer_is_refused_naming_the_field(damage, field):
    d = _good()
    answer_from_json(d)
    damage(d)
    with pytest.raises(RecordedAnswerError, match="VlmAnswer") as e:
        answer_from_json(d, "(tick 3, answer 0)")
    assert field in str(e.value) and "\n" not in str(e.value)
