"""MCAP recordings (runtime.io.recording): a lockstep run records every tick without changing a metric;
a cut-off file reads up to its last complete chunk; a full queue or a failing disk drops and
counts records instead of stalling the tick; outputs are atomic and never overwritten unasked;
VLM answers (masks when they arrive, capture -> mask latency) and per-thread CPU time are recorded."""
from __future__ import annotations

import errno
import io
import json
import time
from types import SimpleNamespace

import numpy as np
import pytest
from click.testing import CliRunner

from hil_sim.episode.lockstep import run_episode
from hil_sim.world.scenario import load_scenario
from runtime.config import load_controller_config
from runtime.io.recording import RecordingError, RecordingReadError, RunRecorder, read_recording
from runtime.io.recording import schemas as S
from runtime.loop.telemetry import STAGES, TickTelemetry

SECONDS = 1.5  # a short lockstep run: about 30 ticks with the lidar, the MPC and the CAN traffic


def _short(name: str = "case1"):
    return load_scenario(name).model_copy(update={"time_limit_s": SECONDS})


@pytest.fixture(scope="module")
def recorded(tmp_path_factory):
    """One recorded episode (small chunks, so that a cut lands in a file of many chunks) and
    the same episode unrecorded."""
    out = tmp_path_factory.mktemp("rec") / "run.mcap"
    # all-fixed: mode dct waits 1.5 s for the VLM's first answer, the whole of this short run.
    config = load_controller_config().with_planner_mode("all-fixed")
    with RunRecorder(out, chunk_size=4096) as rec:
        with_rec = run_episode(_short(), seed=0, recorder=rec, config=config)
    without = run_episode(_short(), seed=0, config=config)
    return out, rec.summary(), with_rec, without


def test_recording_changes_no_metric_and_holds_every_tick(recorded):
    path, summary, with_rec, without = recorded
    assert json.dumps(with_rec.metrics, sort_keys=True) == json.dumps(without.metrics, sort_keys=True)
    assert summary["dropped_total"] == 0 and summary["write_error"] is None
    rec = read_recording(path)
    assert rec.complete and rec.stopped_by is None
    ticks = [m for _, m in rec.messages[S.TOPIC_TICK]]
    assert len(ticks) == with_rec.telemetry["ticks"] == summary["written"]["tick"]
    assert [t["tick"] for t in ticks] == list(range(len(ticks)))
    assert set(ticks[0]["stage_ms"]) == set(STAGES)
    # The recorded stage times are the telemetry's (same ring buffer records, in ms).
    np.testing.assert_allclose([t["tick_ms"] for t in ticks], with_rec.tick_records["tick_s"] * 1e3)
    assert sum(t["deadline_missed"] for t in ticks) == with_rec.telemetry["deadline_misses"]
    assert any(t["sensor_to_command_ms"] is not None for t in ticks)
    assert len(rec.messages[S.TOPIC_POSE]) == len(ticks)
    can = [m for _, m in rec.messages[S.TOPIC_CAN]]
    assert {m["direction"] for m in can} == {"tx", "rx"}
    assert "0x111" in {m["id_hex"] for m in can if m["direction"] == "tx"}
    counts = [m for _, m in rec.messages[S.TOPIC_PARTITION]]
    assert counts and max(c["p_fix"] for c in counts) > 0  # the lower-rate point sets
    assert len(rec.messages[S.TOPIC_P_FIX]) == len(counts) and rec.messages.get(S.TOPIC_PLAN)
    # Foxglove's well-known schemas for what its 3D panel draws; JSON schema encoding throughout.
    assert rec.topics[S.TOPIC_POSE] == "foxglove.PoseInFrame" and rec.topics[S.TOPIC_P_FIX] == "foxglove.PointCloud"
    info = rec.run_info()
    cfg = load_controller_config()
    assert info["stage_budgets_ms"]["planner"] == pytest.approx(cfg.loop.stage_budgets_s["planner"] * 1e3)
    assert info["scenario"] == "case1" and info["clock"] == "lockstep"
    assert rec.recorder_account()["dropped_total"] == 0


