"""A warm restart of `dct run`: the odometry frame and the goal carried over a crash.

The controller has no map: its goals and its pose are in the odometry frame, which starts at the
robot's pose when the process starts. A controller killed mid-drive and started again by its
systemd unit (Restart=on-failure) would otherwise begin a new frame where the robot stopped, and
every goal given in the old one would point somewhere else.

With `--resume-file PATH` the running controller writes, twice a second of wall time, the pose it
is at (odom frame), the base's cumulative wheel distances at that pose (0x311, as received) and
its goal, to PATH (a temporary file beside it, then a rename: a crash leaves the old one or the
new one, never half of one). A thread writes it; the tick's side only hands over a tuple
(`offer`), so the loop never waits on the disk.

At start, a file younger than `--resume-max-age` (60 s by default) is taken up: at the first
wheel reading the odometry starts at the saved pose moved by what the wheels did since (the
base's odometers run on while the controller is down; the heading from the wheels over that
interval, since no gyro was read), so the frame continues (runtime.odometry.stage.resume_from).
Odometers that moved further than the base could have driven in the time since (it rebooted and
counts from zero again), a file that is too old, unreadable or not of this format: a new frame,
and the line at start says why. Without `--goal`, an unreached saved goal is driven on to.
"""
from __future__ import annotations

import json
import math
import os
import tempfile
import threading
import time
from dataclasses import dataclass
from pathlib import Path

from pydantic import BaseModel, ConfigDict, Field, ValidationError

#: Seconds of wall time between two writes.
WRITE_EVERY_S = 0.5
#: A saved state older than this (wall clock) starts a new frame: long enough for systemd's
#: RestartSec, `dct preflight` and the controller's start-up, short enough that the robot has not
#: been carried somewhere else meanwhile.
DEFAULT_MAX_AGE_S = 60.0
FORMAT = "dct-resume-1"


class ResumeState(BaseModel):
    """What a controller saves to be taken up by the next one (module docstring)."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)

    format: str = Field(pattern=f"^{FORMAT}$")
    written_at_s: float  # wall clock (time.time()), seconds since the epoch
    pose: tuple[float, float, float]  # x_m, y_m, yaw_rad in the odom frame
    wheels_m: tuple[float, float]  # the base's cumulative left/right distances at that pose (0x311)
    goal: tuple[float, float, float] | None  # odom frame; None: none yet
    goal_reached: bool
    pid: int


@dataclass(frozen=True)
class Resume:
    """A saved state taken up at start, or why none was (state None)."""

    state: ResumeState | None
    why: str

    def line(self) -> str:
        if self.state is None:
            return f"resume: a new odometry frame ({self.why})"
        s = self.state
        return (f"resume: continuing the odometry frame of pid {s.pid} ({self.why}): saved pose "
                f"{s.pose[0]:.3f} {s.pose[1]:.3f} {s.pose[2]:.3f}" +
                (f", goal {s.goal[0]:.3f} {s.goal[1]:.3f} {s.goal[2]:.3f}"
                 f"{' (reached)' if s.goal_reached else ''}" if s.goal is not None else ", no goal"))


def load_resume(path: Path, max_age_s: float = DEFAULT_MAX_AGE_S, now_s: float | None = None) -> Resume:
    """The state saved at `path` if it is there, readable and young enough; else why not."""
    now_s = time.time() if now_s is None else now_s
    try:
        raw = Path(path).read_text(encoding="utf-8")
    except FileNotFoundError:
        return Resume(None, f"no saved state at {path}")
    except OSError as exc:
        return Resume(None, f"{path}: cannot be read ({exc.strerror or exc})")
    except UnicodeDecodeError:
        return Resume(None, f"{path}: not a saved state of this controller (not UTF-8 text)")
    try:
        state = ResumeState.model_validate(json.loads(raw))
    except (ValueError, ValidationError) as exc:
        first = str(exc).splitlines()
        return Resume(None, f"{path}: not a saved state of this controller ({first[1] if len(first) > 1 else first[0]})")
    age = now_s - state.written_at_s
    if age < -1.0:
        return Resume(None, f"{path}: written {-age:.1f} s in the future (the clock was stepped?)")
    if age > max_age_s:
        return Resume(None, f"{path}: written {age:.0f} s ago, more than --resume-max-age {max_age_s:g} s")
    return Resume(state, f"saved {max(age, 0.0):.1f} s ago")


class ResumeWriter(threading.Thread):
    """Writes the newest offered state to `path` every WRITE_EVERY_S (module docstring)."""

    def __init__(self, path: Path, every_s: float = WRITE_EVERY_S) -> None:
        super().__init__(name="dct-resume-writer", daemon=True)
        self.path = Path(path)
        self.every_s = every_s
        self._latest: tuple | None = None
        self._written: tuple | None = None
        self._done = threading.Event()
        self.writes = 0
        self.error: str | None = None

    def offer(self, pose, wheels_m, goal, goal_reached: bool) -> None:
        """From the loop's after_tick: O(1), no I/O (the reference is replaced, never shared)."""
        if wheels_m is None or not all(map(math.isfinite, (*pose, *wheels_m))):
            return  # no wheel reading yet: nothing a next controller could continue from
        self._latest = (tuple(pose), tuple(wheels_m), None if goal is None else tuple(goal), bool(goal_reached))

    def run(self) -> None:
        while not self._done.wait(self.every_s):
            self._write()
        self._write()

    def close(self) -> None:
        self._done.set()
        self.join(timeout=2.0)

    def _write(self) -> None:
        latest = self._latest
        if latest is None or latest is self._written:
            return
        pose, wheels, goal, reached = latest
        text = json.dumps({"format": FORMAT, "written_at_s": time.time(), "pose": pose, "wheels_m": wheels,
                           "goal": goal, "goal_reached": reached, "pid": os.getpid()})
        try:
            fd, tmp = tempfile.mkstemp(prefix=f".{self.path.name}.", dir=self.path.parent)
            try:
                with os.fdopen(fd, "w", encoding="utf-8") as f:
                    f.write(text)
                    f.flush()
                    os.fsync(f.fileno())
                os.replace(tmp, self.path)
            except BaseException:
                Path(tmp).unlink(missing_ok=True)
                raise
        except OSError as exc:  # a full disk: said in the summary; the controller drives on
            self.error = f"{self.path}: {exc.strerror or exc}"
            return
        self._written = latest
        self.writes += 1
