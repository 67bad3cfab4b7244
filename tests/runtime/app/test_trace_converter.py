"""The trace converter on records made by hand: any mix of ticks (with and without a lidar frame,
late, over their period, with slack work), 0x111 writes, ICP results and VLM answers (answered,
failed, without a send time, taken by a tick the recording lacks) gives a trace in the format; the
edge cases each do what they should; the loader refuses a malformed message in one line."""
from __future__ import annotations

import json

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from runtime.app.reports.latency import ReportInputError
from runtime.app.reports.trace import chrome_trace
from runtime.app.reports.trace_data import IcpRec, TickRec, TraceSource, VlmRec, load_trace_source
from runtime.loop.telemetry import STAGES
from tests.runtime.app.trace_format import check_trace_format, slice_at, thread_names

PERIOD = 0.05


def _tick(k: int, stage_s=(0.001,) * 6, frame: bool = False, lateness: float = 0.0, slack: float = 0.0,
          origin: float = 0.0) -> TickRec:
    scheduled = origin + k * PERIOD
    total = sum(stage_s)
    return TickRec(tick=k, scheduled_s=scheduled, start_s=scheduled + lateness, stage_s=tuple(stage_s),
                   tick_s=total + 1e-5, command_latency_s=lateness + total, state="ACTIVE", missed=False,
                   slack_s=slack, command_written_s=total - 0.5 * stage_s[-1],
                   slack_start_s=total + 2e-5 if slack else None,
                   frame=(scheduled - 0.1, scheduled - 0.002) if frame else None)


def _source(ticks, clock="lockstep", **kw) -> TraceSource:
    writes = kw.pop("can_writes", None)
    if writes is None:  # each tick's command at its loop-clock time, a keep-alive between
        writes = [(t.scheduled_s + (t.command_latency_s if clock != "lockstep" else 0.0), 4e-5) for t in ticks]
        writes += [(t.scheduled_s + 0.02, 3e-5) for t in ticks]
    return TraceSource(name="hand.mcap", clock=clock, period_s=PERIOD, stages=STAGES, ticks=list(ticks),
                       can_writes=sorted(writes), **kw)


def _x(trace, name_start: str) -> list[dict]:
    return [e for e in trace["traceEvents"] if e["ph"] == "X" and e["name"].startswith(name_start)]


@st.composite
def _sources(draw):
    n = draw(st.integers(1, 25))
    clock = draw(st.sampled_from(["lockstep", "wall"]))
    origin = draw(st.sampled_from([0.0, 1.7e9]))  # simulated time, or a robot's ROS time
    ms = st.floats(0.0, 0.03)
    ticks = []
    for k in range(n):
        ticks.append(_tick(k, tuple(draw(st.lists(ms, min_size=6, max_size=6))), frame=draw(st.booleans()),
                           lateness=0.0 if clock == "lockstep" else draw(st.floats(0.0, 0.004)),
                           slack=draw(st.sampled_from([0.0, 0.0, 0.003, 0.2])), origin=origin))
    # A real-time loop starts its next tick after the one before (and its slack work) ended.
    if clock == "wall":
        fixed, t_free = [], -1.0
        for t in ticks:
            start = max(t.start_s, t_free)
            fixed.append(TickRec(**{**t.__dict__, "start_s": start}))
            t_free = start + max(t.tick_s, (t.slack_start_s or 0.0) + t.slack_s) + 1e-6
        ticks = fixed
    framed = [t for t in ticks if t.frame is not None]
    icp = []
    for t in framed:
        if draw(st.booleans()):
            got = t.tick + draw(st.integers(0, 5))  # 0: a result no later tick took; beyond n: not recorded
            icp.append(IcpRec(seq=t.tick, stamp_s=t.frame[0], tick=got, end_s=t.frame[1],
                              compute_s=draw(st.none() | st.floats(0.0, 0.3)), failed=draw(st.booleans())))
    if draw(st.booleans()):
        icp.append(IcpRec(seq=99, stamp_s=origin - 7.0, tick=0))  # a frame no recorded tick used
    vlm = []
    for _ in range(draw(st.integers(0, 3))):
        k = draw(st.integers(0, n + 2))
        sent = origin + draw(st.floats(-0.5, n * PERIOD))
        lat = draw(st.floats(0.0, 2.0))
        answered = sent + lat if draw(st.booleans()) else None
        vlm.append(VlmRec(capture_s=sent - 0.05, tick=k, latency_s=lat, sent_s=sent if answered else None,
                          answered_s=answered, error=draw(st.none() | st.just("timeout"))))
    return _source(ticks, clock, icp=icp, vlm=vlm)


