"""Child processes that run one of our modules beside the caller, and the idle ones kept for reuse.

`spawn_module` starts `python -m MODULE FD`: a fresh interpreter joined to us by a socket pair
(a multiprocessing Connection on our side). No fork of a process that holds threads (CAN buses,
renderers), and, unlike multiprocessing's spawn, no re-import of the caller's main script. The
KISS-ICP worker (runtime.odometry.worker) and the simulated lidar's cast process
(hil_sim.sensors.lidar_cast) run this way.

`IdleChildren` keeps children a closed user left for the next one in this process (a lockstep
campaign's next episode): an interpreter takes 0.3-1 s to import and warm up.
"""
from __future__ import annotations

import socket
import subprocess
import sys
import threading


def spawn_module(module: str):
    """(process, our Connection) of a fresh `python -m module FD`; the child reads its end of
    the socket pair from file descriptor FD (sys.argv[1])."""
    from multiprocessing.connection import Connection

    ours, theirs = socket.socketpair()
    proc = subprocess.Popen([sys.executable, "-m", module, str(theirs.fileno())],
                            pass_fds=(theirs.fileno(),), stdin=subprocess.DEVNULL, close_fds=True)
    theirs.close()
    return proc, Connection(ours.detach())


class IdleChildren:
    """At most `keep` idle (process, connection) pairs, shared by the threads of this process."""

    def __init__(self, keep: int) -> None:
        self.keep = keep
        self._idle: list[tuple[subprocess.Popen, object]] = []
        self._lock = threading.Lock()

    def take(self):
        """An idle child still running (the ended ones are dropped), or None."""
        with self._lock:
            while self._idle:
                proc, conn = self._idle.pop()
                if proc.poll() is None:
                    return proc, conn
                conn.close()
        return None

    def offer(self, proc: subprocess.Popen, conn) -> bool:
        """Keep the child for the next user; False when `keep` are idle already (the caller ends it)."""
        with self._lock:
            if len(self._idle) < self.keep:
                self._idle.append((proc, conn))
                return True
        return False

    def __len__(self) -> int:
        return len(self._idle)

    def __getitem__(self, i: int):
        return self._idle[i]


__all__ = ["IdleChildren", "spawn_module"]
