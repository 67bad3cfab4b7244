"""The simulated lidar's ray casting, in the simulator's process or in a child process of its own.

SimLidar (hil_sim.sensors.lidar) decides when each slice of a frame is due and from which pose;
a caster casts it and keeps the frame's returns:
- `RayCaster` casts in the process that calls it: the slice's directions (the frame's rows of the
  pattern table) turned to the world, `mj_multiRay`, the range noise and the returns;
- `CastProcess` does the same with a RayCaster in a child process (`python -m
  hil_sim.sensors.lidar_cast FD`, joined by a socket pair, as the ICP worker is). The simulator
  copies what mj_multiRay reads of the state at the slice's instant (the geoms' poses, the
  bodies' inertial frames, the flex vertices) into a shared memory file and sends one small
  message; the child casts it while the simulator steps on. When the frame ends, the simulator
  waits for the child's last slice and copies the returns out. The 20k rays of a frame cost the
  simulator's thread 6 ms inline (mj_multiRay, which a thread could not move: the GIL it takes
  back after each cast cost the simulator as much), and about 0.5 ms this way.

The child runs the same RayCaster from the same model (pickled: bit for bit), seed and state, so
the frames are the same bit for bit (tested). A child left idle by a closed lidar is kept for
the next one in this process (a campaign's next episode): its interpreter takes 0.5-1 s to start.
"""
from __future__ import annotations

import contextlib
import math
import mmap
import os
import pickle
import struct
import subprocess
import tempfile

import mujoco
import numpy as np

from runtime.common.child_process import IdleChildren, spawn_module

_CAST = struct.Struct("<ciiiid")   # b"C", frame, i0, i1, slot, offset_s
_COUNT = struct.Struct("<i")