@pytest.fixture(scope="module")
def recorded_case2(tmp_path_factory):
    """case2 in mode dct, just long enough for the sim-oracle's first answer (1.5 s after the query,
    which waits for the first lidar scan)."""
    out = tmp_path_factory.mktemp("rec2") / "case2.mcap"
    with RunRecorder(out) as rec:
        result = run_episode(_short("case2").model_copy(update={"time_limit_s": 1.7}), seed=0, recorder=rec)
    return out, rec.summary(), result


def test_vlm_answers_are_recorded_when_they_arrive_with_their_masks(recorded_case2):
    from PIL import Image

    path, summary, result = recorded_case2
    assert summary["written"]["answer"] >= 1 and summary["dropped_total"] == 0
    rec = read_recording(path)
    assert rec.topics[S.TOPIC_VPP_ANSWER] == "dct.VppAnswer"
    assert rec.topics[S.TOPIC_VPP_MASKS] == "foxglove.CompressedImage"
    answers = [m for _, m in rec.messages[S.TOPIC_VPP_ANSWER]]
    assert len(answers) == summary["written"]["answer"]
    period_s = load_controller_config().loop.period_s
    latency_s = 1.5  # the sim-oracle's simulated backend latency
    for a in answers:
        # Arrival: a tick's scheduled start; the latency is the backend's 1.5 s, quantised to the tick,
        # plus the wait of the image for the tick that sends it (the first query waits for a lidar scan).
        assert round(a["arrival_s"] / period_s) * period_s == pytest.approx(a["arrival_s"], abs=1e-9)
        assert a["latency_ms"] == pytest.approx((a["arrival_s"] - a["capture_s"]) * 1e3)
        assert latency_s * 1e3 - 1e-6 <= a["latency_ms"] <= (latency_s + 2 * period_s) * 1e3 + 1e-6, a
        labels = {o["label"] for o in a["objects"]}
        assert "box" in labels and all(o["pixels"] > 0 for o in a["objects"])
        box = next(o for o in a["objects"] if o["label"] == "box")
        assert box["movable"] and 0.0 <= box["contact_cost"] < 10.0
    ticks = {m["scheduled_s"] for _, m in rec.messages[S.TOPIC_TICK]}
    assert all(any(abs(a["arrival_s"] - t) < 1e-9 for t in ticks) for a in answers)
    images = [m for _, m in rec.messages[S.TOPIC_VPP_MASKS]]
    assert len(images) == len(answers)
    import base64

    img = np.asarray(Image.open(io.BytesIO(base64.b64decode(images[0]["data"]))).convert("RGB"))
    assert images[0]["format"] == "png" and img.shape == (120, 160, 3)
    colours = {tuple(c) for c in img.reshape(-1, 3)}
    assert (0, 0, 0) in colours and len(colours) >= 3  # background, a cost-10 red, the box's colour
    # CPU time per thread: at least the first and the last sample, the loop's and the writer's thread.
    samples = [m for _, m in rec.messages[S.TOPIC_THREADS]]
    assert rec.topics[S.TOPIC_THREADS] == "dct.Threads" and len(samples) >= 2
    names = {t["name"] for t in samples[-1]["threads"]}
    assert {"MainThread", "dct-mcap-writer"} <= names
    assert samples[-1]["wall_s"] > samples[0]["wall_s"]
    main = [t["cpu_s"] for s in samples for t in s["threads"] if t["name"] == "MainThread"]
    assert main == sorted(main) and main[-1] > 0


def test_the_backend_runners_answers_are_recorded_in_full_at_the_tick_that_took_them(recorded_case2):
    from runtime.io.recording.backend_answers import TOPIC, answer_from_json

    path, summary, result = recorded_case2
    rec = read_recording(path)
    assert rec.topics[TOPIC] == "dct.VppBackendAnswers"
    msgs = [m for _, m in rec.messages[TOPIC]]
    assert len(msgs) == summary["written"]["backend_answer"] >= 1
    now_of = {m["tick"]: m["now_s"] for _, m in rec.messages[S.TOPIC_INPUTS]}
    applied = [m for _, m in rec.messages[S.TOPIC_VPP_ANSWER]]
    answers = [answer_from_json(a) for m in msgs for a in m["answers"]]
    assert len(answers) == applied[-1]["answers"]  # every answer the stage received, failed ones too
    for m in msgs:
        assert m["now_s"] == now_of[m["tick"]]  # the controller's clock at the tick that took them
    assert {a.stamp_s for a in answers} == {m["capture_s"] for m in applied}
    box = [o for a in answers for o in a.objects if o.label == "box"]
    assert box and all(o.mask.shape == (480, 640) and o.mask.any() for o in box)


