"""`dct replay`: the clock follows the live ticks (and skips what the live loop skipped), ICP registers
what the live run registered at the live ticks, outputs are checked before the work, bad inputs
are one line and exit 2, and a drivers' bag (rosbag2 folder or MCAP file) replays deterministically:
the same bag gives the same trajectory at any rate, and the replay's own recording replays to the
same trajectory again (the dct-recording path)."""
from __future__ import annotations

import json
import math
from types import SimpleNamespace

import numpy as np
import pytest
from click.testing import CliRunner

from runtime.app.replay.cli import replay_command
from runtime.app.replay.clock import ReplayClock, ReplayDesyncError, TickPlan
from runtime.app.replay.icp import ScriptedIcpWorker, icp_schedule
from runtime.app.replay.outputs import FILES, compare_odometry, output_paths, tum_text
from runtime.app.replay.source import TickInputs
from runtime.loop.fixed_rate import FixedRateLoop
from tests.runtime.app.replay_data import write_mcap_bag, write_rosbag2

PERIOD = 0.05


class _Controlled:
    """What the loop drives, noting each tick's scheduled time and the clock's reading."""

    state_code = 0
    command = (0.0, 0.0)

    def __init__(self, clock) -> None:
        self.clock = clock
        self.ticks: list[tuple[float, float]] = []
        self.keepalives: list[float] = []

    def tick(self, scheduled_s, stages) -> None:
        self.ticks.append((scheduled_s, self.clock.now()))

    def keepalive(self, now_s: float) -> None:
        self.keepalives.append(now_s)

    def note_deadline(self, missed: bool) -> None:
        pass


def _loop_over(plans: list[TickPlan]):
    seen = []
    clock = ReplayClock(iter(plans), lambda plan, after: seen.append((plan.tick, after.tick if after else None)),
                        PERIOD)
    loop = FixedRateLoop(clock, period_s=PERIOD, stage_budgets_s={}, command_deadline_s=0.04,
                         keepalive_period_s=0.02, after_tick=lambda row: clock.after_tick())
    ctl = _Controlled(clock)
    loop.run(ctl, lambda: clock.done)
    return clock, loop, ctl, seen


def test_the_loop_runs_the_live_ticks_at_their_times_and_skips_what_the_live_loop_skipped():
    t0 = 1_760_000_000.0
    ticks = [0, 1, 2, 5, 6]
    plans = [TickPlan(k, t0 + k * PERIOD, t0 + k * PERIOD + 0.001 * (k + 1)) for k in ticks]
    clock, loop, ctl, seen = _loop_over(plans)
    assert [s for s, _ in ctl.ticks] == [p.scheduled_s for p in plans]
    assert [n for _, n in ctl.ticks] == [p.now_s for p in plans]  # the controller's clock is the live one
    assert seen == [(0, 1), (1, 2), (2, 5), (5, 6), (6, None)]
    assert loop.telemetry.ticks_skipped == 2 and clock.ticks == 5
    # keep-alives between consecutive ticks, none across the skipped ones
    assert ctl.keepalives and not any(t0 + 2 * PERIOD < t < t0 + 5 * PERIOD for t in ctl.keepalives)


def test_a_tick_off_the_loops_grid_is_a_desync():
    t0 = 100.0
    plans = [TickPlan(0, t0, t0), TickPlan(1, t0 + PERIOD + 0.01, t0 + PERIOD + 0.01)]
    with pytest.raises(ReplayDesyncError, match="past the next planned tick 1"):
        _loop_over(plans)


def _fake_result(job):
    from runtime.odometry.worker import _failed, _identity

    return _failed(_identity(job), "fake")


class _Engine:
    def process(self, job):
        return _fake_result(job)


def _job(seq: int, stamp: float):
    from runtime.odometry.icp import IcpJob

    return IcpJob(seq=seq, stamp_s=stamp, end_s=stamp + 0.1, points=np.zeros((3, 3), np.float32),
                  offsets_s=np.zeros(3, np.float32), duration_s=0.1, ready_at_s=stamp + 0.2)


