"""The sim-oracle backend on synthetic segmentation images, and the runner that runs backends
beside the tick (lockstep: delivery at the simulated latency; real time: timeouts, errors)."""
from __future__ import annotations

import threading
import time

import numpy as np
import pytest
from pydantic import ValidationError

from models.vlm.interface import VlmAnswer, VlmRequest
from models.vlm.runner import BackendRunner, BackendRunnerConfig
from models.vlm.sim_oracle import (
    PRESETS,
    OracleEntry,
    SimOracleBackend,
    SimOracleConfig,
    SimOracleError,
    mislabel_probability,
)

H, W = 60, 80

TABLE = {
    1: OracleEntry("wall", "fixed", structure=True),
    2: OracleEntry("cabinet", "fixed"),
    3: OracleEntry("box", "movable", contact_cost=1.5),
    4: OracleEntry("crate", "heavy"),
    5: OracleEntry("chair", "movable"),
    6: OracleEntry("chair", "movable"),  # a second geom of the same object
    7: OracleEntry("pebble", "movable"),
}


def _scene() -> np.ndarray:
    seg = np.full((H, W), -1, dtype=np.int32)
    seg[40:, :] = 0  # floor: not in the table
    seg[:10, :] = 1  # wall
    seg[10:30, 0:15] = 2  # cabinet
    seg[20:40, 20:30] = 3  # box
    seg[20:40, 35:45] = 4  # crate
    seg[15:25, 50:60] = 5  # chair seat
    seg[25:40, 52:58] = 6  # chair legs
    seg[30:33, 65:68] = 7  # pebble: 9 pixels, below min_pixels
    seg[12:14, 70:72] = 99  # an id the table does not know
    return seg


def _request(seg: np.ndarray, stamp_s: float = 0.0) -> VlmRequest:
    return VlmRequest(image=np.zeros((*seg.shape, 3), np.uint8), stamp_s=stamp_s, camera_pose_odom=np.eye(4),
                      prompt="what may the robot push?", segmentation=seg)


def _by_label(answer: VlmAnswer) -> dict:
    return {o.label: o for o in answer.objects}


def test_perfect_oracle_gives_exact_masks_labels_and_costs():
    seg = _scene()
    answer = SimOracleBackend(TABLE).query(_request(seg, 2.5))
    assert answer.error is None and answer.backend == "sim-oracle"
    assert answer.stamp_s == 2.5 and answer.latency_s == 1.5
    objs = _by_label(answer)
    assert [o.label for o in answer.objects] == ["wall", "cabinet", "box", "crate", "chair"]  # no pebble
    np.testing.assert_array_equal(objs["wall"].mask, seg == 1)
    np.testing.assert_array_equal(objs["cabinet"].mask, seg == 2)
    np.testing.assert_array_equal(objs["box"].mask, seg == 3)
    np.testing.assert_array_equal(objs["crate"].mask, seg == 4)
    np.testing.assert_array_equal(objs["chair"].mask, (seg == 5) | (seg == 6))
    assert [(o.label, o.movable, o.contact_cost) for o in answer.objects] == [
        ("wall", False, 10.0), ("cabinet", False, 10.0), ("box", True, 1.5),
        ("crate", True, 2.0),  # the heavy look-alike looks movable
        ("chair", True, 2.0)]
    assert all(o.confidence == 1.0 and o.mask.dtype == bool for o in answer.objects)


def test_heavy_told_apart_and_pixel_threshold_when_configured():
    seg = _scene()
    cfg = SimOracleConfig(heavy_looks_movable=False, min_pixels=5, fixed_cost=9.0, movable_cost=3.0)
    objs = _by_label(SimOracleBackend(TABLE, cfg).query(_request(seg)))
    assert (objs["crate"].movable, objs["crate"].contact_cost) == (False, 9.0)
    assert (objs["pebble"].movable, objs["pebble"].contact_cost) == (True, 3.0)
    assert objs["box"].contact_cost == 1.5  # its own cost wins over the default


def test_the_dangerous_mislabel_calls_a_named_fixed_object_movable_and_cheap():
    seg = _scene()
    objs = _by_label(SimOracleBackend(TABLE, SimOracleConfig(called_movable=("cabinet",))).query(_request(seg)))
    assert (objs["cabinet"].movable, objs["cabinet"].contact_cost) == (True, 2.0)
    assert not objs["wall"].movable  # nothing else changes