def test_the_hook_records_a_new_answer_once_and_counts_drops(tmp_path):
    """A fake VPP stage: an answer is queued when last_answer_s changes, once; with a full queue it is
    dropped and counted."""
    from runtime.io.recording.messages import mask_label_image

    mask = np.zeros((480, 640), bool)
    mask[100:200, 300:400] = True
    entry = SimpleNamespace(object_id=7, label="box", movable=True, contact_cost=2.0, mask=mask, stamp_s=0.1)
    ctl = _FakeController()
    ctl.vpp = SimpleNamespace(answers=0, memory=SimpleNamespace(last_answer_s=None, entries=[]))
    out = tmp_path / "answers.mcap"
    rec = RunRecorder(out)
    hook = rec.attach(ctl, load_controller_config(), {"clock": "test"})
    for k, row in enumerate(_rows(10)):
        if k == 4:
            ctl.vpp.answers, ctl.vpp.memory.last_answer_s, ctl.vpp.memory.entries = 1, 0.1, [entry]
        hook(row)
    summary = rec.close()
    got = read_recording(out)
    (a,) = [m for _, m in got.messages[S.TOPIC_VPP_ANSWER]]
    assert a["arrival_s"] == pytest.approx(0.2) and a["latency_ms"] == pytest.approx(100.0)
    assert a["objects"] == [{"object_id": 7, "label": "box", "movable": True, "contact_cost": 2.0, "pixels": 10000}]
    img = mask_label_image((entry,))
    assert img.shape == (120, 160, 3) and np.count_nonzero(img.any(axis=2)) == 25 * 25
    # A writer that is behind: held inside its first record, the queue holds one more (the tick).
    import threading

    rec2 = RunRecorder(tmp_path / "full.mcap", queue_capacity=1)
    entered, gate, write = threading.Event(), threading.Event(), rec2._write_item

    def held(item):
        entered.set()
        gate.wait(10)
        write(item)

    rec2._write_item = held
    hook2 = rec2.attach(ctl, load_controller_config(), {"clock": "test"})
    assert entered.wait(10)
    ctl.vpp.memory.last_answer_s = 0.3
    hook2(_rows(1)[0])
    gate.set()
    summary2 = rec2.close()
    assert summary2["dropped_queue_full"]["answer"] == 1 and summary2["written"]["tick"] == 1
    assert summary["dropped_queue_full"]["answer"] == 0


def test_no_proc_means_no_thread_samples(tmp_path):
    from runtime.io.recording.recorder import thread_cpu_seconds

    assert thread_cpu_seconds(str(tmp_path)) is None
    threads = thread_cpu_seconds()
    if threads is not None:  # Linux
        assert any(t["name"] == "MainThread" and t["cpu_s"] > 0 for t in threads)


def test_the_report_of_an_all_fixed_run_says_image_to_mask_was_not_recorded(recorded):
    from runtime.app.reports.latency import latency_report, load_ticks

    path, _, _, _ = recorded
    rep = latency_report(load_ticks(path))
    assert rep["image_to_mask_ms"]["recorded"] is False and rep["image_to_mask_ms"]["why"]
    assert rep["sensor_to_command_ms"]["image_to_mask"] == "not recorded"
    assert rep["threads"]["recorded"] is True and "MainThread" in rep["threads"]["by_name"]