def test_icp_registers_the_live_frames_and_delivers_each_at_its_live_tick():
    from runtime.odometry.worker import InlineIcpWorker

    ticks = [TickInputs(k, 0.05 * k, 0.05 * k + 0.002, 0, icp, (0.0, 0.0, 0.0)) for k, icp in
             [(0, ()), (4, ((0, 0.0),)), (9, ((2, 0.2),))]]
    schedule = icp_schedule(ticks)
    assert schedule == {0: (0.202, 0.0), 2: (0.452, 0.2)}
    w = ScriptedIcpWorker(InlineIcpWorker(_Engine), schedule)
    for seq, stamp in ((0, 0.0), (1, 0.1), (2, 0.2)):
        w.submit(_job(seq, stamp))
    assert (w.dropped, w.submitted, w.mismatched) == (1, 2, 0)  # frame 1: the live worker was busy
    assert w.poll(0.2) == [] and [r.seq for r in w.poll(0.202)] == [0]
    assert w.poll(0.45) == [] and [r.seq for r in w.poll(0.452)] == [2]
    w.submit(_job(3, 0.3))  # in flight when the live run ended: never delivered
    w.schedule[4] = (0.6, 0.4)
    w.submit(_job(4, 0.45))  # another frame than the live job 4: out of step, named
    assert w.dropped == 2 and w.mismatched == 1


def test_outputs_are_checked_before_the_work(tmp_path):
    from calibration.outputs import OutputPathError

    paths = output_paths(tmp_path / "new", force=False)
    assert {p.name for p in paths.values()} == set(FILES.values()) and not (tmp_path / "new").exists()
    (tmp_path / "f").write_text("x")
    with pytest.raises(OutputPathError, match="is a file; give a folder"):
        output_paths(tmp_path / "f", force=False)
    with pytest.raises(OutputPathError, match="does not exist"):
        output_paths(tmp_path / "a" / "b", force=False)
    out = tmp_path / "out"
    out.mkdir()
    (out / "odometry.tum").write_text("old")
    with pytest.raises(OutputPathError, match="odometry.tum already exists"):
        output_paths(out, force=False)
    assert output_paths(out, force=True)["trajectory"] == out / "odometry.tum"
    with pytest.raises(OutputPathError, match="also an input"):
        output_paths(out, force=True, inputs=[out / "replay.mcap"])


def test_tum_lines_and_the_odometry_comparison():
    poses = [(10.0, 1.0, 2.0, math.pi / 2), (10.05, 1.5, 2.0, -math.pi / 2)]
    assert tum_text(poses).splitlines()[0] == "10.000000000 1.000000000 2.000000000 0 0 0 0.707106781 0.707106781"
    live = [(int(round(t * 1e9)), x + 0.003, y - 0.004, yaw + 0.01) for t, x, y, yaw in poses] + [(5, 0.0, 0.0, 0.0)]
    cmp = compare_odometry(live, poses)
    assert cmp["matched"] == 2 and cmp["live_poses"] == 3
    assert cmp["max_m"] == pytest.approx(0.005) and cmp["mean_m"] == pytest.approx(0.005)
    assert cmp["max_yaw_rad"] == pytest.approx(0.01)
    assert compare_odometry(live[2:], poses)["matched"] == 0


def _invoke(*args):
    return CliRunner().invoke(replay_command, [str(a) for a in args])