@settings(max_examples=120, deadline=None)
@given(_sources())
def test_any_mix_of_records_gives_a_trace_in_the_format(src):
    trace, summary = chrome_trace(src)
    flows = check_trace_format(trace)
    c = summary.counts
    assert c["ticks"] == len(_x(trace, "tick ")) == len(src.ticks)
    assert len(_x(trace, "0x111 command")) == len(src.ticks) == c["0x111 commands"]
    stamps = {t.frame[0] for t in src.ticks if t.frame is not None}
    assert len(_x(trace, "lidar frame")) == len(stamps)
    names = [evs[0]["name"] for evs in flows.values()]
    assert names.count("lidar -> 0x111") + c.get("flows left out (out of order)", 0) >= len(stamps)
    ticks = {t.tick for t in src.ticks}
    drawable = [v for v in src.vlm if v.sent_s is not None and v.tick in ticks]
    assert len(_x(trace, "VLM request")) == len(drawable)
    assert c.get("VLM answers whose tick is not in the recording", 0) == sum(
        v.sent_s is not None and v.tick not in ticks for v in src.vlm)
    for t in _x(trace, "tick "):  # never longer than the time to the next tick
        nxt = [u["ts"] for u in _x(trace, "tick ") if u["ts"] > t["ts"]]
        assert not nxt or t["ts"] + t["dur"] <= min(nxt)


def test_ticks_without_a_frame_give_no_lidar_track_and_no_lidar_flow():
    trace, summary = chrome_trace(_source([_tick(k) for k in range(4)]))
    check_trace_format(trace)
    assert "lidar frames" not in thread_names(trace).values()
    assert not [e for e in trace["traceEvents"] if e["ph"] in "stf"]
    assert summary.counts["0x111 commands"] == 4 and summary.counts["0x111 between ticks"] == 4


def test_a_missing_vlm_answer_draws_nothing_and_one_whose_tick_is_gone_is_counted():
    ticks = [_tick(k) for k in range(4)]
    vlm = [VlmRec(capture_s=0.0, tick=2, latency_s=1.5),  # recorded without a send time
           VlmRec(capture_s=0.0, tick=40, latency_s=1.5, sent_s=0.01, answered_s=1.51),  # tick not recorded
           VlmRec(capture_s=0.0, tick=3, latency_s=0.1, sent_s=0.02, answered_s=0.12, error="timeout")]
    trace, summary = chrome_trace(_source(ticks, vlm=vlm))
    flows = check_trace_format(trace)
    (req,) = _x(trace, "VLM request")
    assert req["name"] == "VLM request (failed)" and req["args"]["error"] == "timeout"
    assert req["dur"] == 100_000 and req["args"]["taken_by_tick"] == 3
    assert summary.counts["VLM answers whose tick is not in the recording"] == 1
    (vlm_flow,) = [evs for evs in flows.values() if evs[0]["name"] == "VLM -> 0x111"]
    assert slice_at(trace, vlm_flow[1])["name"] == "partition" and slice_at(trace, vlm_flow[2])["args"]["tick"] == 3


def test_in_real_time_the_answer_is_placed_at_the_tick_that_took_it():
    """The runner's clock is time.monotonic, the loop's ROS time: only their difference is used."""
    ticks = [_tick(k, origin=1.7e9) for k in range(6)]
    vlm = [VlmRec(capture_s=0.0, tick=5, latency_s=0.2, sent_s=1000.0, answered_s=1000.2)]
    trace, _ = chrome_trace(_source(ticks, clock="wall", vlm=vlm))
    check_trace_format(trace)
    (req,) = _x(trace, "VLM request")
    part = next(e for e in _x(trace, "partition") if e["args"]["tick"] == 5)
    assert req["ts"] + req["dur"] == pytest.approx(part["ts"] + part["dur"] / 2, abs=1)
    assert req["dur"] == pytest.approx(200_000, abs=1)