class RayCaster:
    """The rays of the frames and their returns (module docstring): the lidar's pattern table,
    its noise generator and the frame's buffers."""

    def __init__(self, model: mujoco.MjModel, config, body: int, seed: int) -> None:
        from hil_sim.sensors.lidar import pattern_directions

        self.config = c = config
        n = c.points_per_frame
        self._m = model
        self._body = body if body > 0 else -1
        self._geomgroup = None if c.geomgroup is None else np.asarray(c.geomgroup, dtype=np.uint8)
        self._rng = np.random.default_rng(seed)
        self._table = pattern_directions(n * c.pattern_frames, c.elevation_min_deg, c.elevation_max_deg)
        # Buffers sized for a whole frame: several due slices of one frame are cast in one call.
        self._dir_l = np.empty((n, 3))      # directions in the lidar frame (this pass's rotation)
        self._dir_w = np.empty((n, 3))      # the same in the world frame
        self._geomid = np.empty(n, dtype=np.int32)
        self._dist = np.empty(n)
        self._noise = np.zeros(n)
        self._dirs_buf = np.empty((n, 3))  # this frame's directions when the pass turns the table
        self._dirs: np.ndarray = self._dirs_buf
        self._dirs_frame = -1             # the frame _dirs belongs to
        self._no_gids = np.empty(0, dtype=np.int32)
        self.pts = np.empty((n, 3), dtype=np.float32)
        self.offs = np.empty(n, dtype=np.float32)
        self.gids = np.empty(n, dtype=np.int32) if c.ground_truth_frames else None
        self.count = 0

    def warm_up(self) -> None:
        """Load the compiled collection kernel (from numba's cache) now, not in the first frame."""
        from hil_sim.sensors.lidar import collect_returns

        gids = self.gids if self.gids is not None else self._no_gids
        collect_returns(self._dir_l[:0], self._geomid[:0], self._dist[:0], self._noise[:0], 0.0, 0.0, 1.0, 0.0,
                        self.pts, self.offs, gids, False, 0)

    def cast(self, data: mujoco.MjData, frame: int, i0: int, i1: int, offset_s: float, r_wl: np.ndarray,
             origin: np.ndarray) -> None:
        """Cast rays [i0, i1) of `frame` in `data` from the lidar pose (r_wl, origin) and append
        their returns, stamped offset_s."""
        from hil_sim.sensors.lidar import collect_returns

        c = self.config
        n = i1 - i0
        dl = self._dir_l[:n]
        dl[...] = self._frame_directions(frame)[i0:i1]  # a fresh buffer: matmul's input laid out as always
        dw = self._dir_w[:n]
        np.matmul(dl, r_wl.T, out=dw)
        geomid, dist = self._geomid[:n], self._dist[:n]
        mujoco.mj_multiRay(self._m, data, np.ascontiguousarray(origin), dw.reshape(-1), self._geomgroup, 1,
                           self._body, geomid, dist, None, n, c.max_range_m)
        sigma = c.range_noise_sigma_m
        noise = self._noise[:n]
        if sigma > 0:
            self._rng.standard_normal(out=noise)
        gids = self.gids if self.gids is not None else self._no_gids
        self.count = collect_returns(dl, geomid, dist, noise, sigma, c.min_range_m, c.max_range_m, offset_s,
                                     self.pts, self.offs, gids, self.gids is not None, self.count)

    def take(self) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
        """The frame's returns (points, time offsets, geom ids or None), copied; the next frame
        starts empty."""
        k, self.count = self.count, 0
        return self.pts[:k].copy(), self.offs[:k].copy(), None if self.gids is None else self.gids[:k].copy()

    def wait_ready(self) -> None:
        """Ready at once (the kernels load at the first frame)."""

    def close(self) -> None:
        """Nothing to release in this process."""

    def _frame_directions(self, frame: int) -> np.ndarray:
        """The frame's ray directions in the lidar frame (n, 3): its rows of the pattern table,
        turned about z by the golden angle once per pass over the table (computed once a frame)."""
        if self._dirs_frame != frame:
            from hil_sim.sensors.lidar import GOLDEN_ANGLE_RAD

            c = self.config
            pass_index, frame_in_table = divmod(frame, c.pattern_frames)
            base = frame_in_table * c.points_per_frame
            tab = self._table[base: base + c.points_per_frame]
            if pass_index:
                a = pass_index * GOLDEN_ANGLE_RAD
                ca, sa = math.cos(a), math.sin(a)
                d = self._dirs_buf
                d[:, 0] = ca * tab[:, 0] - sa * tab[:, 1]
                d[:, 1] = sa * tab[:, 0] + ca * tab[:, 1]
                d[:, 2] = tab[:, 2]
                self._dirs = d
            else:
                self._dirs = tab
            self._dirs_frame = frame
        return self._dirs


class _Layout:
    """The shared memory file: one state slot per slice of a frame (the geoms' poses, the
    bodies' inertial frames, the flex vertices, the lidar's rotation and origin), then the
    frame's returns (points, offsets, geom ids)."""

    def __init__(self, model: mujoco.MjModel, config) -> None:
        self.fields = (("geom_xpos", model.ngeom * 3), ("geom_xmat", model.ngeom * 9), ("xipos", model.nbody * 3),
                       ("flexvert_xpos", model.nflexvert * 3), ("r_wl", 9), ("origin", 3))
        self.slot = sum(size for _, size in self.fields)
        self.slots = config.slices_per_frame
        self.n = n = config.points_per_frame
        self.size = 8 * self.slot * self.slots + 12 * n + 4 * n + 4 * n

    def views(self, buf) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """(slots (S, slot) float64, points (n, 3) float32, offsets (n,) float32, geom ids (n,) int32)."""
        n = self.n
        slots = np.ndarray((self.slots, self.slot), np.float64, buf)
        at = slots.nbytes
        pts = np.ndarray((n, 3), np.float32, buf, at)
        offs = np.ndarray(n, np.float32, buf, at + 12 * n)
        gids = np.ndarray(n, np.int32, buf, at + 16 * n)
        return slots, pts, offs, gids

    def put(self, slot: np.ndarray, data: mujoco.MjData, r_wl: np.ndarray, origin: np.ndarray) -> None:
        """Write the state the cast reads, and the lidar pose, into a slot (the simulator's side)."""
        at = 0
        for name, size in self.fields[:4]:
            if size:
                slot[at:at + size] = getattr(data, name).ravel()
            at += size
        slot[at:at + 9] = r_wl.ravel()
        slot[at + 9:at + 12] = origin

    def get(self, slot: np.ndarray, data: mujoco.MjData) -> tuple[np.ndarray, np.ndarray]:
        """Put a slot's state into data; the lidar pose (r_wl, origin) (the child's side)."""
        at = 0
        for name, size in self.fields[:4]:
            if size:
                getattr(data, name).ravel()[...] = slot[at:at + size]
            at += size
        return slot[at:at + 9].reshape(3, 3), slot[at + 9:at + 12]