def test_bad_inputs_exit_2_with_one_line_before_any_work(tmp_path):
    from runtime.config import load_controller_config
    from runtime.io.recording import RunRecorder

    r = _invoke(tmp_path / "none.mcap", "--out", tmp_path / "o")
    assert r.exit_code == 2 and "no such file or folder" in r.output and len(r.output.strip().splitlines()) == 1
    bad = tmp_path / "bad.mcap"
    bad.write_bytes(b"not mcap")
    r = _invoke(bad, "--out", tmp_path / "o")
    assert r.exit_code == 2 and "is not an MCAP file" in r.output
    old = tmp_path / "old.mcap"  # a dct recording from before /dct/inputs
    rec = RunRecorder(old)
    hook = rec.attach(SimpleNamespace(snapshot=None), load_controller_config(), {"clock": "test"})
    from tests.runtime.io.test_recording import _rows

    for row in _rows(3):
        hook(row)
    rec.close()
    r = _invoke(old, "--out", tmp_path / "o")
    assert r.exit_code == 2 and "without /dct/inputs" in r.output
    lockstep = tmp_path / "lockstep.mcap"  # ticks, but the simulator handed the sensors over in its process
    rec = RunRecorder(lockstep)
    snap = SimpleNamespace(t_s=0.0, pose=SimpleNamespace(x_m=0.0, y_m=0.0, yaw_rad=0.0), scan=None,
                           goal=SimpleNamespace(x_m=1.0, y_m=0.0, yaw_rad=0.0), points_fix=np.zeros((0, 2)), plan=None,
                           reference_path=None, partition_frame=None, vlm_answers=0, vlm_last_answer_s=None,
                           vlm_masks=(), inputs_delivered=3, icp_delivered=())
    hook = rec.attach(SimpleNamespace(snapshot=snap), load_controller_config(), {"clock": "lockstep"})
    for row in _rows(3):
        hook(row)
    rec.close()
    r = _invoke(lockstep, "--out", tmp_path / "o")
    assert r.exit_code == 2 and "lockstep simulation's recording" in r.output and "--realtime" in r.output
    bag = write_mcap_bag(tmp_path / "bag.mcap", duration_s=0.3)
    r = _invoke(bag, "--out", tmp_path / "o", "--lidar-topic", "/nothing", "--imu-topic", "/nothing")
    assert r.exit_code == 2 and "none of the sensor topics" in r.output
    r = _invoke(bag, "--out", tmp_path / "o", "--imu-topic", "/livox/lidar")
    assert r.exit_code == 2 and "/livox/lidar is sensor_msgs/msg/PointCloud2, which the imu cannot be read from" in r.output
    out = tmp_path / "o"
    out.mkdir()
    (out / "replay.json").write_text("{}")
    r = _invoke(bag, "--out", out)
    assert r.exit_code == 2 and "replay.json already exists" in r.output
    assert sorted(p.name for p in out.iterdir()) == ["replay.json"]