def _messages_per_chunk(path) -> list[tuple[int, int, int]]:
    """(chunk end offset, tick messages, all messages) of each chunk of a complete file."""
    from mcap.data_stream import ReadDataStream
    from mcap.reader import make_reader
    from mcap.records import Chunk, Message
    from mcap.stream_reader import breakup_chunk

    with open(path, "rb") as f:
        summary = make_reader(f).get_summary()
    tick_channel = next(c.id for c in summary.channels.values() if c.topic == S.TOPIC_TICK)
    out = []
    with open(path, "rb") as f:
        for idx in sorted(summary.chunk_indexes, key=lambda c: c.chunk_start_offset):
            f.seek(idx.chunk_start_offset + 9)  # opcode (1) + record length (8)
            chunk = Chunk.read(ReadDataStream(f))
            records = breakup_chunk(chunk)
            msgs = [r for r in records if isinstance(r, Message)]
            out.append((idx.chunk_start_offset + idx.chunk_length,
                        sum(m.channel_id == tick_channel for m in msgs), len(msgs)))
    return out


def test_a_cut_off_file_reads_up_to_its_last_complete_chunk(recorded, tmp_path):
    path, _, _, _ = recorded
    data = path.read_bytes()
    chunks = _messages_per_chunk(path)
    assert len(chunks) >= 5, "the test needs a file of several chunks"
    full = read_recording(path)
    full_ticks = [m["tick"] for _, m in full.messages[S.TOPIC_TICK]]
    # Cuts in the middle of chunks (power loss while writing one) and just after one.
    cuts = [len(data) // 2, len(data) // 3, 2 * len(data) // 3, chunks[2][0], chunks[2][0] + 5]
    for cut in cuts:
        cut_file = tmp_path / f"cut_{cut}.mcap"
        cut_file.write_bytes(data[:cut])
        rec = read_recording(cut_file)
        whole = [c for c in chunks if c[0] <= cut]
        assert not rec.complete and rec.stopped_by, cut
        got_ticks = [m["tick"] for _, m in rec.messages.get(S.TOPIC_TICK, [])]
        assert len(got_ticks) == sum(c[1] for c in whole), cut
        assert sum(len(v) for v in rec.messages.values()) == sum(c[2] for c in whole), cut
        assert got_ticks == full_ticks[: len(got_ticks)]  # a prefix, in order
        assert rec.run_info()["stages"] == list(STAGES)  # the run's description is written first


def test_not_an_mcap_file_is_refused_in_one_line(tmp_path):
    p = tmp_path / "notes.mcap"
    p.write_text("hello\n")
    with pytest.raises(RecordingReadError, match="is not an MCAP file"):
        read_recording(p)


class _FakeController:
    """What the tick hook reads from a controller (its published snapshot), without a controller:
    `vpp` holds the VLM's answer count and mask memory the snapshot carries."""

    def __init__(self) -> None:
        self.vpp = None

    @property
    def snapshot(self):
        memory = self.vpp.memory if self.vpp is not None else None
        return SimpleNamespace(
            pose=SimpleNamespace(x_m=1.0, y_m=2.0, yaw_rad=0.5), scan=None, points_fix=np.zeros((100, 2)),
            plan=None, reference_path=None, partition_frame=None,
            vlm_answers=self.vpp.answers if self.vpp is not None else 0,
            vlm_last_answer_s=memory.last_answer_s if memory is not None else None,
            vlm_masks=memory.entries if memory is not None else ())


def _rows(n: int) -> list[np.void]:
    tel = TickTelemetry(capacity=n + 1)
    rows = []
    for k in range(n):
        row = tel.begin_tick()
        row["tick"], row["scheduled_s"], row["tick_s"] = k, 0.05 * k, 0.004
        tel.commit_tick(row)
        rows.append(row)
    return rows


class _SlowFile(io.FileIO):
    """A disk that takes 50 ms per write."""

    def write(self, b):
        time.sleep(0.05)
        return super().write(b)


class _FullDisk(io.FileIO):
    """A disk that fills up after `room` bytes (a short write, then ENOSPC)."""

    room = 6000

    def write(self, b):
        left = self.room - self.tell()
        if left <= 0:
            raise OSError(errno.ENOSPC, "No space left on device")
        return super().write(bytes(b)[:left])


def test_a_slow_disk_drops_and_counts_records_never_blocks(tmp_path):
    out = tmp_path / "slow.mcap"
    rec = RunRecorder(out, queue_capacity=8, chunk_size=256, opener=lambda p: _SlowFile(p, "wb"))
    hook = rec.attach(_FakeController(), load_controller_config(), {"clock": "test"})
    rows = _rows(500)
    for row in rows:  # the writer cannot keep up with 500 ticks queued at once
        hook(row)
    summary = rec.close()
    assert summary["dropped_queue_full"]["tick"] > 0
    assert summary["written"]["tick"] + summary["dropped_queue_full"]["tick"] == 500
    got = read_recording(out)
    assert got.complete and len(got.messages[S.TOPIC_TICK]) == summary["written"]["tick"]
    assert got.recorder_account()["dropped_queue_full"]["tick"] == summary["dropped_queue_full"]["tick"]


def test_a_full_disk_stops_writing_counts_the_rest_and_keeps_what_was_written(tmp_path):
    out = tmp_path / "full.mcap"
    rec = RunRecorder(out, chunk_size=512, flush_interval_s=0.0, opener=lambda p: _FullDisk(p, "wb"))
    hook = rec.attach(_FakeController(), load_controller_config(), {"clock": "test"})
    for row in _rows(300):
        hook(row)
    summary = rec.close()
    assert summary["write_error"] and "No space left" in summary["write_error"]
    assert summary["dropped_write_error"] > 0
    assert summary["written"]["tick"] + summary["dropped_write_error"] + summary["dropped_queue_full"]["tick"] \
        + summary["dropped_queue_full"]["points"] + summary["written"]["points"] >= 300
    assert out.exists() and not list(tmp_path.glob(".*.part"))  # renamed onto the output all the same
    got = read_recording(out)  # cut off where the disk filled up
    assert not got.complete
    assert len(got.messages.get(S.TOPIC_TICK, [])) <= summary["written"]["tick"]


def test_an_existing_recording_is_refused_without_force(tmp_path):
    out = tmp_path / "run.mcap"
    out.write_bytes(b"old")
    with pytest.raises(RecordingError, match="already exists; choose another name or pass --force"):
        RunRecorder(out)
    assert out.read_bytes() == b"old"
    with pytest.raises(RecordingError, match="must end in .mcap"):
        RunRecorder(tmp_path / "run.json")
    rec = RunRecorder(out, force=True)
    assert out.read_bytes() == b"old"  # written under a temporary name until the end
    rec.close()
    assert read_recording(out).complete


def test_hil_run_record_option(tmp_path):
    """`dct hil run SCENARIO --record out.mcap`, and the refusal to overwrite it."""
    from hil_sim.cli import hil_group

    scenario = tmp_path / "short.yaml"
    raw = load_scenario("case1").model_dump(mode="json", by_alias=True)
    raw["time_limit_s"] = 0.6
    scenario.write_text(json.dumps(raw))  # JSON is YAML
    out = tmp_path / "run.mcap"
    res = CliRunner().invoke(hil_group, ["run", str(scenario), "--record", str(out)])
    assert res.exit_code in (0, 1), res.output  # 1: the episode did not reach the goal in 0.6 s
    assert f"recorded {out}:" in res.output and "dropped 0" in res.output
    assert len(read_recording(out).messages[S.TOPIC_TICK]) >= 10
    again = CliRunner().invoke(hil_group, ["run", str(scenario), "--record", str(out)])
    assert again.exit_code == 2 and "already exists" in again.output


def test_a_held_tick_says_why_in_the_recording(tmp_path):
    """/dct/tick carries the reason the robot stands (the faulty inputs while HOLDING), so that a
    long hold in a recorded run can be explained from the file alone."""
    from hil_sim.episode.faults import FaultSpec

    out = tmp_path / "held.mcap"
    config = load_controller_config().with_planner_mode("all-fixed")
    with RunRecorder(out) as rec:
        run_episode(_short().model_copy(update={"time_limit_s": 2.0}), seed=0, recorder=rec, config=config,
                    faults=[FaultSpec("imu-silent", 0.8, 0.5)])
    ticks = [m for _, m in read_recording(out).messages[S.TOPIC_TICK]]
    held = [t for t in ticks if t["state"] == "HOLDING"]
    assert held and all("IMU" in t["reason"] for t in held)
    assert all(t["reason"] is None for t in ticks if t["state"] == "ACTIVE")