def test_presets_and_config_errors():
    assert SimOracleConfig.from_preset("gpt5").precision == 1.0
    assert SimOracleConfig.from_preset("gpt5").recall == 0.82
    g = SimOracleConfig.from_preset("gemini25", seed=3)
    assert (g.precision, g.recall, g.seed) == (0.75, 0.95, 3)
    assert set(PRESETS) >= {"gpt5", "gemini25", "perfect"}
    with pytest.raises(SimOracleError, match="preset 'gpt4'"):
        SimOracleConfig.from_preset("gpt4")
    with pytest.raises(ValidationError):
        SimOracleConfig(recal=0.5)
    with pytest.raises(ValidationError):
        SimOracleConfig(precision=0.0)
    with pytest.raises(ValidationError):
        SimOracleConfig(failure_rate=1.5)


def test_bad_tables_are_named():
    with pytest.raises(SimOracleError, match=r"table\[3\].*class"):
        SimOracleBackend({3: OracleEntry("x", "glass")})  # type: ignore[arg-type]
    with pytest.raises(SimOracleError, match=r"table\[-2\]"):
        SimOracleBackend({-2: OracleEntry("x", "fixed")})
    with pytest.raises(SimOracleError, match="contact_cost"):
        SimOracleBackend({1: OracleEntry("x", "fixed", contact_cost=11.0)})
    with pytest.raises(SimOracleError, match="several ids"):
        SimOracleBackend({1: OracleEntry("x", "fixed"), 2: OracleEntry("x", "movable")})
    with pytest.raises(SimOracleError, match=r"table\[1\].*deformable.*only for class movable"):
        SimOracleBackend({1: OracleEntry("x", "fixed", deformable=True)})


def test_a_deformable_object_is_answered_deformable_only_when_called_movable():
    seg = _scene()
    table = {**TABLE, 4: OracleEntry("curtain", "movable", contact_cost=1.0, deformable=True)}
    objs = _by_label(SimOracleBackend(table).query(_request(seg)))
    assert objs["curtain"].deformable and objs["curtain"].movable
    assert not any(o.deformable for o in objs.values() if o.label != "curtain")
    # a backend that misses it as fixed does not call it deformable (validate_object forbids it)
    missed = _by_label(SimOracleBackend(table, SimOracleConfig(recall=0.0)).query(_request(seg)))
    assert "curtain" not in missed or not missed["curtain"].deformable


def test_request_without_segmentation_is_an_error_answer():
    req = VlmRequest(image=np.zeros((H, W, 3), np.uint8), stamp_s=0.0, camera_pose_odom=np.eye(4), prompt="")
    answer = SimOracleBackend(TABLE).query(req)
    assert answer.objects == () and "no segmentation" in answer.error


def test_empty_table_and_empty_image_answer_nothing():
    assert SimOracleBackend({}).query(_request(_scene())).objects == ()
    assert SimOracleBackend(TABLE).query(_request(np.full((H, W), -1, np.int32))).objects == ()


def _grid_scene(n_movable: int, n_fixed: int):
    """One 6x6 block per object in a row, plus a wall strip."""
    n = n_movable + n_fixed
    seg = np.full((20, 8 * n), -1, dtype=np.int32)
    seg[:3, :] = 0
    table = {0: OracleEntry("wall", "fixed", structure=True)}
    for k in range(n):
        seg[8:14, 8 * k:8 * k + 6] = k + 1
        table[k + 1] = OracleEntry(f"m{k}" if k < n_movable else f"f{k}", "movable" if k < n_movable else "fixed")
    return seg, table


@pytest.mark.parametrize("preset", ["gpt5", "gemini25"])
def test_recall_and_precision_statistics_match_the_configuration(preset):
    seg, table = _grid_scene(10, 10)
    cfg = SimOracleConfig.from_preset(preset, seed=7)
    oracle = SimOracleBackend(table, cfg)
    tp = fp = 0
    n_requests = 500
    for i in range(n_requests):
        answer = oracle.query(_request(seg, 0.1 * i))
        for o in answer.objects:
            if o.label == "wall":
                assert not o.movable  # structure is never mislabelled
            if o.movable:
                tp += o.label.startswith("m")
                fp += o.label.startswith("f")
            elif o.label.startswith("f"):
                assert o.contact_cost == 10.0
    recall = tp / (10 * n_requests)
    precision = tp / (tp + fp)
    assert recall == pytest.approx(cfg.recall, abs=0.015)
    assert precision == pytest.approx(cfg.precision, abs=0.015)