def test_a_drivers_bag_replays_deterministically_and_its_replay_replays_the_same(tmp_path):
    from runtime.app.reports.latency import latency_report, load_ticks

    bag = write_rosbag2(tmp_path / "bag", duration_s=2.0)
    r1 = _invoke(bag, "--out", tmp_path / "r1")
    assert r1.exit_code == 0, r1.output
    s1 = json.loads((tmp_path / "r1" / "replay.json").read_text())
    assert s1["kind"] == "bag" and s1["inputs"]["sensor_samples"] == 20 + 400 and s1["inputs"]["can_frames"] == 0
    assert s1["icp"]["frames_submitted"] == 20 and s1["icp"]["fused"] >= 15 and s1["sensor_errors"] == {}
    assert s1["controller_state"] in ("INITIALIZING", "STOPPED")  # no base: it never starts, and says why
    traj = (tmp_path / "r1" / "odometry.tum").read_text().splitlines()
    assert len(traj) == s1["ticks"] >= 50
    last = [float(v) for v in traj[-1].split()]
    assert math.hypot(last[1], last[2]) < 0.01  # the lidar stood still
    assert latency_report(load_ticks(tmp_path / "r1" / "replay.mcap"))["run"]["ticks"] == s1["ticks"]
    assert (tmp_path / "r1" / "latency.html").stat().st_size > 1000
    # The same bag as one MCAP file, paced at the recorded rate: the same trajectory
    mcap_bag = write_mcap_bag(tmp_path / "bag.mcap", duration_s=2.0)
    r2 = _invoke(mcap_bag, "--out", tmp_path / "r2", "--rate", "recorded")
    assert r2.exit_code == 0, r2.output
    s2 = json.loads((tmp_path / "r2" / "replay.json").read_text())
    assert s2["replay_wall_s"] >= 0.9 * s1["recording_s"]
    assert (tmp_path / "r2" / "odometry.tum").read_text() == "\n".join(traj) + "\n"
    # The replay's recording is a dct recording: replayed, it gives the same poses at every tick
    r3 = _invoke(tmp_path / "r1" / "replay.mcap", "--out", tmp_path / "r3")
    assert r3.exit_code == 0, r3.output
    s3 = json.loads((tmp_path / "r3" / "replay.json").read_text())
    assert s3["kind"] == "dct" and s3["ticks"] == s1["ticks"] and s3["icp"]["out_of_step"] == 0
    from runtime.io.recording.reader import read_recording

    # it says its ticks' now_s are their own: a replay takes them as they are
    assert read_recording(tmp_path / "r1" / "replay.mcap", topics=[]).metadata["dct.run"]["tick_now"] == "own"
    assert s3["inputs"]["ticks_now_repaired"] == []
    assert s3["odometry_vs_live"]["matched"] == s1["ticks"] and s3["odometry_vs_live"]["max_m"] == 0.0
    assert (tmp_path / "r3" / "odometry.tum").read_text() == "\n".join(traj) + "\n"
    r4 = _invoke(tmp_path / "r1" / "replay.mcap", "--out", tmp_path / "r3")
    assert r4.exit_code == 2 and "already exists" in r4.output
    # Recorded in parts of 0.6 s, the replay's recording replays as the whole run
    r5 = _invoke(bag, "--out", tmp_path / "r5", "--record-part-minutes", "0.01")
    assert r5.exit_code == 0, r5.output
    assert (tmp_path / "r5" / "replay.part3.mcap").exists()
    assert latency_report(load_ticks(tmp_path / "r5" / "replay.mcap"))["run"]["ticks"] == s1["ticks"]
    r6 = _invoke(tmp_path / "r5" / "replay.mcap", "--out", tmp_path / "r6")
    assert r6.exit_code == 0, r6.output
    s6 = json.loads((tmp_path / "r6" / "replay.json").read_text())
    assert s6["ticks"] == s1["ticks"] and s6["inputs"]["sensor_samples"] == s1["inputs"]["sensor_samples"]
    assert (tmp_path / "r6" / "odometry.tum").read_text() == "\n".join(traj) + "\n"


