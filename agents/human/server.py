"""The console's web server: the standard library's threaded HTTP server, nothing else.

Routes (every one served from the package, so an installed agos serves the page):

==========================  ===================================================================
``GET /``                   the page (``static/index.html``, with ``console.js`` and ``console.css``)
``GET /api/events``         server-sent events: the board's state as JSON, at once and on every change
                            (at most every ``MIN_EVENT_INTERVAL_S``), a comment line every 10 s between
``GET /api/state``          the same state once (polling, scripts)
``GET /img/<digest>``       an image the state names (immutable: its address is its hash)
``POST /api/act``           a decision: a JSON object; the answer is ``{"ok", "message"}`` with the
                            board's HTTP status (200, 400, 409, 422; 403 on a spectator)
==========================  ===================================================================

A POST must say ``Content-Type: application/json``: a browser sends that cross-origin only after a
preflight this server never answers, so another site open in the same browser cannot decide for
the person. The server binds to loopback unless told another interface.
"""

from __future__ import annotations

import json
import logging
import threading
from http import HTTPStatus
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from importlib import resources
from typing import Any

from agos.agents.human.board import PageBoard

log = logging.getLogger("agos.human.server")
STATIC = {"index.html": "text/html; charset=utf-8", "console.js": "text/javascript; charset=utf-8",
          "console.css": "text/css; charset=utf-8"}
MAX_BODY_BYTES = 16_384
KEEPALIVE_S = 10.0
MIN_EVENT_INTERVAL_S = 0.1
"""Fastest rate of state events per page (a spectator's stream changes many times a second)."""


def static_file(name: str) -> bytes:
    """A file of the page, from the installed package."""
    return (resources.files("agos.agents.human") / "static" / name).read_bytes()


class _Handler(BaseHTTPRequestHandler):
    source: PageBoard
    closing: threading.Event
    server_version = "agos-human"

    def log_message(self, format: str, *args: Any) -> None:
        log.debug("%s " + format, self.address_string(), *args)

    def _send(self, status: int, body: bytes, content_type: str, cache: str = "no-store") -> None:
        self.send_response(status)
        self.send_header("Content-Type", content_type)
        self.send_header("Content-Length", str(len(body)))
        self.send_header("Cache-Control", cache)
        self.send_header("X-Content-Type-Options", "nosniff")
        self.end_headers()
        self.wfile.write(body)

    def _json(self, status: int, data: Any) -> None:
        self._send(status, json.dumps(data).encode(), "application/json")

    def do_GET(self) -> None:
        path = self.path.split("?", 1)[0]
        if path in ("/", "/index.html", "/spectate"):
            self._send(200, static_file("index.html"), STATIC["index.html"])
        elif path.startswith("/static/") and path.removeprefix("/static/") in STATIC:
            name = path.removeprefix("/static/")
            self._send(200, static_file(name), STATIC[name])
        elif path == "/favicon.ico":
            self.send_response(HTTPStatus.NO_CONTENT)
            self.end_headers()
        elif path == "/api/state":
            self._send(200, self.source.snapshot_json().encode(), "application/json")
        elif path == "/api/events":
            self._events()
        elif path.startswith("/img/"):
            found = self.source.image(path.removeprefix("/img/"))
            if found is None:
                self._json(404, {"ok": False, "message": "no such image (it belongs to an older decision)"})
            else:
                self._send(200, found[0], found[1], cache="public, max-age=86400, immutable")
        else:
            self._json(404, {"ok": False, "message": f"no page at {path}"})

    def do_POST(self) -> None:
        if self.path.split("?", 1)[0] != "/api/act":
            self._json(404, {"ok": False, "message": f"nothing to post at {self.path}"})
            return
        if self.headers.get("Content-Type", "").split(";")[0].strip() != "application/json":
            self._json(415, {"ok": False, "message": "send the decision as application/json"})
            return
        try:
            length = int(self.headers.get("Content-Length", "0"))
        except ValueError:
            length = -1
        if not 0 < length <= MAX_BODY_BYTES:
            self._json(400, {"ok": False, "message": f"a decision is a JSON object of at most {MAX_BODY_BYTES} bytes"})
            return
        try:
            body = json.loads(self.rfile.read(length))
        except (json.JSONDecodeError, UnicodeDecodeError):
            self._json(400, {"ok": False, "message": "Malformed request: not JSON."})
            return
        verdict = self.source.submit(body)
        self._json(verdict.status, {"ok": verdict.ok, "message": verdict.message})

    def _events(self) -> None:
        self.send_response(HTTPStatus.OK)
        self.send_header("Content-Type", "text/event-stream")
        self.send_header("Cache-Control", "no-store")
        self.end_headers()
        version = None
        try:
            while not self.closing.is_set():
                now = self.source.version if version is None else self.source.wait_change(version, KEEPALIVE_S)
                if now != version:
                    version = now
                    self.wfile.write(b"data: " + self.source.snapshot_json().encode() + b"\n\n")
                    self.wfile.flush()
                    self.closing.wait(MIN_EVENT_INTERVAL_S)
                else:
                    self.wfile.write(b": keep-alive\n\n")
                    self.wfile.flush()
        except (BrokenPipeError, ConnectionResetError, TimeoutError):
            return  # the page went away


class ConsoleServer:
    """Serves ``source`` on ``host:port`` from a background thread (one more thread per request)."""

    def __init__(self, source: PageBoard, host: str = "127.0.0.1", port: int = 8765) -> None:
        self.closing = threading.Event()
        handler = type("ConsoleHandler", (_Handler,), {"source": source, "closing": self.closing})
        self.httpd = ThreadingHTTPServer((host, port), handler)
        self.httpd.daemon_threads = True
        self._thread = threading.Thread(target=self.httpd.serve_forever, name="console-http", daemon=True)

    @property
    def port(self) -> int:
        return int(self.httpd.server_address[1])

    def url(self, host: str) -> str:
        shown = "127.0.0.1" if host in ("", "0.0.0.0", "::") else host
        return f"http://{shown}:{self.port}/"

    def start(self) -> ConsoleServer:
        self._thread.start()
        return self

    def close(self) -> None:
        self.closing.set()
        self.httpd.shutdown()
        self.httpd.server_close()