def test_a_tick_longer_than_its_period_is_squeezed_and_counted():
    ticks = [_tick(0, (0.001, 0.002, 0.1, 0.01, 0.001, 0.001)), _tick(1)]
    trace, summary = chrome_trace(_source(ticks))
    check_trace_format(trace)
    first = next(e for e in _x(trace, "tick ") if e["args"]["tick"] == 0)
    assert first["dur"] <= PERIOD * 1e6 and first["args"]["drawn_scale"] < 0.5
    assert first["args"]["tick_ms"] == pytest.approx(115.01)  # the measured time, in the args
    assert summary.counts["ticks squeezed"] == 1


def test_icp_results_follow_their_frame_to_the_tick_that_received_them():
    ticks = [_tick(k, frame=k % 2 == 0) for k in range(8)]
    icp = [IcpRec(seq=0, stamp_s=ticks[2].frame[0], tick=6, end_s=ticks[2].frame[1], compute_s=0.03),
           IcpRec(seq=1, stamp_s=-42.0, tick=3, compute_s=0.01)]  # its frame: used by no recorded tick
    trace, summary = chrome_trace(_source(ticks, icp=icp))
    flows = check_trace_format(trace)
    (reg,) = _x(trace, "ICP #")
    assert (reg["args"]["handed_over_tick"], reg["args"]["received_tick"]) == (2, 6)
    (worker,) = _x(trace, "registration (worker)")
    assert worker["dur"] == 30_000 and worker["ts"] == reg["ts"]
    assert summary.counts["ICP results without the tick that handed over their frame"] == 1
    (path,) = [evs for evs in flows.values() if evs[0]["name"] == "lidar -> ICP -> 0x111"]
    assert [slice_at(trace, e)["args"].get("tick") for e in path] == [2, None, 6, 6]


def test_the_format_check_itself_catches_overlaps_and_unpaired_flows():
    trace, _ = chrome_trace(_source([_tick(k, frame=True) for k in range(3)]))
    check_trace_format(trace)
    bad = json.loads(json.dumps(trace))
    x = next(e for e in bad["traceEvents"] if e["ph"] == "X" and e["name"] == "odometry")
    x["dur"] += 10_000_000  # starts inside its tick, ends past it
    with pytest.raises(AssertionError, match="overlaps"):
        check_trace_format(bad)
    bad = json.loads(json.dumps(trace))
    bad["traceEvents"] = [e for e in bad["traceEvents"] if e["ph"] != "f"]
    with pytest.raises(AssertionError):
        check_trace_format(bad)


def _write_mcap(path, ticks: list[dict], info: dict | None = None) -> None:
    from mcap.writer import Writer

    with open(path, "wb") as f:
        w = Writer(f)
        w.start()
        w.add_metadata("dct.run", info or {"stages": json.dumps(list(STAGES)), "period_ms": "50.0"})
        ch = w.register_channel("/dct/tick", "json", w.register_schema("dct.Tick", "jsonschema", b"{}"))
        for i, m in enumerate(ticks):
            w.add_message(ch, log_time=i, publish_time=i, data=json.dumps(m).encode())
        w.finish()


_GOOD = {"tick": 0, "scheduled_s": 0.0, "stage_ms": {s: 1.0 for s in STAGES}, "tick_ms": 6.0}


@pytest.mark.parametrize("change, says", [
    ({"scheduled_s": "soon"}, "/dct/tick tick 0: scheduled_s: expected a finite number"),
    ({"tick": 1.5}, "tick: expected an integer"),
    ({"stage_ms": [1, 2]}, "stage_ms: expected an object"),
    ({"command_written_at_ms": True}, "command_written_at_ms: expected a finite number"),
])
def test_a_malformed_tick_is_refused_in_one_line_naming_the_field(tmp_path, change, says):
    p = tmp_path / "bad.mcap"
    _write_mcap(p, [{**_GOOD, **change}])
    with pytest.raises(ReportInputError) as e:
        load_trace_source(p)
    assert says in str(e.value) and "\n" not in str(e.value)


_JSONISH = st.recursive(st.none() | st.booleans() | st.integers(-5, 5) | st.floats(-1e3, 1e3) | st.text(max_size=4),
                        lambda c: st.lists(c, max_size=3) | st.dictionaries(st.text(max_size=6), c, max_size=4),
                        max_leaves=8)