def test_a_bags_camera_info_is_replayed_and_checked_and_its_replay_replays_it_in_step(tmp_path):
    """The camera driver's CameraInfo (here on a topic of its own, named with --camera-info-topic)
    reaches the calibration check as live; the replay's recording carries it, numbered as the inbox
    counted it, so replaying that recording feeds every tick the same samples."""
    fx = 337.20964009 * 1.05  # the nominal camera's focal length, 5% off: beyond the 1% tolerance
    bag = write_mcap_bag(tmp_path / "bag.mcap", duration_s=1.0, camera_info=("/cam/info", fx))
    r1 = _invoke(bag, "--out", tmp_path / "r1", "--camera-info-topic", "/cam/info")
    assert r1.exit_code == 0, r1.output
    s1 = json.loads((tmp_path / "r1" / "replay.json").read_text())
    assert s1["streams"]["camera_info"] == ["/cam/info", "sensor_msgs/msg/CameraInfo"]
    assert s1["inputs"]["sensor_samples"] == 10 + 200 + 5 and s1["sensor_errors"] == {}
    check = s1["calibration_check"]
    assert check["camera_infos_compared"] == 1 and "the camera reports 354.1 (+5.0%, tolerance 1%)" in check["intrinsics"]
    assert check["mismatch"].startswith("camera intrinsics:")
    from runtime.io.recording import read_recording

    rec = read_recording(tmp_path / "r1" / "replay.mcap", topics=["/cam/info", "/dct/inputs"])
    assert rec.topics["/cam/info"] == "sensor_msgs/msg/CameraInfo" and len(rec.messages["/cam/info"]) == 5
    assert rec.messages["/dct/inputs"][-1][1]["sensor_samples"] == 215  # every sample counted, CameraInfo too
    # The replay's recording names the topic in its config: replayed, the same inputs at every tick
    r2 = _invoke(tmp_path / "r1" / "replay.mcap", "--out", tmp_path / "r2")
    assert r2.exit_code == 0, r2.output
    s2 = json.loads((tmp_path / "r2" / "replay.json").read_text())
    assert s2["kind"] == "dct" and s2["streams"]["camera_info"] == ["/cam/info", "sensor_msgs/msg/CameraInfo"]
    assert s2["inputs"]["sensor_samples"] == 215 and s2["inputs"]["sensor_samples_missing"] == 0
    assert s2["odometry_vs_live"]["matched"] == s1["ticks"] == s2["ticks"] and s2["odometry_vs_live"]["max_m"] == 0.0
    assert s2["calibration_check"] == check
    assert (tmp_path / "r2" / "odometry.tum").read_text() == (tmp_path / "r1" / "odometry.tum").read_text()


def _answer(stamp: float, error: str | None = None):
    from models.vlm.interface import DetectedObject, VlmAnswer

    mask = np.zeros((4, 6), bool)
    mask[1:3, 2:5] = True
    objects = () if error else (DetectedObject(mask=mask, label="box", movable=True, contact_cost=2.0, confidence=0.9),)
    return VlmAnswer(stamp_s=stamp, camera_pose_odom=np.eye(4), objects=objects, backend="live", latency_s=0.4,
                     error=error)


def test_the_scripted_vlm_delivers_the_recorded_answers_at_their_ticks_in_order():
    from runtime.app.replay.vlm import ScriptedVlmRunner

    a1, a2, a3 = _answer(0.5), _answer(1.0, error="live: no answer within 5 s (abandoned)"), _answer(1.5)
    runner = ScriptedVlmRunner([(1.05, a1), (1.05, a2), (2.0, a3)])
    posted = []
    runner.post = lambda request, answer: posted.append((request.stamp_s, answer))
    for stamp in (0.5, 1.0):
        runner.submit(SimpleNamespace(stamp_s=stamp))
    assert runner.busy and runner.poll(1.0) == [] and runner.busy  # not before the live tick
    got = runner.poll(1.05)
    assert [a is b for a, b in zip(got, (a1, a2))] == [True, True] and len(got) == 2  # both, in order
    assert [p[0] for p in posted] == [0.5] and posted[0][1] is a1  # post-processing: the valid answer only
    assert not runner.busy
    runner.submit(SimpleNamespace(stamp_s=1.5))
    runner.submit(SimpleNamespace(stamp_s=2.5))  # the live run never got an answer to this one
    assert runner.poll(1.99) == [] and runner.poll(2.0) == [a3]
    assert runner.busy and runner.poll(100.0) == [] and runner.busy  # a missing answer stays missing
    c = runner.counters()
    assert (c["delivered"], c["failed"], c["mismatched"], runner.left) == (3, 1, 0, 0)


def test_a_scripted_answer_to_an_image_the_replay_did_not_send_is_out_of_step():
    from runtime.app.replay.vlm import ScriptedVlmRunner

    runner = ScriptedVlmRunner([(1.0, _answer(0.5)), (3.0, _answer(2.0))])
    runner.post = lambda request, answer: pytest.fail("no request: nothing to prepare")
    runner.submit(SimpleNamespace(stamp_s=0.7))
    assert len(runner.poll(1.0)) == 1 and runner.mismatched == 1 and not runner.busy
    assert runner.left == 1  # the replay ended before the second
