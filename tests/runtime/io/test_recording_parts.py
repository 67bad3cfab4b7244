"""A recording in parts (runtime.io.recording): a run recorded every `split_every_s` into its own
MCAP file reads back, joined, as the run recorded in one file does; each part is a whole MCAP file
that mcap's own reader opens; a stale part of another run is never joined; parts of an earlier
recording are not overwritten unasked; the writer's index does not grow with the run."""
from __future__ import annotations

import json
import time

import numpy as np
import pytest

from hil_sim.episode.lockstep import run_episode
from hil_sim.world.scenario import load_scenario
from runtime.config import load_controller_config
from runtime.io.recording import RecordingError, RunRecorder, read_recording
from runtime.io.recording import schemas as S
from runtime.io.recording.reader import existing_parts, part_path

SECONDS = 1.5
PART_S = 0.4  # four parts in a 1.5-s run


@pytest.fixture(scope="module")
def two_ways(tmp_path_factory):
    """The same short lockstep episode recorded in one file and in parts."""
    d = tmp_path_factory.mktemp("parts")
    sc = load_scenario("case1").model_copy(update={"time_limit_s": SECONDS})
    config = load_controller_config().with_planner_mode("all-fixed")
    with RunRecorder(d / "one.mcap") as rec:
        run_episode(sc, seed=0, recorder=rec, config=config)
    with RunRecorder(d / "run.mcap", split_every_s=PART_S) as parted:
        run_episode(sc, seed=0, recorder=parted, config=config)
    return d, rec.summary(), parted.summary()


def _ticks(rec) -> list[int]:
    return [m["tick"] for _, m in rec.messages[S.TOPIC_TICK]]


def test_the_parts_read_back_as_the_run_in_one_file(two_ways):
    d, one_summary, summary = two_ways
    names = [part_path(d / "run.mcap", k).name for k in range(4)]
    assert names == ["run.mcap", "run.part1.mcap", "run.part2.mcap", "run.part3.mcap"]
    assert [p.rsplit("/", 1)[-1] for p in summary["parts"]] == names
    assert sorted(p.name for p in existing_parts(d / "run.mcap")) == names[1:]
    assert not list(d.glob(".*.part"))  # every temporary file renamed
    one, joined = read_recording(d / "one.mcap"), read_recording(d / "run.mcap")
    assert [p.name for p in joined.parts] == names and joined.complete
    assert _ticks(joined) == _ticks(one) == list(range(summary["ticks_seen"]))
    wall = ("send_us", "icp_results")  # the wall clock's figures (ICP's compute_ms among them) left out
    for topic in (S.TOPIC_CAN, S.TOPIC_POSE, S.TOPIC_INPUTS):
        assert ([{k: v for k, v in m.items() if k not in wall} for _, m in joined.messages[topic]]
                == [{k: v for k, v in m.items() if k not in wall} for _, m in one.messages[topic]]), topic
    assert joined.recorder_account()["dropped_total"] == 0
    assert joined.recorder_account()["last_part"] is True and joined.recorder_account()["part"] == 3
    info = joined.run_info()
    assert info["part"] == 0 and info["recording_id"] == summary["recording_id"]
    # Each part alone: a whole MCAP file with its summary, the run's description and /tf_static.
    from mcap.reader import make_reader

    for k, name in enumerate(names):
        alone = read_recording(d / name, follow_parts=False)
        assert alone.complete and alone.run_info()["part"] == k
        assert alone.run_info()["recording_id"] == summary["recording_id"]
        assert alone.messages.get("/tf_static") or k == 0 and "/tf_static" not in one.messages
        with open(d / name, "rb") as f:
            reader = make_reader(f)
            count = sum(1 for _ in reader.iter_messages(topics=[S.TOPIC_TICK]))
        assert count == len(alone.messages[S.TOPIC_TICK]) > 0
    assert one_summary["parts"] == [str(d / "one.mcap")]


def test_the_latency_report_covers_every_part(two_ways):
    from runtime.app.reports.latency import latency_report, load_ticks

    d, _, summary = two_ways
    data = load_ticks(d / "run.mcap")
    assert len(data.tick) == summary["ticks_seen"]
    assert latency_report(data)["deadline_misses"]["count"] == latency_report(load_ticks(d / "one.mcap"))["deadline_misses"]["count"]
    assert data.recorder["last_part"] is True
    later = load_ticks(d / "run.part2.mcap")  # from a later part on
    assert later.tick[0] > 0 and later.tick[-1] == data.tick[-1]
    np.testing.assert_array_equal(later.tick, data.tick[-len(later.tick):])