class CastProcess:
    """A RayCaster in a child process (module docstring); RayCaster's interface."""

    def __init__(self, model: mujoco.MjModel, config, body: int, seed: int, start_timeout_s: float = 60.0) -> None:
        self.config = config
        self._layout = layout = _Layout(model, config)
        self._start_timeout_s = start_timeout_s
        fd, self._path = _shared_file()
        try:
            os.ftruncate(fd, layout.size)
            self._mem = mmap.mmap(fd, layout.size)
        finally:
            os.close(fd)
        self._slots, self._pts, self._offs, self._gids = layout.views(self._mem)
        self._slot = 0
        self._ready = False
        self._closed = False
        try:
            init = b"I" + pickle.dumps((model, config, body, seed, self._path))
            idle = _IDLE.take()
            if idle is not None:
                try:
                    idle[1].send_bytes(init)
                except OSError:  # it ended while idle: a fresh one
                    _end(*idle)
                    idle = None
            self._proc, self._conn = idle or _spawn()
            if idle is None:
                self._conn.send_bytes(init)
        except BaseException:
            self._mem.close()
            self._unlink()
            raise

    def cast(self, data: mujoco.MjData, frame: int, i0: int, i1: int, offset_s: float, r_wl: np.ndarray,
             origin: np.ndarray) -> None:
        """Copy the state the cast reads into this slice's slot and send the slice."""
        self._layout.put(self._slots[self._slot], data, r_wl, origin)
        self._send(_CAST.pack(b"C", frame, i0, i1, self._slot, offset_s))
        self._slot += 1

    def take(self) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
        """Wait for the child's last slice of the frame; its returns, copied out."""
        self._send(b"T")
        answer = self._recv()
        if answer[:1] != b"K":
            raise RuntimeError(f"SimLidar's cast process failed: {answer[1:].decode(errors='replace')}")
        (k,) = _COUNT.unpack_from(answer, 1)
        self._slot = 0
        gids = self._gids[:k].copy() if self.config.ground_truth_frames else None
        return self._pts[:k].copy(), self._offs[:k].copy(), gids

    def close(self) -> None:
        """Leave the child idle for the next lidar of this process, or end it (one that never
        said ready, failed or does not answer is killed); remove the shared memory file. Once."""
        if self._closed:
            return
        self._closed = True
        proc, conn = self._proc, self._conn
        try:
            if not self._ready:
                raise OSError("not started")
            conn.send_bytes(b"N")
            if not conn.poll(5.0) or conn.recv_bytes() != b"n":
                raise OSError("no idle answer")
            if not _IDLE.offer(proc, conn):
                conn.close()
                proc.wait(timeout=5.0)
        except (OSError, EOFError, subprocess.TimeoutExpired):
            _end(proc, conn)
        finally:
            self._slots = self._pts = self._offs = self._gids = None
            self._mem.close()
            self._unlink()

    def _unlink(self) -> None:
        if self._path is not None:
            path, self._path = self._path, None
            with contextlib.suppress(FileNotFoundError):  # removed by someone else: gone either way
                os.unlink(path)

    def wait_ready(self) -> None:
        """Until the child has built its caster and loaded its kernels (its interpreter starts in
        0.5-1 s, beside whatever the simulator builds meanwhile); raises when it failed."""
        self._recv(ready_only=True)

    def _send(self, message: bytes) -> None:
        try:
            self._conn.send_bytes(message)
        except OSError as exc:
            raise RuntimeError(f"SimLidar's cast process is gone ({exc})") from exc

    def _recv(self, ready_only: bool = False) -> bytes:
        try:
            if not self._ready:
                if not self._conn.poll(self._start_timeout_s):
                    raise RuntimeError(f"SimLidar's cast process did not start within {self._start_timeout_s:.0f} s")
                ready = self._conn.recv_bytes()
                if ready != b"R":
                    raise RuntimeError(f"SimLidar's cast process failed to start: {ready[1:].decode(errors='replace')}")
                self._ready = True
                self._unlink()  # both ends have it mapped: nothing is left behind if either dies
            return b"" if ready_only else self._conn.recv_bytes()
        except (EOFError, OSError) as exc:
            raise RuntimeError(f"SimLidar's cast process is gone ({type(exc).__name__})") from exc


