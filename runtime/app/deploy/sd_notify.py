"""systemd's notify protocol in a few lines: READY=1, WATCHDOG=1, STATUS=... over $NOTIFY_SOCKET.

The bundle's unit (templates.py) is `Type=notify` with `WatchdogSec=`: systemd starts counting
the controller as running when it sends READY=1 and restarts it (Restart=on-failure) when no
WATCHDOG=1 arrives within WatchdogSec. The controller process (`dct run`) makes one
`SystemdNotifier()` at start, calls `ready()` once the loop runs and `watchdog()` from the loop
thread (every tick is fine: it is one datagram, and `watchdog()` rate-limits itself to
`min_interval_s`), so a hung loop, not only a dead process, gets the service restarted.

Outside systemd (no $NOTIFY_SOCKET) every call is a no-op, so HIL runs and tests need no switch.
Never raises: a notification that cannot be sent is counted in `errors`.
"""
from __future__ import annotations

import os
import socket
import time


class SystemdNotifier:
    def __init__(self, environ: dict[str, str] | None = None, clock=time.monotonic) -> None:
        env = os.environ if environ is None else environ
        addr = env.get("NOTIFY_SOCKET", "")
        if addr.startswith("@"):  # abstract namespace socket
            addr = "\0" + addr[1:]
        self.address = addr or None
        usec = env.get("WATCHDOG_USEC", "")
        pid = env.get("WATCHDOG_PID", "")
        watchdog_for_us = usec.isdigit() and (not pid or pid == str(os.getpid()))
        #: systemd's WatchdogSec for this process (None: no watchdog asked for).
        self.watchdog_s = int(usec) / 1e6 if watchdog_for_us else None
        #: Ping at most this often (a quarter of WatchdogSec; systemd advises half or less).
        self.min_interval_s = self.watchdog_s / 4 if self.watchdog_s else 0.0
        self._clock = clock
        self._last_ping = -float("inf")
        self._sock: socket.socket | None = None
        self.sent = 0
        self.errors = 0

    @property
    def enabled(self) -> bool:
        return self.address is not None

    def notify(self, state: str) -> bool:
        """Send one notification (e.g. "READY=1"); False outside systemd or on failure."""
        if self.address is None:
            return False
        try:
            if self._sock is None:
                self._sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM | socket.SOCK_CLOEXEC)
            self._sock.sendto(state.encode("utf-8"), self.address)
            self.sent += 1
            return True
        except OSError:
            self.errors += 1
            return False

    def ready(self, status: str | None = None) -> bool:
        return self.notify("READY=1" + (f"\nSTATUS={status}" if status else ""))

    def status(self, text: str) -> bool:
        return self.notify(f"STATUS={text}")

    def watchdog(self) -> bool:
        """WATCHDOG=1, at most every `min_interval_s` (cheap to call every tick)."""
        if self.watchdog_s is None:
            return False
        now = self._clock()
        if now - self._last_ping < self.min_interval_s:
            return False
        self._last_ping = now
        return self.notify("WATCHDOG=1")

    def stopping(self) -> bool:
        return self.notify("STOPPING=1")

    def close(self) -> None:
        if self._sock is not None:
            self._sock.close()
            self._sock = None


__all__ = ["SystemdNotifier"]
