"""Record a run to MCAP from a thread outside the tick.

The tick's side only copies a few values into a bounded queue (a deque append of a tuple: no
I/O, no JSON, no lock the writer could hold); a writer thread serialises them to JSON and writes
a chunked MCAP file. When the queue is full (the writer is behind: slow disk, busy CPU) or the
file cannot be written (full disk), records are dropped and counted per kind, never waited for:
a recording must not stall the control loop. The counts are printed by the caller and written
into the file's `dct.recording` metadata.

A cut-off file (power loss) reads up to its last complete chunk (runtime.io.recording.reader):
chunks are small (`chunk_size`) and the writer also closes a chunk every `flush_interval_s`.
The file is written under a temporary name beside the output and renamed onto it at the end;
the run's description (stages, budgets, config) is written first, so a cut-off file keeps it.

Parts (`split_every_s`): the MCAP writer keeps every chunk's index in memory until the file is
finished (about 1.3 kB a chunk, some 13 chunks a second in real time: 60 MB an hour), so a long
run is recorded in parts, as rosbag2 splits a bag by duration: every `split_every_s` of the
loop's clock the part is finished and renamed (`run.mcap`, then `run.part1.mcap`,
`run.part2.mcap`, ...) and the next begins with the run's description again (with its `part`
number and the `recording_id` all parts share) and /tf_static. Each part is a whole MCAP file
any reader opens; runtime.io.recording.reader joins them into the run.

Masks when they arrive: the hook notices a new VPP answer (the mask memory's `last_answer_s`
changed) and queues references to its entries (immutable) and three floats; the writer thread
counts their pixels, paints one downscaled label image coloured by contact cost and PNG-encodes
it (`/dct/vpp/answer` and `/dct/vpp/masks`). The answers the backend runner handed the stage at a
tick (a tuple the snapshot references) are queued as they are and written in full on the writer
thread (`/dct/vpp/backend_answer`, backend_answers.py), for `dct replay`. The writer also samples every live Python thread's
CPU time about once a second of wall time (`/dct/threads`, from /proc/self/task; nothing where
there is no /proc), with a first sample at start and a last at close, so the report can say what
each thread spent over the run.

ROS 2 channels: /tf (odom -> base_link every tick, from the pose the tick record carries) and
/tf_static (the sensor mounts given to `attach()`, once, queued at the first tick) are
tf2_msgs/msg/TFMessage in ROS 2 CDR (runtime.io.recording.ros_channels), serialised on the writer
thread like the JSON.

The sensor messages as received (`sensor_tap()`, called on the ROS receiver's thread): their raw
CDR bytes on their own topics, as ROS 2 channels (runtime.io.recording.raw_inputs), and per tick
on `/dct/inputs` what the tick took in (the sensor samples counted so far, the ICP results, the
goal): together what `dct replay` needs to hand a controller the same inputs at the same ticks.

Used by any loop: `attach()` returns the per-tick hook (FixedRateLoop's `after_tick`), and
`wrap_bus()` puts a recording proxy between a driver and its CAN bus.
The messages each record becomes are built in runtime.io.recording.messages.
"""
from __future__ import annotations

import io
import json
import math
import os
import tempfile
import threading
import time
import uuid
from collections import deque
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np

from runtime.io.recording import messages as M
from runtime.io.recording import raw_inputs as RAW
from runtime.io.recording import ros_channels as R
from runtime.io.recording import schemas as S
from runtime.io.recording.reader import existing_parts, part_path
from runtime.loop.telemetry import STAGES

#: Channel message kinds, and how each is counted when dropped.
KINDS = ("tick", "can", "points", "plan", "answer", "backend_answer", *RAW.KINDS)
#: Wall-clock seconds between two samples of the threads' CPU time.
THREAD_SAMPLE_EVERY_S = 1.0


class RecordingError(ValueError):
    """A recording that cannot be made (bad output path); the message says why in one line."""