@settings(max_examples=60, deadline=None)
@given(st.lists(st.fixed_dictionaries({}, optional={k: _JSONISH for k in (
    "tick", "scheduled_s", "lateness_ms", "stage_ms", "tick_ms", "slack_work_ms", "command_written_at_ms",
    "slack_work_start_at_ms", "lidar_frame_stamp_s", "lidar_frame_end_s")}) | _JSONISH, min_size=1, max_size=3))
def test_the_loader_reads_or_refuses_any_tick_message_in_one_line(tmp_path_factory, msgs):
    p = tmp_path_factory.mktemp("fuzz") / "f.mcap"
    _write_mcap(p, msgs)
    try:
        src = load_trace_source(p)
    except ReportInputError as exc:
        assert "\n" not in str(exc)
        return
    check_trace_format(chrome_trace(src)[0])


def test_a_frame_recorded_as_it_arrived_shows_its_delivery_and_its_flow_starts_there(tmp_path):
    """`dct run --record`: the receiver's tap stamps each raw frame on arrival; the tick that used
    the frame names its start, which is the raw message's header stamp."""
    from types import SimpleNamespace

    import numpy as np

    from runtime.config import load_controller_config
    from runtime.io.recording import RunRecorder
    from runtime.loop.telemetry import TickTelemetry
    from tests.runtime.io.test_recording_inputs import _custom_msg

    t0 = 1_760_000_000.25
    out = tmp_path / "robot.mcap"
    rec = RunRecorder(out)
    scan = SimpleNamespace(stamp_s=t0, point_time_offsets_s=np.array([0.0, 0.098]), frame_duration_s=0.1)
    snap = SimpleNamespace(t_s=t0, pose=SimpleNamespace(x_m=0.0, y_m=0.0, yaw_rad=0.0), scan=None,
                           goal=SimpleNamespace(x_m=1.0, y_m=0.0, yaw_rad=0.0), points_fix=np.zeros((0, 2)),
                           plan=None, reference_path=None, partition_frame=None, vlm_answers=0,
                           vlm_last_answer_s=None, vlm_masks=(), inputs_delivered=0, icp_delivered=())
    ctl = SimpleNamespace(snapshot=snap)
    hook = rec.attach(ctl, load_controller_config(), {"clock": "wall"})
    rec.sensor_tap(lambda: t0 + 0.13)("lidar", "/livox/lidar", "livox_ros_driver2/msg/CustomMsg", _custom_msg(t0), 1)
    tel = TickTelemetry(capacity=8)
    bus = rec.wrap_bus(SimpleNamespace(send=lambda msg, timeout=None: None), lambda: clock[0])
    clock = [0.0]
    for k in range(3):
        row = tel.begin_tick()
        row["tick"], row["scheduled_s"] = k, t0 + 0.1 + 0.05 * k
        row["stage_s"][:] = 0.001
        row["tick_s"], row["command_written_s"], row["command_latency_s"] = 0.0061, 0.0055, 0.0056
        clock[0] = row["scheduled_s"] + 0.0055
        bus.send(SimpleNamespace(arbitration_id=0x111, data=bytes(8)))
        tel.commit_tick(row)
        ctl.snapshot = SimpleNamespace(**{**vars(snap), "scan": scan if k == 1 else None, "inputs_delivered": 1})
        hook(row)
    rec.close()
    src = load_trace_source(out)
    assert src.lidar_arrivals == [(pytest.approx(t0, abs=1e-6), pytest.approx(t0 + 0.13))]
    assert not any("lidar arrivals" in n for n in src.missing)
    trace, summary = chrome_trace(src)
    flows = check_trace_format(trace)
    (frame,) = _x(trace, "lidar frame")
    assert frame["args"]["arrival_s"] == pytest.approx(t0 + 0.13) and summary.counts["lidar arrivals"] == 1
    (delivery,) = _x(trace, "delivery")
    assert delivery["dur"] == pytest.approx(0.032e6, abs=1)  # the frame's last point -> arrival
    (path,) = [evs for evs in flows.values() if evs[0]["name"] == "lidar -> 0x111"]
    assert slice_at(trace, path[0])["name"] == "delivery" and slice_at(trace, path[-1])["args"]["tick"] == 1
