"""MCAP recordings (runtime.recording): a lockstep run records every tick without changing a metric;
a cut-off file reads up to its last complete chunk; a full queue or a failing disk drops and
counts records instead of stalling the tick; outputs are atomic and never overwritten unasked."""
from __future__ import annotations

import errno
import io
import json
import time
from types import SimpleNamespace

import numpy as np
import pytest
from click.testing import CliRunner

from hil_sim.runner import run_episode
from hil_sim.scenario import load_scenario
from runtime.config import load_controller_config
from runtime.recording import RecordingError, RecordingReadError, RunRecorder, read_recording
from runtime.recording import schemas as S
from runtime.telemetry import STAGES, TickTelemetry

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
    """What the tick hook reads from a controller, without a controller."""

    def __init__(self) -> None:
        self.pose = SimpleNamespace(x_m=1.0, y_m=2.0, yaw_rad=0.5)
        self.monitor = SimpleNamespace(good_scan=None)
        self.points_fix = np.zeros((100, 2))


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