def _ns(t_s: float) -> int:
    return max(0, int(round(t_s * 1e9)))


def thread_cpu_seconds(proc_root: str = "/proc") -> list[dict] | None:
    """[{name, tid, cpu_s}] of every live Python thread (user + system time from
    /proc/self/task/<tid>/stat); None where there is no /proc (not Linux). A thread that ended
    between the listing and the read is left out."""
    task = os.path.join(proc_root, "self", "task")
    if not os.path.isdir(task):
        return None
    tick = os.sysconf("SC_CLK_TCK") if hasattr(os, "sysconf") else 100
    out = []
    for th in threading.enumerate():
        tid = getattr(th, "native_id", None)
        if tid is None:
            continue
        try:
            with open(os.path.join(task, str(tid), "stat"), "rb") as f:
                stat = f.read()
        except OSError:
            continue
        fields = stat[stat.rfind(b")") + 2:].split()  # after "pid (comm) ": state is field 3
        try:
            cpu_s = (int(fields[11]) + int(fields[12])) / tick  # utime, stime: fields 14 and 15
        except (IndexError, ValueError):
            continue
        out.append({"name": th.name, "tid": int(tid), "cpu_s": cpu_s})
    return out


def _process_figures(proc_root: str = "/proc") -> dict:
    """{rss_mb, open_fds} of this process from /proc; {} where there is none."""
    try:
        with open(os.path.join(proc_root, "self", "statm"), "rb") as f:
            resident_pages = int(f.read().split()[1])
        fds = len(os.listdir(os.path.join(proc_root, "self", "fd")))
    except (OSError, ValueError, IndexError):
        return {}
    return {"rss_mb": resident_pages * os.sysconf("SC_PAGE_SIZE") / 2 ** 20, "open_fds": fds}


def _tick_inputs(snap) -> tuple | None:
    """What the tick took in, for /dct/inputs: (the controller's clock, the sensor samples its inbox
    had counted, the ICP results it received (IcpResult each, immutable: read on the writer thread),
    its goal); None without a ControllerSnapshot."""
    if getattr(snap, "inputs_delivered", None) is None:
        return None
    g = snap.goal
    return (float(snap.t_s), int(snap.inputs_delivered), tuple(snap.icp_delivered),
            (float(g.x_m), float(g.y_m), float(g.yaw_rad)))