def test_mislabel_probability_formula():
    # E[FP] = q * N_fix = TP (1 - P) / P
    assert mislabel_probability(0.75, 9, 10) == pytest.approx(9 * 0.25 / (0.75 * 10))
    assert mislabel_probability(1.0, 9, 10) == 0.0
    assert mislabel_probability(0.75, 0, 10) == 0.0
    assert mislabel_probability(0.75, 5, 0) == 0.0
    assert mislabel_probability(0.1, 5, 1) == 1.0  # clipped: too few fixed objects to be that wrong


def test_failure_rate():
    oracle = SimOracleBackend(TABLE, SimOracleConfig(failure_rate=0.3, seed=1))
    answers = [oracle.query(_request(_scene(), 0.05 * i)) for i in range(1000)]
    failed = [a for a in answers if a.error is not None]
    assert len(failed) / len(answers) == pytest.approx(0.3, abs=0.045)
    assert all(a.objects == () and "simulated backend failure" in a.error for a in failed)
    assert all(len(a.objects) == 5 for a in answers if a.error is None)


def _signature(answer: VlmAnswer):
    return answer.error, [(o.label, o.movable, o.contact_cost, o.mask.tobytes()) for o in answer.objects]


def test_same_seed_and_stamp_give_the_same_answer():
    seg, table = _grid_scene(6, 6)
    cfg = SimOracleConfig.from_preset("gemini25", failure_rate=0.2, seed=11)
    a, b = SimOracleBackend(table, cfg), SimOracleBackend(table, cfg)
    stamps = [0.1 * i for i in range(40)]
    first = [_signature(a.query(_request(seg, s))) for s in stamps]
    # Another instance, the requests in another order: the same answer per stamp.
    second = {s: _signature(b.query(_request(seg, s))) for s in reversed(stamps)}
    assert first == [second[s] for s in stamps]
    other = SimOracleBackend(table, cfg.model_copy(update={"seed": 12}))
    assert first != [_signature(other.query(_request(seg, s))) for s in stamps]


# ------------------------------------------------------------------------------------ runner


class _Recorder:
    """A backend that records what it was asked and from which thread."""

    name = "recorder"

    def __init__(self, latency_s: float | None = None, fail: bool = False) -> None:
        if latency_s is not None:
            self.latency_s = latency_s
        self.asked: list[float] = []
        self.threads: list[str] = []
        self.fail = fail

    def query(self, request: VlmRequest) -> VlmAnswer:
        self.asked.append(request.stamp_s)
        self.threads.append(threading.current_thread().name)
        if self.fail:
            raise ConnectionError("server down")
        return VlmAnswer(stamp_s=request.stamp_s, camera_pose_odom=request.camera_pose_odom, objects=(),
                         backend=self.name, latency_s=0.0)


def _req(stamp_s: float) -> VlmRequest:
    pose = np.eye(4)
    pose[0, 3] = stamp_s
    return VlmRequest(image=np.zeros((4, 4, 3), np.uint8), stamp_s=stamp_s, camera_pose_odom=pose, prompt="")


@pytest.mark.parametrize("threaded", [False, True])
def test_lockstep_delivers_at_exactly_the_simulated_latency(threaded):
    backend = _Recorder(latency_s=1.5)
    r = BackendRunner(backend, BackendRunnerConfig(lockstep_thread=threaded))
    assert r.latency_s == 1.5
    r.submit(_req(0.0))
    assert r.poll(0.0) == [] and r.poll(1.49) == []
    (answer,) = r.poll(1.5)
    assert (answer.stamp_s, answer.latency_s, answer.error) == (0.0, 1.5, None)
    assert answer.camera_pose_odom[0, 3] == 0.0
    assert r.poll(10.0) == []
    assert r.counters() == {"submitted": 1, "delivered": 1, "failed": 0, "timed_out": 0, "replaced": 0}
    assert (backend.threads[0] == "dct-vlm-backend") == threaded