def test_a_part_of_another_run_is_not_joined(two_ways, tmp_path):
    d, _, _ = two_ways
    for k in range(3):
        (tmp_path / part_path("run.mcap", k).name).write_bytes(part_path(d / "run.mcap", k).read_bytes())
    # part 3 from another recording under the same name: a stale file the reader must not join
    with RunRecorder(tmp_path / "other.mcap", split_every_s=PART_S) as rec:
        run_episode(load_scenario("case1").model_copy(update={"time_limit_s": 1.0}), seed=1, recorder=rec,
                    config=load_controller_config().with_planner_mode("all-fixed"))
    (tmp_path / "other.part2.mcap").rename(tmp_path / "run.part3.mcap")
    got = read_recording(tmp_path / "run.mcap")
    assert [p.name for p in got.parts] == ["run.mcap", "run.part1.mcap", "run.part2.mcap"]
    assert got.recorder_account()["part"] == 2  # the account of the last part joined


def test_parts_of_an_earlier_recording_are_not_overwritten_unasked(tmp_path):
    stale = tmp_path / "run.part4.mcap"
    stale.write_bytes(b"old")
    with pytest.raises(RecordingError, match="parts of an earlier recording are there"):
        RunRecorder(tmp_path / "run.mcap", split_every_s=60.0)
    assert stale.read_bytes() == b"old" and not (tmp_path / "run.mcap").exists()
    RunRecorder(tmp_path / "run.mcap", split_every_s=60.0, force=True).close()
    for bad in (0.0, -1.0, float("nan")):
        with pytest.raises(RecordingError, match="positive number of seconds"):
            RunRecorder(tmp_path / "x.mcap", split_every_s=bad)


def test_the_writers_index_is_released_with_each_part(tmp_path):
    """The chunk indexes the MCAP writer holds until a file is finished: a part's are gone when
    the next part begins, so what is held does not grow with the run."""
    from runtime.loop.telemetry import TickTelemetry

    tel = TickTelemetry(capacity=3001)
    rows = []
    for k in range(3000):
        row = tel.begin_tick()
        row["tick"], row["scheduled_s"], row["tick_s"] = k, 0.05 * k, 0.004
        tel.commit_tick(row)
        rows.append(row)
    rec = RunRecorder(tmp_path / "run.mcap", split_every_s=30.0, chunk_size=256, flush_interval_s=1e9)
    cfg = load_controller_config()
    hook = rec.attach(object(), cfg)
    held = []
    for row in rows:
        hook(row)
        if int(row["tick"]) % 500 == 499:
            while rec._queue:  # let the writer catch up
                time.sleep(0.005)
            held.append(len(rec._writer._Writer__chunk_indices))
    rec.close()
    assert len(rec.parts) == 5  # 150 s of ticks in parts of 30 s
    from mcap.reader import make_reader

    chunks = 0
    for name in rec.parts:
        with open(name, "rb") as f:
            chunks += make_reader(f).get_summary().statistics.chunk_count
    # About a chunk a tick here: one file would hold 3000 indexes at its end; a part holds its 600.
    assert chunks >= 3000 and max(held) <= 1.1 * 600
    assert json.loads(json.dumps(rec.summary()))["dropped_total"] == 0


def test_a_next_part_that_cannot_be_opened_stops_the_recording_and_keeps_the_parts_written(tmp_path):
    """A full disk when a part begins: the parts finished stay, the rest is counted as dropped,
    and closing the recorder neither raises nor loses the first part."""
    import errno
    import io

    from runtime.loop.telemetry import TickTelemetry

    opened = []

    def opener(name):
        opened.append(name)
        if len(opened) > 1:
            raise OSError(errno.ENOSPC, "No space left on device")
        return io.FileIO(name, "wb")

    tel = TickTelemetry(capacity=64)
    rec = RunRecorder(tmp_path / "run.mcap", split_every_s=0.5, opener=opener)
    hook = rec.attach(object(), load_controller_config())
    for k in range(40):  # 2 s of ticks: the second part would begin at 0.5 s
        row = tel.begin_tick()
        row["tick"], row["scheduled_s"], row["tick_s"] = k, 0.05 * k, 0.004
        tel.commit_tick(row)
        hook(row)
    summary = rec.close()
    assert "No space left" in summary["write_error"] and summary["dropped_write_error"] > 0
    assert [p.rsplit("/", 1)[-1] for p in summary["parts"]] == ["run.mcap"]
    first = read_recording(tmp_path / "run.mcap")
    assert first.complete and [m["tick"] for _, m in first.messages[S.TOPIC_TICK]] == list(range(10))
