"""HTTP transport shared by the VLM client and the grounding-detector client: one POST per
attempt with a hard deadline (a daemon thread the caller waits on; at the deadline the socket is
shut down), the retry classification (TransientError: timeout, connection trouble, 429, 5xx;
PermanentError: other 4xx, an oversized body), and the settings both clients share.

Why not a library: the venv has neither httpx nor requests, and a socket timeout bounds each
read, not the whole answer (a server that trickles its body would hold a caller far longer).
"""
from __future__ import annotations

import http.client
import json
import socket
import threading
import urllib.parse

from pydantic import BaseModel, ConfigDict, Field, field_validator


class HttpServiceConfig(BaseModel):
    """Where a service is and how long to wait for it; subclasses set their own defaults."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    base_url: str
    timeout_s: float = Field(default=10.0, gt=0.0, le=600.0, description="bound on one attempt, end to end")
    max_retries: int = Field(default=1, ge=0, le=10)
    backoff_s: float = Field(default=0.25, ge=0.0, le=60.0, description="sleep before retry k is backoff_s * 2**k")

    @field_validator("base_url")
    @classmethod
    def _http_url(cls, v: str) -> str:
        u = urllib.parse.urlsplit(v)
        if u.scheme not in ("http", "https") or not u.hostname or u.query or u.fragment:
            raise ValueError(f"base_url must be http(s)://host[:port][/path] without query, got {v!r}")
        return v.rstrip("/")

    def worst_case_s(self) -> float:
        """The longest a call may take (all attempts time out), before scheduling noise."""
        return (self.max_retries + 1) * self.timeout_s + self.backoff_s * (2**self.max_retries - 1)


def error_message(status: int, body: bytes) -> str:
    """'HTTP 401: <the server's error message>'."""
    detail = body[:200].decode("utf-8", "replace")
    try:
        data = json.loads(body)
        if isinstance(data, dict) and isinstance(data.get("error"), dict) and "message" in data["error"]:
            detail = str(data["error"]["message"])[:200]
    except (ValueError, RecursionError):
        pass
    return f"HTTP {status}: {detail}"


# ------------------------------------------------------------------------------------ transport


class TransientError(Exception):
    """Worth retrying: timeout, connection trouble, 429, 5xx."""


class PermanentError(Exception):
    """Not worth retrying: other 4xx, an oversized body."""


class Attempt:
    """One POST in a daemon thread; `run` waits at most timeout_s and then kills the socket."""

    def __init__(self, url: urllib.parse.SplitResult, path: str, body: bytes, headers: dict[str, str],
                 timeout_s: float, max_bytes: int):
        self._url, self._path, self._body, self._headers = url, path, body, headers
        self._timeout_s, self._max_bytes = timeout_s, max_bytes
        self._conn: http.client.HTTPConnection | None = None
        self._result: tuple[int, bytes] | None = None
        self._exc: BaseException | None = None
        self._lock = threading.Lock()
        self._abandoned = False

    def _work(self) -> None:
        try:
            cls = http.client.HTTPSConnection if self._url.scheme == "https" else http.client.HTTPConnection
            conn = cls(self._url.hostname, self._url.port, timeout=self._timeout_s)
            with self._lock:
                if self._abandoned:
                    return
                self._conn = conn
            conn.connect()  # bounded by timeout_s (DNS excepted: see the module docstring)
            with self._lock:
                if self._abandoned:  # the caller gave up while we connected
                    return
            conn.request("POST", self._path, body=self._body, headers=self._headers)
            resp = conn.getresponse()
            chunks, total = [], 0
            while True:
                chunk = resp.read(65536)
                if not chunk:
                    break
                chunks.append(chunk)
                total += len(chunk)
                if total > self._max_bytes:
                    raise PermanentError(f"response larger than {self._max_bytes} bytes")
            self._result = (resp.status, b"".join(chunks))
        except BaseException as e:  # noqa: BLE001 - handed to the caller's thread
            self._exc = e
        finally:
            with self._lock:
                conn, self._conn = self._conn, None
            if conn is not None:
                conn.close()

    def run(self) -> tuple[int, bytes]:
        t = threading.Thread(target=self._work, name="vlm-http", daemon=True)
        t.start()
        t.join(self._timeout_s)
        if t.is_alive():
            with self._lock:
                self._abandoned = True
                conn = self._conn
            sock = getattr(conn, "sock", None) if conn is not None else None
            if sock is not None:
                try:
                    sock.shutdown(socket.SHUT_RDWR)  # wakes the blocked recv/send in _work
                except OSError:
                    pass
            raise TransientError(f"no complete answer within {self._timeout_s:g} s")
        if self._exc is not None:
            e = self._exc
            if isinstance(e, PermanentError):
                raise e
            if isinstance(e, (TimeoutError, socket.timeout)):
                raise TransientError(f"no complete answer within {self._timeout_s:g} s")
            if isinstance(e, (OSError, http.client.HTTPException)):
                raise TransientError(f"connection failed ({type(e).__name__}: {str(e)[:80]})")
            raise PermanentError(f"{type(e).__name__}: {str(e)[:80]}")
        assert self._result is not None
        return self._result


__all__ = ["Attempt", "HttpServiceConfig", "PermanentError", "TransientError", "error_message"]