def test_lockstep_one_in_flight_newest_waiting_replaces_older():
    backend = _Recorder()
    r = BackendRunner(backend, BackendRunnerConfig(latency_s=1.0))
    r.submit(_req(0.0))
    r.submit(_req(0.2), now_s=0.25)  # waits
    r.submit(_req(0.4), now_s=0.45)  # replaces 0.2
    assert r.replaced == 1 and r.busy
    (first,) = r.poll(1.0)
    assert first.stamp_s == 0.0 and (first.sent_s, first.answered_s) == (0.0, 1.0)
    # 0.4 starts when 0.0 is delivered (1.0), so it is delivered at 2.0: sent at 1.0, after its wait.
    assert r.poll(1.99) == []
    (second,) = r.poll(2.5)
    assert second.stamp_s == 0.4 and (second.sent_s, second.answered_s) == (1.0, 2.0)
    r.submit(_req(5.0), now_s=5.1)  # idle: starts at its submit time
    assert r.poll(6.09) == [] and [a.stamp_s for a in r.poll(6.1)] == [5.0]
    assert backend.asked == [0.0, 0.4, 5.0]  # 0.2 was never sent
    assert r.counters() == {"submitted": 4, "delivered": 3, "failed": 0, "timed_out": 0, "replaced": 1}


def test_lockstep_late_poll_delivers_in_order_and_settle_computes_outside_the_poll():
    backend = _Recorder()
    r = BackendRunner(backend, BackendRunnerConfig(latency_s=0.5))
    r.submit(_req(0.0))
    r.submit(_req(0.1))
    r.settle(0.49)
    assert backend.asked == []
    r.settle(0.5)  # the barrier: 0.0 computed here, 0.1 starts at 0.5
    assert backend.asked == [0.0]
    r.settle(1.0)
    assert backend.asked == [0.0, 0.1]
    assert [a.stamp_s for a in r.poll(3.0)] == [0.0, 0.1]
    assert backend.asked == [0.0, 0.1]  # poll computed nothing


def test_lockstep_raising_backend_gives_an_error_answer_at_the_latency():
    r = BackendRunner(_Recorder(fail=True), BackendRunnerConfig(latency_s=1.5))
    r.submit(_req(1.0))
    assert r.poll(2.4) == []
    (answer,) = r.poll(2.5)
    assert answer.objects == () and "ConnectionError: server down" in answer.error
    assert (r.delivered, r.failed) == (1, 1)


def test_lockstep_with_the_oracle_is_deterministic():
    seg, table = _grid_scene(5, 5)

    def run():
        r = BackendRunner(SimOracleBackend(table, SimOracleConfig.from_preset("gemini25", failure_rate=0.1)))
        out = []
        for k in range(60):
            t = 0.25 * k
            r.submit(_request(seg, t))
            r.settle(t + 0.25)
            out += [(round(t, 6), a.stamp_s, _signature(a)) for a in r.poll(t + 0.25)]
        return out, r.counters()

    first, second = run(), run()
    assert first == second
    assert first[1]["delivered"] > 5 and first[1]["replaced"] > 0


def _poll_until(r: BackendRunner, n: int = 1, limit_s: float = 20.0) -> list[VlmAnswer]:
    """Real time: poll (never blocking) until n answers arrived, or give up after limit_s."""
    out: list[VlmAnswer] = []
    end = time.monotonic() + limit_s
    while len(out) < n and time.monotonic() < end:
        out += r.poll(0.0)
        time.sleep(0.01)
    return out


class _Hanging:
    name = "hanging"

    def __init__(self) -> None:
        self.release = threading.Event()
        self.entered = threading.Event()

    def query(self, request: VlmRequest) -> VlmAnswer:
        self.entered.set()
        self.release.wait(30.0)
        return VlmAnswer(stamp_s=request.stamp_s, camera_pose_odom=request.camera_pose_odom, objects=(),
                         backend=self.name, latency_s=0.0)


def test_realtime_slow_backend_times_out_with_an_error_and_never_blocks_the_caller():
    backend = _Hanging()
    r = BackendRunner(backend, BackendRunnerConfig(clock="realtime", timeout_s=0.3, max_abandoned=1))
    try:
        r.submit(_req(0.0))  # returns although the backend is stuck (release is never set before finally)
        assert backend.entered.wait(10.0)
        early = r.poll(0.0)  # returns too, answer or not
        r.submit(_req(1.0))  # waits behind the stuck one
        first, second = early + _poll_until(r, n=2 - len(early))
        assert not backend.release.is_set()
        assert first.stamp_s == 0.0 and first.objects == () and "no answer within 0.3 s" in first.error
        assert first.latency_s >= 0.3
        assert first.answered_s - first.sent_s >= 0.3  # sent, abandoned after the timeout (wall clock)
        # The waiting request would need a thread, but the abandoned one still runs: it fails at once.
        assert second.stamp_s == 1.0 and second.objects == () and "backend hung" in second.error
        assert second.sent_s is None and second.answered_s is not None  # never sent
        assert r.counters() == {"submitted": 2, "delivered": 2, "failed": 2, "timed_out": 1, "replaced": 0}
    finally:
        backend.release.set()


