"""A scripted JSON-over-HTTP server for the client tests (VLM and grounding detector): one
behaviour per request (the last one repeats), every request recorded, hanging handlers released
at close."""
from __future__ import annotations

import json
import threading
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from typing import Callable

Behaviour = Callable[[BaseHTTPRequestHandler], None]


class ScriptedServer:
    """On 127.0.0.1 (port 0); `base_url` ends in `path_prefix`; `requests` holds each request's
    path, headers and JSON body."""

    def __init__(self, path_prefix: str) -> None:
        self.script: list[Behaviour] = []
        self.requests: list[dict] = []
        self.release = threading.Event()  # set at close: hanging handlers return
        server = self

        class Handler(BaseHTTPRequestHandler):
            def do_POST(self) -> None:  # noqa: N802 - http.server's name
                raw = self.rfile.read(int(self.headers.get("Content-Length", "0")))
                server.requests.append({"path": self.path, "headers": dict(self.headers), "body": json.loads(raw)})
                server.script[min(len(server.requests), len(server.script)) - 1](self)

            def log_message(self, *args) -> None:
                pass

        self.httpd = ThreadingHTTPServer(("127.0.0.1", 0), Handler)
        self.httpd.daemon_threads = True
        self.thread = threading.Thread(target=self.httpd.serve_forever, kwargs={"poll_interval": 0.02}, daemon=True)
        self.thread.start()
        self.base_url = f"http://127.0.0.1:{self.httpd.server_address[1]}{path_prefix}"

    def close(self) -> None:
        self.release.set()
        self.httpd.shutdown()
        self.httpd.server_close()


def send(status: int, payload) -> Behaviour:
    """Answer `status` with `payload` (bytes as they are, anything else as JSON)."""
    data = payload if isinstance(payload, bytes) else json.dumps(payload).encode()

    def act(h: BaseHTTPRequestHandler) -> None:
        h.send_response(status)
        h.send_header("Content-Type", "application/json")
        h.send_header("Content-Length", str(len(data)))
        h.end_headers()
        h.wfile.write(data)

    return act


def drip(server: ScriptedServer, interval_s: float, body: bytes) -> Behaviour:
    """Headers at once, then the body one byte per interval: every read is quick, the whole is slow."""

    def act(h: BaseHTTPRequestHandler) -> None:
        h.send_response(200)
        h.send_header("Content-Length", str(len(body)))
        h.end_headers()
        try:
            for b in body:
                if server.release.wait(interval_s):
                    return
                h.wfile.write(bytes([b]))
                h.wfile.flush()
        except OSError:
            pass

    return act


def hang(server: ScriptedServer) -> Behaviour:
    """Never answer (until the server closes)."""
    return lambda h: server.release.wait(60)


def close_connection(h: BaseHTTPRequestHandler) -> None:
    """Read the request, answer nothing, close (HTTP/1.0 handler closes after do_POST)."""
    h.close_connection = True