class RunRecorder:
    """One MCAP recording. Use as a context manager (or call `close()`): the file is finished
    and renamed onto `path` even when the run raised (the log of a failed run is the one wanted).

    queue_capacity: records waiting for the writer; beyond it records are dropped and counted.
    points_every_ticks: P_fix / partition counts / plan every this many ticks (the lower rate).
    max_raw_pending_bytes: raw sensor bytes waiting for the writer beyond which a sample is dropped.
    split_every_s: loop-clock seconds per part (module docstring); None: one file however long.
    """

    def __init__(
        self,
        path: str | Path,
        *,
        force: bool = False,
        stages: tuple[str, ...] = STAGES,
        queue_capacity: int = 1 << 15,
        chunk_size: int = 64 * 1024,
        flush_interval_s: float = 1.0,
        points_every_ticks: int = 10,
        compression: str = "zstd",
        opener: Callable[[str], Any] | None = None,
        max_raw_pending_bytes: int = 64 << 20,
        split_every_s: float | None = None,
    ) -> None:
        from calibration.outputs import OutputPathError, check_output_path

        if queue_capacity <= 0 or points_every_ticks <= 0:
            raise RecordingError("recorder queue_capacity and points_every_ticks must be positive")
        try:
            self.path = check_output_path(path, what="--record", overwrite=force)
        except OutputPathError as exc:
            raise RecordingError(str(exc)) from exc
        if not str(self.path).endswith(".mcap"):
            raise RecordingError(f"--record {self.path}: the file name must end in .mcap")
        if split_every_s is not None and not (math.isfinite(split_every_s) and split_every_s > 0):
            raise RecordingError(f"--record: a part's length must be a positive number of seconds, not {split_every_s}")
        if split_every_s is not None and not force:
            taken = sorted(str(q) for q in existing_parts(self.path))
            if taken:
                raise RecordingError(f"--record {self.path}: parts of an earlier recording are there ({taken[0]}, "
                                     f"{len(taken)} in all): move them or pass --force")
        self.split_every_s = split_every_s
        self.recording_id = uuid.uuid4().hex
        self.part = 0  # the part being written
        self.parts: list[str] = []  # the parts finished and renamed, in order
        self._part_t0: float | None = None  # loop clock of the part's first tick
        self._run_meta: dict | None = None
        self._mounts = None
        self._opener, self._chunk_size, self._compression = opener, chunk_size, compression
        self.force = force
        self.stages = tuple(stages)
        self.queue_capacity = int(queue_capacity)
        self.points_every_ticks = int(points_every_ticks)
        self.flush_interval_s = float(flush_interval_s)
        self.max_raw_pending_bytes = int(max_raw_pending_bytes)
        # Raw bytes queued (only the receiver's thread adds) and written (only the writer's): the
        # difference is what waits, with no counter two threads write.
        self._raw_queued_bytes = 0
        self._raw_written_bytes = 0
        self._raw: RAW.RawInputWriter | None = None
        self._open(opener, chunk_size, compression)
        self._queue: deque = deque()
        self.dropped = dict.fromkeys(KINDS, 0)  # queue full (counted on the tick's side)
        self.dropped_write_error = 0  # counted on the writer's side
        self.written = dict.fromkeys(KINDS, 0)
        self.write_error: str | None = None
        self.bad_records = 0  # records that would not serialise (a bug, not the disk)
        self.bad_record_error: str | None = None
        self.ticks_seen = 0
        self._channels: dict[str, int] = {}
        self._closing = False
        self._closed = False
        self._started = False
        self._run_ended_with: str | None = None
        self._last_plan: object = None
        self._last_reference: object = None
        self._last_answer_s: float | None = None
        self._last_answers = 0  # the VPP stage's answer count at the last /dct/vpp/backend_answer
        self.thread_samples = 0
        self._threads_supported = True
        self._last_t_s = 0.0  # loop-clock time of the newest tick written: the threads' log time
        self._tf_frames = ("odom", "base_link")  # /tf parent and child: config.ros.outputs' frames
        self._wall0 = time.monotonic()
        self._thread = threading.Thread(target=self._writer_main, name="dct-mcap-writer", daemon=True)
        self._thread.start()

    def _open(self, opener: Callable[[str], Any] | None, chunk_size: int, compression: str) -> None:
        """The temporary file beside the output and the MCAP writer on it."""
        from mcap.writer import CompressionType, Writer

        parent = self.path.parent if str(self.path.parent) else Path(".")
        name = part_path(self.path, self.part).name
        fd, tmp = tempfile.mkstemp(prefix=f".{name}.", suffix=".part", dir=parent)
        os.close(fd)
        self.tmp_path = Path(tmp)
        # opener: tests put a slow or failing file object here (full disk, slow disk).
        self._file = opener(tmp) if opener is not None else open(tmp, "wb")
        if isinstance(self._file, io.RawIOBase):  # our buffer, so that close() flushes it
            self._file = io.BufferedWriter(self._file)
        self._part_open = True  # a temporary file to finish and rename
        self._writer = Writer(self._file, chunk_size=chunk_size,
                              compression={"zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4,
                                           "none": CompressionType.NONE}[compression])

    # ---------------------------------------------------------------- the tick's side
    def _put(self, kind: str, item: tuple) -> None:
        """O(1), never blocks: append, or count a drop when the writer is behind."""
        if len(self._queue) >= self.queue_capacity or self._closing:
            self.dropped[kind] += 1
        else:
            self._queue.append(item)

    def sensor_tap(self, clock: Callable[[], float]) -> Callable[[str, str, str, bytes, int | None], None]:
        """The ROS receiver's `tap` (runtime.io.ros.receiver): each sample's raw bytes with the
        loop clock's time, queued for the writer (raw_inputs.py); O(1), never blocks."""
        put, cap = self._put, self.max_raw_pending_bytes
        kinds = RAW.KIND_OF_STREAM

        def tap(stream: str, topic: str, type_name: str, data: bytes, seq: int | None) -> None:
            t = clock()
            kind = kinds[stream]
            if not isinstance(data, bytes):
                data = bytes(data)
            if self._raw_queued_bytes - self._raw_written_bytes + len(data) > cap:
                self.dropped[kind] += 1
                return
            self._raw_queued_bytes += len(data)
            put(kind, ("raw", t, stream, topic, type_name, data, seq))

        return tap

    def wrap_bus(self, bus, clock: Callable[[], float]) -> "RecordingBus":
        """A proxy for `bus` that records every frame the driver sends and receives."""
        return RecordingBus(bus, self, clock)

    def attach(self, controller, config, run_info: dict | None = None,
               static_transforms: Sequence[tuple[str, str, np.ndarray]] | None = None) -> Callable[[np.void], None]:
        """Write the run's description and return the hook to call after each tick (with the
        tick's telemetry row, outside its stage timings): FixedRateLoop(after_tick=...).

        controller: its published `snapshot` (runtime.controller.snapshot) is read after each tick
        for the pose, the lidar frame it used, P_fix, the plan and the VLM's answers (a controller
        without one records the tick alone).
        config: the ControllerConfig (its loop section gives the budgets the report compares to,
        its `ros.outputs` the odom and base frame names of /tf).
        static_transforms: the fixed mounts for /tf_static, (parent, child, 4x4 homogeneous matrix)
        each (runtime.io.ros.outbound.robot_sensor_mounts gives base_link -> lidar and -> camera);
        checked here (RecordingError), written once at the first tick. None: no /tf_static.
        """
        try:
            mounts = R.checked_mounts(static_transforms) if static_transforms is not None else None
        except ValueError as exc:
            raise RecordingError(f"--record: the static transforms: {exc}") from None
        outputs = getattr(getattr(config, "ros", None), "outputs", None)
        if outputs is not None:
            self._tf_frames = (str(outputs.odom_frame), str(outputs.base_frame))
        loop = config.loop
        budgets = {s: float(loop.stage_budgets_s.get(s, loop.period_s)) for s in self.stages}
        info = {
            "stages": json.dumps(list(self.stages)),
            "stage_budgets_ms": json.dumps({s: b * 1e3 for s, b in budgets.items()}),
            "period_ms": repr(loop.period_s * 1e3),
            "command_deadline_ms": repr(loop.command_deadline_s * 1e3),
            "planner": str(config.preset),
            "controller_config": json.dumps(config.model_dump(mode="json")),
            "recorded_at_unix_s": repr(time.time()),
            # each tick's now_s is the controller's clock at that tick (a replay takes it as is)
            S.META_TICK_NOW: S.TICK_NOW_OWN,
            **{k: str(v) for k, v in (run_info or {}).items()},
            "recording_id": self.recording_id,
        }
        self._run_meta, self._mounts = info, mounts
        self._queue.append(("meta", S.META_RUN, {**info, "part": "0"}))  # never dropped
        every = self.points_every_ticks
        put = self._put

        def after_tick(row: np.void) -> None:
            self.ticks_seen += 1
            if mounts is not None and self.ticks_seen == 1:  # never dropped, as the run's description
                self._queue.append(("tf_static", float(row["scheduled_s"]), mounts))
            snap = getattr(controller, "snapshot", None)
            xyyaw = frame = scan = why = None
            if snap is not None:
                pose, scan = snap.pose, snap.scan
                xyyaw = (float(pose.x_m), float(pose.y_m), float(pose.yaw_rad))
                why = getattr(snap, "hold_reason", None) or getattr(snap, "stop_reason", None)  # a reference
            if scan is not None:
                offs, stamp = scan.point_time_offsets_s, float(scan.stamp_s)
                frame = (stamp, stamp + (float(offs.max()) if len(offs) else float(scan.frame_duration_s)))
            put("tick", ("tick", row.copy(), xyyaw, frame, _tick_inputs(snap), why))
            stamp = snap.vlm_last_answer_s if snap is not None else None
            if stamp is not None and stamp != self._last_answer_s:
                self._last_answer_s = stamp
                t = float(row["scheduled_s"])  # references only: entries and their masks are immutable
                put("answer", ("answer", t, float(stamp), int(snap.vlm_answers), tuple(snap.vlm_masks)))
            delivered = getattr(snap, "vlm_delivered", ())
            if delivered and snap.vlm_answers != self._last_answers:
                self._last_answers = snap.vlm_answers  # the stage's count moved: this tick took these
                put("backend_answer", ("backend_answer", float(row["scheduled_s"]), int(row["tick"]), float(snap.t_s),
                                       delivered))
            if int(row["tick"]) % every == 0 and snap is not None:
                self._sample_points(snap, row)

        return after_tick

    def _sample_points(self, snap, row: np.void) -> None:
        """P_fix, the partition's P_mov count and a new plan or reference path, from the tick's
        snapshot (runtime.controller.snapshot)."""
        t_s = float(row["scheduled_s"])
        frame = snap.partition_frame
        p_mov = frame.movable_count if frame is not None else None
        returns = int(snap.scan.num_points) if snap.scan is not None else 0
        fix = np.array(snap.points_fix, dtype=np.float32, copy=True)
        self._put("points", ("points", t_s, int(row["tick"]), returns, fix, p_mov))
        plan, path = snap.plan, snap.reference_path
        if plan is not None and plan is not self._last_plan or path is not None and path is not self._last_reference:
            states = np.array(plan.states, copy=True) if plan is not None and plan is not self._last_plan else None
            copied = np.array(path, copy=True) if path is not None and path is not self._last_reference else None
            self._last_plan, self._last_reference = plan, path
            self._put("plan", ("plan", t_s, states, copied))

    # ---------------------------------------------------------------- the writer thread
    def _register(self) -> None:
        w = self._writer
        w.start(profile="", library="dct runtime.io.recording")
        for topic, (name, schema) in S.channel_schemas(self.stages).items():
            sid = w.register_schema(name=name, encoding="jsonschema", data=S.schema_bytes(schema))
            self._channels[topic] = w.register_channel(topic=topic, message_encoding="json", schema_id=sid)
        for topic, (name, text) in R.channel_schemas().items():
            sid = w.register_schema(name=name, encoding=R.SCHEMA_ENCODING, data=text)
            self._channels[topic] = w.register_channel(topic=topic, message_encoding=R.MESSAGE_ENCODING, schema_id=sid)
        self._raw = RAW.RawInputWriter(w)
        self._started = True

    def _emit(self, topic: str, t_s: float, msg: dict) -> None:
        self._add(topic, t_s, json.dumps(msg, separators=(",", ":"), allow_nan=False).encode())

    def _add(self, topic: str, t_s: float, data: bytes) -> None:
        ns = _ns(t_s)
        self._writer.add_message(self._channels[topic], log_time=ns, publish_time=ns, data=data)

    def _write_item(self, item: tuple) -> None:
        kind = item[0]
        if kind == "meta":
            self._writer.add_metadata(item[1], item[2])
            return
        if kind == "tf_static":
            self._add(R.TOPIC_TF_STATIC, item[1], R.tf_static_cdr(item[1], item[2]))
            return
        if kind == "raw":
            try:
                self._raw.write(item)
            finally:
                self._raw_written_bytes += len(item[5])
            self.written[RAW.KIND_OF_STREAM[item[2]]] += 1
            return
        if kind == "tick":
            self._last_t_s = float(item[1]["scheduled_s"])
            if self._part_t0 is None:
                self._part_t0 = self._last_t_s
            elif self.split_every_s is not None and self._last_t_s - self._part_t0 >= self.split_every_s:
                self._next_part()
                self._part_t0 = self._last_t_s
        for topic, t, msg in M.messages_of(item, self.stages):
            self._emit(topic, t, msg)
        if kind == "tick" and item[2] is not None:
            self._add(R.TOPIC_TF, self._last_t_s, R.tf_cdr(self._last_t_s, item[2], self._tf_frames))
        self.written[kind] += 1

    def _next_part(self) -> None:
        """Finish the part being written (writer thread) and begin the next: its description and
        /tf_static again, the raw channels registered again as their samples come."""
        self._finish_part(last=False)
        self.part += 1
        goal_seq = self._raw.goal_seq if self._raw is not None else 0
        self._open(self._opener, self._chunk_size, self._compression)
        self._register()
        self._raw.goal_seq = goal_seq  # goals are numbered across the parts
        if self._run_meta is not None:
            self._writer.add_metadata(S.META_RUN, {**self._run_meta, "part": str(self.part)})
        if self._mounts is not None:
            self._add(R.TOPIC_TF_STATIC, self._last_t_s, R.tf_static_cdr(self._last_t_s, self._mounts))

    def _finish_part(self, last: bool) -> None:
        """The recorder's account and the summary written, the file synced, closed and renamed onto
        its part's name. OSError from renaming is the caller's. Nothing when the next part's file
        could not be opened (the previous one is already in place)."""
        if not self._part_open:
            return
        meta = {k: json.dumps(v) for k, v in self.summary().items() if k != "path"}
        meta["part"] = json.dumps(self.part)
        meta["last_part"] = json.dumps(last)
        try:
            if self.write_error is None:
                self._writer.add_metadata(S.META_RECORDING, meta)
                self._writer.finish()
        except OSError as exc:
            self.write_error = f"{type(exc).__name__}: {exc}"
        finally:
            try:
                self._file.flush()
                os.fsync(self._file.fileno())
            except (OSError, ValueError, io.UnsupportedOperation):
                pass
            try:
                self._file.close()
            except OSError as exc:
                self.write_error = self.write_error or f"{type(exc).__name__}: {exc}"
        target = part_path(self.path, self.part)
        if not self.force and target.exists():  # appeared during the run: keep both
            raise RecordingError(f"--record {target} appeared during the run; the recording is in {self.tmp_path}")
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(self.tmp_path, 0o666 & ~umask)
        os.replace(self.tmp_path, target)
        self._part_open = False
        self.parts.append(str(target))

    def _sample_threads(self) -> None:
        """One /dct/threads message (writer thread only); off for good where there is no /proc."""
        if not self._threads_supported:
            return
        threads = thread_cpu_seconds()
        if threads is None:
            self._threads_supported = False
            return
        t = self._last_t_s
        self._emit(S.TOPIC_THREADS, t, {"timestamp": M.stamp(t), "wall_s": time.monotonic() - self._wall0,
                                        "process_cpu_s": time.process_time(), "queue": len(self._queue),
                                        **_process_figures(), "threads": threads})
        self.thread_samples += 1

    def _writer_main(self) -> None:
        try:
            self._register()
        except OSError as exc:
            self.write_error = f"{type(exc).__name__}: {exc}"
        last_flush = time.monotonic()
        last_threads = -math.inf
        q = self._queue
        while True:
            now = time.monotonic()
            if self.write_error is None and self._started and (
                    now - last_threads >= THREAD_SAMPLE_EVERY_S or (self._closing and not q)):
                last_threads = now
                try:
                    self._sample_threads()
                except OSError as exc:
                    self.write_error = f"{type(exc).__name__}: {exc}"
                except Exception as exc:  # noqa: BLE001 - never die
                    self.bad_records += 1
                    self.bad_record_error = f"threads: {type(exc).__name__}: {exc}"
            if not q:
                if self._closing:
                    return
                time.sleep(0.01)
                continue
            item = q.popleft()
            if self.write_error is not None:
                if item[0] == "raw":
                    self._raw_written_bytes += len(item[5])  # no longer waiting
                if item[0] != "meta":
                    self.dropped_write_error += 1
                continue
            try:
                self._write_item(item)
                time.sleep(0)  # hand the GIL to the loop thread if it waits (else up to the 5 ms switch interval)
                now = time.monotonic()
                if now - last_flush >= self.flush_interval_s:
                    self._writer.flush()  # closes the chunk: a power loss loses at most this much
                    last_flush = now
            except (OSError, RecordingError) as exc:  # full disk, I/O error, a part's name taken: stop writing
                self.write_error = f"{type(exc).__name__}: {exc}"
                if item[0] != "meta":
                    self.dropped_write_error += 1
            except Exception as exc:  # noqa: BLE001 - one record that would not serialise: skip it, never die
                self.bad_records += 1
                self.bad_record_error = f"{item[0]}: {type(exc).__name__}: {exc}"

    # ---------------------------------------------------------------- the end
    def note_run_end(self, error: BaseException | None) -> None:
        if error is not None:
            self._run_ended_with = f"{type(error).__name__}: {error}"

    def summary(self) -> dict:
        return {
            "path": str(self.path),
            "recording_id": self.recording_id,
            "parts": list(self.parts),  # finished and renamed so far
            "ticks_seen": self.ticks_seen,
            "written": dict(self.written),
            "thread_samples": self.thread_samples,
            "dropped_queue_full": dict(self.dropped),
            "dropped_write_error": self.dropped_write_error,
            "dropped_total": sum(self.dropped.values()) + self.dropped_write_error,
            "write_error": self.write_error,
            "bad_records": self.bad_records,
            "bad_record_error": self.bad_record_error,
            "run_error": self._run_ended_with,
        }

    def close(self) -> dict:
        """Drain the queue, write the recorder's account, finish the file and rename it onto the
        output. Returns summary(). Idempotent."""
        if self._closed:
            return self.summary()
        self._closing = True  # records put from now on are dropped and counted
        self._thread.join()
        self._closed = True
        self._finish_part(last=True)
        return self.summary()

    def __enter__(self) -> "RunRecorder":
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        self.note_run_end(exc)
        self.close()


class RecordingBus:
    """Stands between a driver and its python-can bus and records each frame it passes (the
    frame's id and bytes, the loop clock's time and, for a frame sent, the wall-clock time send()
    took: a tuple appended to the recorder's queue)."""

    def __init__(self, bus, recorder: RunRecorder, clock: Callable[[], float]) -> None:
        self._bus = bus
        self._recorder = recorder
        self._clock = clock

    def send(self, msg, timeout: float | None = None) -> None:
        t0 = time.perf_counter()
        self._bus.send(msg, timeout)
        took = time.perf_counter() - t0  # wall clock in send(): the write's span in a trace
        self._recorder._put("can", ("can", self._clock(), "tx", int(msg.arbitration_id), bytes(msg.data), took))

    def recv(self, timeout: float | None = None):
        msg = self._bus.recv(timeout)
        if msg is not None:
            self._recorder._put("can", ("can", self._clock(), "rx", int(msg.arbitration_id), bytes(msg.data), None))
        return msg

    def __getattr__(self, name: str):
        return getattr(self._bus, name)
