"""`dct report latency RUN --trace`: a short lockstep recording as Chrome trace-event JSON, checked
against the format and against the recording (stages inside their tick and in order, the flows from
a lidar frame to the 0x111 that used it, the VLM request), its PNG timeline, the refusals, and a
recording made before the trace's fields were kept."""
from __future__ import annotations

import json

import pytest
from click.testing import CliRunner

from hil_sim.episode.lockstep import run_episode
from hil_sim.world.scenario import load_scenario
from runtime.app.reports.cli import report_group
from runtime.io.recording import RunRecorder
from runtime.io.recording.reader import read_recording
from runtime.loop.telemetry import STAGES
from tests.runtime.app.trace_format import check_trace_format, slice_at, thread_names


@pytest.fixture(scope="module")
def recorded(tmp_path_factory):
    d = tmp_path_factory.mktemp("trace")
    out = d / "run.mcap"
    with RunRecorder(out) as rec:
        # 1.7 s: long enough for the sim-oracle's first answer (1.5 s after the query at the first scan).
        run_episode(load_scenario("case1").model_copy(update={"time_limit_s": 1.7}), seed=0, recorder=rec)
    trace, png = d / "trace.json", d / "trace.png"
    res = CliRunner().invoke(report_group, ["latency", str(out), "--trace", str(trace), "--trace-png", str(png)])
    assert res.exit_code == 0, res.output
    return out, json.loads(trace.read_text()), png, res.output


def _track(trace: dict, tid: int) -> str:
    return thread_names(trace)[tid].split(" #")[0]


def test_the_trace_follows_the_trace_event_format(recorded):
    _, trace, _, output = recorded
    check_trace_format(trace)
    names = set(thread_names(trace).values())
    assert {"loop: tick", "CAN 0x111 writes", "lidar frames", "ICP registrations", "VLM requests"} <= names
    assert "trace " in output and "ICP registrations" in output
    assert "absent: lidar arrivals" in output  # lockstep: no raw sensor channels


def test_each_tick_holds_its_stages_in_order(recorded):
    path, trace, _, _ = recorded
    ticks = {m["tick"]: m for _, m in read_recording(path, topics=["/dct/tick"]).messages["/dct/tick"]}
    xs = [e for e in trace["traceEvents"] if e["ph"] == "X" and e["cat"] == "tick"]
    spans = {e["args"]["tick"]: e for e in xs if e["name"].startswith("tick ")}
    assert set(spans) == set(ticks)
    for k, t in spans.items():
        stages = sorted((e for e in xs if e["name"] in STAGES and e["args"]["tick"] == k), key=lambda e: e["ts"])
        assert [e["name"] for e in stages] == list(STAGES)
        assert all(e["tid"] == t["tid"] for e in stages)
        assert stages[0]["ts"] >= t["ts"] and stages[-1]["ts"] + stages[-1]["dur"] <= t["ts"] + t["dur"]
        assert all(a["ts"] + a["dur"] <= b["ts"] for a, b in zip(stages, stages[1:]))
        scale = t["args"]["drawn_scale"]
        for e in stages:  # the measured wall-clock duration (times the squeeze, if any), in whole microseconds
            assert e["dur"] == pytest.approx(ticks[k]["stage_ms"][e["name"]] * 1e3 * scale, abs=1.0)
    assert sum(t["args"]["drawn_scale"] == 1.0 for t in spans.values()) > len(spans) // 2


def test_a_lidar_frame_flows_to_the_0x111_of_the_tick_that_used_it(recorded):
    path, trace, _, _ = recorded
    flows = check_trace_format(trace)
    by_name: dict[str, list] = {}
    for evs in flows.values():
        by_name.setdefault(evs[0]["name"], []).append(evs)
    direct = by_name["lidar -> 0x111"]
    assert len(direct) > 5
    used = {m["lidar_frame_stamp_s"]: m["tick"] for _, m in
            read_recording(path, topics=["/dct/tick"]).messages["/dct/tick"] if m["lidar_frame_stamp_s"] is not None}
    for evs in direct:
        frame, read, can = (slice_at(trace, e) for e in evs)
        assert _track(trace, evs[0]["tid"]) == "lidar frames" and read["name"] == "read"
        assert can["name"] == f"0x111 command (tick {read['args']['tick']})"
        assert used[frame["args"]["stamp_s"]] == read["args"]["tick"]
    via_icp = by_name["lidar -> ICP -> 0x111"]
    assert len(via_icp) > 5
    for evs in via_icp:
        hops = [slice_at(trace, e) for e in evs]
        assert [_track(trace, e["tid"]) for e in evs] == ["loop: tick", "ICP registrations", "loop: tick",
                                                          "CAN 0x111 writes"]
        handed, icp, received, can = hops
        assert handed["name"] == received["name"] == "odometry"
        icp_span = icp if icp["name"].startswith("ICP #") else next(
            x for x in trace["traceEvents"] if x["ph"] == "X" and x["name"].startswith("ICP #")
            and x["tid"] == icp["tid"] and x["ts"] <= icp["ts"] <= x["ts"] + x["dur"])
        assert (icp_span["args"]["handed_over_tick"], icp_span["args"]["received_tick"]) == (
            handed["args"]["tick"], received["args"]["tick"])
        assert icp_span["args"]["compute_ms"] > 0
        assert can["args"]["tick"] == received["args"]["tick"]


