"""A recording whose tick carries a deadline stop's time instead of its own is replayed at the tick's start."""
from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace

from runtime.app.replay.source import ReplaySource, _tick_now, _tick_starts


def _rec(rows):
    return SimpleNamespace(messages={"/dct/tick": [(0, r) for r in rows]})


def test_a_tick_recorded_with_the_stop_verdicts_time_is_replayed_at_its_start():
    src = ReplaySource(Path("x.mcap"), "dct", {})
    started = _tick_starts(_rec([{"tick": 75, "scheduled_s": 3.75, "lateness_ms": 0.5},
                                 {"tick": 76, "scheduled_s": 3.80, "lateness_ms": 0.41}]))
    # the ordinary tick: its own now (a few microseconds after the loop's reading) is kept as recorded
    assert _tick_now(src, 75, 3.7505123, started) == 3.7505123
    # the tick the stop came after: recorded 62 ms late (the verdict's time), replayed at its start
    assert abs(_tick_now(src, 76, 3.8628, started) - 3.80041) < 1e-9
    # a tick without its /dct/tick row keeps what was recorded
    assert _tick_now(src, 77, 3.9, started) == 3.9
    assert src.now_repaired == [76]


def test_a_recording_that_says_its_ticks_now_are_their_own_is_never_repaired():
    """On a busy machine the controller reads its clock milliseconds after the loop's reading
    (measured: 3 ms); a recording that says each now_s is its tick's own keeps them all."""
    from runtime.io.recording.schemas import META_RUN, META_TICK_NOW, TICK_NOW_OWN

    rows = [{"tick": 37, "scheduled_s": 1.85, "lateness_ms": 0.241}]
    rec = _rec(rows)
    rec.metadata = {META_RUN: {META_TICK_NOW: TICK_NOW_OWN}}
    src = ReplaySource(Path("x.mcap"), "dct", {})
    assert _tick_now(src, 37, 1.8532, _tick_starts(rec)) == 1.8532
    assert src.now_repaired == []
    rec.metadata = {META_RUN: {}}  # an older recording: the same tick is taken for a stop's
    assert abs(_tick_now(src, 37, 1.8532, _tick_starts(rec)) - 1.850241) < 1e-9
    assert src.now_repaired == [37]