def test_realtime_raising_backend_gives_an_error_answer():
    r = BackendRunner(_Recorder(fail=True), BackendRunnerConfig(clock="realtime"))
    r.submit(_req(3.0))
    (answer,) = _poll_until(r)
    assert answer.stamp_s == 3.0 and "ConnectionError: server down" in answer.error
    assert (r.failed, r.timed_out) == (1, 0)


def test_realtime_oracle_answer_waits_for_its_latency_and_newest_replaces_waiting():
    seg = _scene()
    backend = SimOracleBackend(TABLE, SimOracleConfig(latency_s=0.2))
    r = BackendRunner(backend, BackendRunnerConfig(clock="realtime", timeout_s=5.0))
    for k in range(3):
        r.submit(_request(seg, float(k)))
    answers = _poll_until(r, n=2)
    assert [a.stamp_s for a in answers] == [0.0, 2.0]
    assert all(a.error is None and len(a.objects) == 5 and a.latency_s >= 0.2 for a in answers)
    # Sent one after the other (the second once the first was answered), each answered after its latency.
    assert all(a.answered_s - a.sent_s >= 0.2 for a in answers) and answers[1].sent_s >= answers[0].answered_s
    assert r.counters() == {"submitted": 3, "delivered": 2, "failed": 0, "timed_out": 0, "replaced": 1}


def test_runner_config_errors():
    with pytest.raises(ValidationError, match="timeout_s"):
        BackendRunnerConfig(clock="realtime", latency_s=2.0, timeout_s=1.0)
    with pytest.raises(ValueError, match="timeout_s"):
        BackendRunner(_Recorder(latency_s=3.0), BackendRunnerConfig(clock="realtime", timeout_s=1.0))
    with pytest.raises(ValidationError):
        BackendRunnerConfig(clock="wallclock")
    r = BackendRunner(_Recorder())
    r.close()
    with pytest.raises(RuntimeError, match="after close"):
        r.submit(_req(0.0))


def test_runner_validates_objects_where_they_enter_dropping_bad_ones_by_name():
    """Whatever a backend's own checks, the runner checks each object against the request's
    image: a non-bool movable, a wrong-size or non-bool mask is dropped and named, the rest pass."""
    from models.vlm.interface import DetectedObject, VlmAnswer, VlmRequest
    from models.vlm.runner import BackendRunner, BackendRunnerConfig

    class Sloppy:
        name = "sloppy"

        def query(self, request):
            good = DetectedObject(np.ones((4, 6), bool), "box", True, 2.0, 0.9)
            bad = (DetectedObject(np.ones((4, 6), bool), "wall", "false", 2.0, 0.9),
                   DetectedObject(np.ones((8, 12), bool), "box", True, 2.0, 0.9),
                   DetectedObject(np.ones((4, 6), np.uint8), "box", True, 2.0, 0.9))
            return VlmAnswer(request.stamp_s, request.camera_pose_odom, (good, *bad), self.name, 0.0)

    runner = BackendRunner(Sloppy(), BackendRunnerConfig(clock="lockstep", latency_s=0.1))
    runner.submit(VlmRequest(np.zeros((4, 6, 3), np.uint8), 0.0, np.eye(4), "p"))
    (answer,) = runner.poll(0.2)
    assert [o.label for o in answer.objects] == ["box"] and len(answer.rejected) == 3
    assert any("movable" in r for r in answer.rejected) and any("mask shape" in r for r in answer.rejected)
    assert any("dtype" in r for r in answer.rejected)


def test_a_real_time_runner_refuses_a_backend_slower_than_its_timeout():
    from models.vlm.runner import BackendRunner, BackendRunnerConfig

    class Cfg:
        def worst_case_s(self):
            return 61.5

    class Slow:
        name, config = "slow", Cfg()

        def query(self, request):  # pragma: no cover - never called
            raise AssertionError

    with pytest.raises(ValueError, match="up to 61.5 s"):
        BackendRunner(Slow(), BackendRunnerConfig(clock="realtime", timeout_s=5.0))