def test_the_vlm_request_runs_from_its_send_to_the_tick_that_took_the_answer(recorded):
    path, trace, _, _ = recorded
    (req,) = [e for e in trace["traceEvents"] if e["ph"] == "X" and e["name"] == "VLM request"]
    (answer,) = [a for _, m in read_recording(path, topics=["/dct/vpp/backend_answer"])
                 .messages["/dct/vpp/backend_answer"] for a in m["answers"]]
    assert req["dur"] == pytest.approx(answer["latency_s"] * 1e6, abs=1.0)  # lockstep: the oracle's 1.5 s
    assert req["args"]["sent_s"] == answer["sent_s"]
    flows = check_trace_format(trace)
    (vlm,) = [evs for evs in flows.values() if evs[0]["name"] == "VLM -> 0x111"]
    part = slice_at(trace, vlm[1])
    assert part["name"] == "partition" and part["args"]["tick"] == req["args"]["taken_by_tick"]


def test_the_png_timeline_is_a_picture(recorded):
    import matplotlib.image as mpimg

    _, _, png, output = recorded
    img = mpimg.imread(png)
    assert img.ndim == 3 and img.shape[0] > 200 and img.shape[1] > 1000
    assert img[..., :3].std() > 0.05  # not blank
    assert f"trace timeline {png}" in output


def test_refusals_are_one_line_and_leave_the_file_alone(recorded, tmp_path):
    path, _, _, _ = recorded
    runner = CliRunner()
    existing = tmp_path / "t.json"
    existing.write_text("{}")
    res = runner.invoke(report_group, ["latency", str(path), "--trace", str(existing)])
    assert res.exit_code == 2 and "already exists; choose another name or pass --force" in res.output
    assert existing.read_text() == "{}"
    res = runner.invoke(report_group, ["latency", str(path), "--trace", str(tmp_path / "a.json"),
                                       "--json", str(tmp_path / "a.json")])
    assert res.exit_code == 2 and "--json and --trace are the same file" in res.output
    res = runner.invoke(report_group, ["latency", str(path), "--trace", str(existing), "--force"])
    assert res.exit_code == 0 and "traceEvents" in json.loads(existing.read_text())
    assert not list(tmp_path.glob(".*"))  # atomic: no temporary left


def test_a_recording_made_before_the_trace_fields_gives_the_ticks_and_says_what_is_absent(tmp_path):
    """Ticks as an older recorder wrote them (no stage offsets of the command, no frame starts, ICP
    results without compute times): the trace has the ticks and their stages; the rest is said."""
    from mcap.writer import Writer

    old = tmp_path / "old.mcap"
    with open(old, "wb") as f:
        w = Writer(f)
        w.start()
        w.add_metadata("dct.run", {"stages": json.dumps(list(STAGES)), "period_ms": "50.0", "clock": "lockstep"})
        sid = w.register_schema("dct.Tick", "jsonschema", b"{}")
        tick = w.register_channel("/dct/tick", "json", sid)
        inputs = w.register_channel("/dct/inputs", "json", sid)
        for k in range(5):
            m = {"tick": k, "scheduled_s": 0.05 * k, "lateness_ms": 0.0, "stage_ms": {s: 1.0 for s in STAGES},
                 "tick_ms": 6.5, "slack_work_ms": 2.0 if k == 2 else 0.0, "command_latency_ms": 0.0,
                 "state": "ACTIVE", "lidar_frame_end_s": 0.05 * k - 0.002}
            w.add_message(tick, log_time=k * 50_000_000, publish_time=0, data=json.dumps(m).encode())
            w.add_message(inputs, log_time=k * 50_000_000, publish_time=0, data=json.dumps(
                {"tick": k, "icp_results": [{"seq": k - 1, "stamp_s": 0.05 * k - 0.1}] if k else []}).encode())
        w.finish()
    out = tmp_path / "old.json"
    res = CliRunner().invoke(report_group, ["latency", str(old), "--trace", str(out)])
    assert res.exit_code == 0, res.output
    trace = json.loads(out.read_text())
    check_trace_format(trace)
    assert set(thread_names(trace).values()) == {"loop: tick"}
    assert sum(e["ph"] == "X" for e in trace["traceEvents"]) == 5 * (1 + len(STAGES))
    for what in ("0x111 writes: no command times", "slack work: no start times", "lidar frames:",
                 "ICP registrations: no compute times"):
        assert f"absent: {what}" in res.output