def _end(proc: subprocess.Popen, conn) -> None:
    """Kill a child and reap it (no zombie left), and close our end of its socket."""
    proc.kill()
    try:
        proc.wait(timeout=5.0)
    except subprocess.TimeoutExpired:
        pass
    conn.close()


def _shared_file() -> tuple[int, str]:
    """A new file for the shared memory: in /dev/shm (memory only) when it is there and writable,
    else in the temporary directory (the page cache keeps it in memory as long as it is mapped)."""
    try:
        return tempfile.mkstemp(prefix="dct-lidar-", dir="/dev/shm")
    except OSError:
        return tempfile.mkstemp(prefix="dct-lidar-")


#: Idle cast processes for the next lidar of this process (a campaign's next episode).
MAX_IDLE = 1
_IDLE = IdleChildren(MAX_IDLE)


def _spawn():
    """A fresh cast process and our end of its socket pair."""
    return spawn_module("hil_sim.sensors.lidar_cast")


def _serve(conn) -> None:
    """The child: one lidar at a time (I: its model, config, seed and memory file; C: a slice;
    T: the frame's returns; N: idle until the next lidar), until the socket closes."""
    while True:
        try:
            message = conn.recv_bytes()
        except (EOFError, OSError):
            return
        if message[:1] != b"I":
            continue
        error = None
        try:
            model, config, body, seed, path = pickle.loads(message[1:])
            caster, data, layout = RayCaster(model, config, body, seed), mujoco.MjData(model), _Layout(model, config)
            caster.warm_up()
            with open(path, "r+b") as f:
                mem = mmap.mmap(f.fileno(), layout.size)
            slots, pts, offs, gids = layout.views(mem)
            conn.send_bytes(b"R")
        except Exception as exc:  # noqa: BLE001 - named to the simulator
            conn.send_bytes(b"E" + f"{type(exc).__name__}: {exc}".encode())
            continue
        while True:
            try:
                message = conn.recv_bytes()
            except (EOFError, OSError):
                return
            kind = message[:1]
            if kind == b"C":
                _, frame, i0, i1, slot, offset_s = _CAST.unpack(message)
                if error is None:
                    try:
                        caster.cast(data, frame, i0, i1, offset_s, *layout.get(slots[slot], data))
                    except Exception as exc:  # noqa: BLE001 - answered at the frame's end
                        error = f"{type(exc).__name__}: {exc}"
            elif kind == b"T":
                if error is not None:
                    conn.send_bytes(b"E" + error.encode())
                    continue
                k, caster.count = caster.count, 0
                pts[:k] = caster.pts[:k]
                offs[:k] = caster.offs[:k]
                if caster.gids is not None:
                    gids[:k] = caster.gids[:k]
                conn.send_bytes(b"K" + _COUNT.pack(k))
            elif kind == b"N":
                slots = pts = offs = gids = None
                mem.close()
                conn.send_bytes(b"n")
                break


__all__ = ["CastProcess", "RayCaster"]


if __name__ == "__main__":  # the cast process (started by CastProcess)
    import signal
    import sys
    from multiprocessing.connection import Connection as _Connection

    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the simulator ends it (closing the socket)
    _serve(_Connection(int(sys.argv[1])))
