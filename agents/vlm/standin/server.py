"""The stand-in's HTTP server: a ``ThreadingHTTPServer`` that serves ``/v1/models``,
``/v1/chat/completions`` and ``/stats``, draws each request's outcome and latency, and asks the
responder for the decision (see :mod:`agos.agents.vlm.standin` for the endpoints and outcomes).
"""

from __future__ import annotations

import contextlib
import hmac
import json
import random
import socket
import sys
import threading
import time
from collections import Counter, deque
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from typing import TYPE_CHECKING, Any

from agos.agents.vlm.standin.faults import OK, OUTCOMES, FaultSpecError, check_faults, draw_outcome, fault_rng
from agos.agents.vlm.standin.replies import cap_tokens, completion_body, render_content
from agos.agents.vlm.standin.requests import ChatRequest, RequestError, error_body, parse_chat_body, split_messages
from agos.agents.vlm.standin.schema import violation

if TYPE_CHECKING:
    from agos.agents.vlm.protocol import SplitRequest

Responder = Callable[["SplitRequest"], dict[str, Any]]

DEFAULT_MODELS = ("agos-standin",)
MAX_BODY_BYTES = 64 * 1024 * 1024
RECORDED = 64
"""How many recent chat-completion requests :attr:`StandinServer.recorded` keeps."""


def wait_responder(request: SplitRequest) -> dict[str, Any]:
    """The fallback responder when ``standin.brain`` is not there: always WAIT (legal for both roles)."""
    return {"action": "WAIT", "reason": f"stand-in without a brain; saw {len(request.images)} labelled image(s)"}


def default_responder() -> Responder:
    """``agos.agents.vlm.standin.brain.respond``, or :func:`wait_responder` while that module does not exist."""
    try:
        from agos.agents.vlm.standin.brain import respond
    except ModuleNotFoundError as exc:
        if exc.name != "agos.agents.vlm.standin.brain":
            raise
        return wait_responder
    return respond


def responder_name(responder: Responder) -> str:
    """``module.qualname`` of a responder, for logs."""
    return f"{getattr(responder, '__module__', '?')}.{getattr(responder, '__qualname__', repr(responder))}"


# --- the server ---------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Plan:
    """What one valid chat-completion request gets, drawn at its arrival."""

    index: int
    outcome: str
    delay_s: float
    seed: int


@dataclass(frozen=True)
class Recorded:
    """A chat-completion request as received (for tests): headers and the parsed JSON body."""

    headers: dict[str, str]
    body: dict[str, Any]


@dataclass(frozen=True)
class Response:
    status: int
    body: bytes | None
    """None: drop the connection without answering."""
    headers: tuple[tuple[str, str], ...] = ()
    content_type: str = "application/json"


def _json_response(status: int, obj: Any, headers: tuple[tuple[str, str], ...] = ()) -> Response:
    return Response(status, json.dumps(obj).encode(), headers)


class StandinServer:
    """The stand-in endpoint. Bound at construction (``url`` is known, ``port=0`` picks a free port);
    :meth:`start` serves from a background thread; :meth:`close` stops it and drops open connections.
    Usable as a context manager (``with StandinServer(...) as s:``, started on entry).

    ``responder(split_request)`` is called from handler threads, several at once: it must be safe to
    call concurrently. ``script`` fixes the outcomes of the first requests (then the seeded draws).
    """

    def __init__(self, responder: Responder | None = None, *, models: Sequence[str] = DEFAULT_MODELS,
                 latency_ms: float = 0.0, jitter_ms: float = 0.0, faults: Mapping[str, float] | None = None,
                 retry_after_s: float = 0.05, hang_s: float = 90.0, max_images: int | None = None, seed: int = 0,
                 wrap_p: float = 0.3, script: Sequence[str] = (), host: str = "127.0.0.1", port: int = 0,
                 log: Callable[[str], None] | None = None, api_key: str | None = None) -> None:
        if not models:
            raise ValueError("at least one model name is needed")
        if latency_ms < 0 or jitter_ms < 0 or retry_after_s < 0 or hang_s < 0:
            raise ValueError("latency, jitter, retry-after and hang times must be >= 0")
        if max_images is not None and max_images < 0:
            raise ValueError("max_images must be >= 0")
        if not 0.0 <= wrap_p <= 1.0:
            raise ValueError("wrap_p must be in [0, 1]")
        if api_key is not None and not api_key:
            raise ValueError("the API key is empty")
        unknown = [s for s in script if s not in OUTCOMES]
        if unknown:
            raise FaultSpecError(f"unknown scripted outcome(s) {unknown} (known: {', '.join(OUTCOMES)})")
        self.responder = responder or default_responder()
        self.models = tuple(models)
        self.latency_s, self.jitter_s = latency_ms / 1000.0, jitter_ms / 1000.0
        self.faults = check_faults(faults)
        self.retry_after_s, self.hang_s, self.max_images, self.seed, self.wrap_p = retry_after_s, hang_s, max_images, seed, wrap_p
        self.log = log
        self._api_key = api_key
        self.recorded: deque[Recorded] = deque(maxlen=RECORDED)
        self._script = deque(script)
        self._fault_rng, self._reply_rng = fault_rng(seed), random.Random(f"agos-vlm-standin:{seed}:replies")
        self._lock = threading.Lock()
        self._counts: Counter[str] = Counter()
        self._outcomes: Counter[str] = Counter()
        self._errors: Counter[str] = Counter()
        self._sequence: list[str] = []
        self._in_flight = self._max_in_flight = 0
        self._closing = threading.Event()
        self._thread: threading.Thread | None = None
        self._http = _HttpServer((host, port), self)

    # lifecycle

    @property
    def host(self) -> str:
        return str(self._http.server_address[0])

    @property
    def port(self) -> int:
        return int(self._http.server_address[1])

    @property
    def url(self) -> str:
        """Base URL, ending in ``/v1``."""
        host = f"[{self.host}]" if ":" in self.host else self.host
        return f"http://{host}:{self.port}/v1"

    def start(self) -> StandinServer:
        if self._thread is None:
            self._thread = threading.Thread(target=self._http.serve_forever, name="vlm-standin", daemon=True)
            self._thread.start()
        return self

    def close(self) -> None:
        """Stop serving, wake sleeping handlers and drop open connections (idempotent)."""
        if self._closing.is_set():
            return
        self._closing.set()
        if self._thread is not None:
            self._http.shutdown()
            self._thread.join()
        self._http.drop_connections()
        self._http.server_close()

    def __enter__(self) -> StandinServer:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.close()

    # observation

    def stats(self) -> dict[str, Any]:
        """Counts: ``requests`` (all HTTP), ``chat_completions``, ``models``; ``outcomes`` per outcome of
        valid chat completions and ``faults`` (their sum without ok); ``errors`` per refused status;
        ``responder_errors``; ``in_flight`` and ``max_in_flight`` chat completions."""
        with self._lock:
            outcomes = {k: self._outcomes.get(k, 0) for k in OUTCOMES}
            return {"requests": self._counts["requests"], "chat_completions": self._counts["chat_completions"],
                    "models": self._counts["models"], "outcomes": outcomes,
                    "faults": sum(v for k, v in outcomes.items() if k != OK), "errors": dict(self._errors),
                    "responder_errors": self._counts["responder_errors"],
                    "in_flight": self._in_flight, "max_in_flight": self._max_in_flight}

    def sequence(self) -> list[str]:
        """Outcomes of the valid chat completions so far, in arrival order."""
        with self._lock:
            return list(self._sequence)

    # serving (called from handler threads)

    def _count(self, key: str) -> None:
        with self._lock:
            self._counts[key] += 1

    def _refused(self, exc: RequestError) -> Response:
        with self._lock:
            self._errors[str(exc.status)] += 1
        return _json_response(exc.status, exc.body())

    def models_response(self) -> Response:
        self._count("models")
        created = int(time.time())
        data = [{"id": m, "object": "model", "created": created, "owned_by": "agos-vlm-standin"} for m in self.models]
        return _json_response(200, {"object": "list", "data": data})

    def unauthorized(self, authorization: str | None) -> Response | None:
        """The 401 a ``/v1/*`` request gets without the server's key (None: let it through). The key is
        never echoed: a wrong one is named by its length only."""
        if self._api_key is None:
            return None
        scheme, _, given = (authorization or "").strip().partition(" ")
        given = given.strip()
        if scheme.lower() != "bearer" or not given:
            return self._refused(RequestError(
                401, "You didn't provide an API key: send it as 'Authorization: Bearer KEY' (agos vlm-standin "
                     "was started with --api-key-env).", kind="authentication_error", code="missing_api_key"))
        if not hmac.compare_digest(given.encode(), self._api_key.encode()):
            return self._refused(RequestError(
                401, f"Incorrect API key provided (a key of {len(given)} characters).", kind="authentication_error",
                code="invalid_api_key"))
        return None

    def stats_response(self) -> Response:
        return _json_response(200, self.stats())

    def not_found(self, method: str, path: str) -> Response:
        return self._refused(RequestError(404, f"{method} {path} is not served (try GET /v1/models, "
                                                  "POST /v1/chat/completions, GET /stats)"))

    def _plan(self) -> Plan:
        with self._lock:
            index = self._counts["planned"]
            self._counts["planned"] += 1
            outcome = self._script.popleft() if self._script else draw_outcome(self._fault_rng.random(), self.faults)
            seed = self._reply_rng.getrandbits(64)
            self._outcomes[outcome] += 1
            self._sequence.append(outcome)
            self._in_flight += 1
            self._max_in_flight = max(self._max_in_flight, self._in_flight)
        delay = self.latency_s + random.Random(seed).uniform(0.0, self.jitter_s)
        return Plan(index, outcome, delay, seed)

    def chat_response(self, raw: bytes, headers: dict[str, str]) -> Response:
        """Validate, draw the plan, sleep and answer one chat completion."""
        self._count("chat_completions")
        try:
            chat = parse_chat_body(raw, self.models, self.max_images)
            split = split_messages(chat)
        except RequestError as exc:
            return self._refused(exc)
        self.recorded.append(Recorded(headers, chat.body))
        plan = self._plan()
        started = time.monotonic()
        try:
            response = self._answer(plan, chat, split)
        finally:
            with self._lock:
                self._in_flight -= 1
        if self.log:
            self.log(f"#{plan.index} {chat.model} {plan.outcome} -> {response.status} "
                     f"({len(chat.image_sizes)} images, {(time.monotonic() - started) * 1000:.0f} ms)")
        return response

    def _answer(self, plan: Plan, chat: ChatRequest, split: SplitRequest) -> Response:
        if plan.outcome == "429":
            ms = round(self.retry_after_s * 1000)
            return _json_response(429, error_body("Rate limit reached (injected by agos vlm-standin)", "rate_limit_error",
                                                  "rate_limit_exceeded"),
                                  (("Retry-After", f"{self.retry_after_s:g}"), ("retry-after-ms", str(ms))))
        if plan.outcome == "500":
            return _json_response(500, error_body("Internal server error (injected by agos vlm-standin)", "server_error"))
        started = time.monotonic()
        if plan.outcome == "timeout" and self._closing.wait(self.hang_s):
            return Response(0, None)
        try:
            reply = self.responder(split)
            if not isinstance(reply, dict):
                raise TypeError(f"the responder returned {type(reply).__name__}, not a dict")
        except Exception as exc:  # a responder bug: answer 500 and say so, keep serving
            self._count("responder_errors")
            print(f"vlm-standin: responder {responder_name(self.responder)} failed: {exc!r}", file=sys.stderr)
            return _json_response(500, error_body(f"stand-in responder failed: {type(exc).__name__}: {exc}", "server_error"))
        if chat.strict_schema is not None:
            problem = violation(reply, chat.strict_schema)
            if problem is not None:  # a real endpoint constrains its answer or refuses; it never answers off-schema
                return self._refused(RequestError(
                    400, f"agos vlm-standin cannot answer the strict json_schema of this request: its responder's "
                         f"answer fails it at {problem}", param="response_format"))
        if self._closing.wait(max(0.0, plan.delay_s - (time.monotonic() - started))):
            return Response(0, None)
        if plan.outcome == "garbage":
            return Response(200, b"<html><body><h1>502 Bad Gateway</h1></body></html>", content_type="text/html")
        choices = []
        for i in range(chat.n):  # each choice draws its own wrapping (the first as a single answer would)
            rng = random.Random(plan.seed + 1 + i)
            content, finish = render_content(plan.outcome, reply, structured=chat.structured, wrap_p=self.wrap_p, rng=rng)
            if plan.outcome == OK:
                content, finish = cap_tokens(content, finish, chat.max_tokens)
            choices.append((content, finish))
        return _json_response(200, completion_body(plan.index, chat.model, choices, chat.prompt_tokens))


class _HttpServer(ThreadingHTTPServer):
    """A thread per connection; keeps the open connections so :meth:`drop_connections` can end them."""

    daemon_threads = True

    def __init__(self, address: tuple[str, int], standin: StandinServer) -> None:
        if ":" in address[0]:
            self.address_family = socket.AF_INET6
        self.standin = standin
        self._connections: set[socket.socket] = set()
        self._connections_lock = threading.Lock()
        super().__init__(address, _Handler)

    def process_request(self, request: Any, client_address: Any) -> None:
        with self._connections_lock:
            self._connections.add(request)
        super().process_request(request, client_address)

    def shutdown_request(self, request: Any) -> None:
        with self._connections_lock:
            self._connections.discard(request)
        super().shutdown_request(request)

    def drop_connections(self) -> None:
        with self._connections_lock:
            connections = list(self._connections)
        for conn in connections:
            with contextlib.suppress(OSError):
                conn.shutdown(socket.SHUT_RDWR)


class _Handler(BaseHTTPRequestHandler):
    protocol_version = "HTTP/1.1"
    server_version = "agos-vlm-standin/1"
    timeout = 300  # an idle keep-alive connection is closed after this many seconds
    disable_nagle_algorithm = True  # TCP_NODELAY: an answer leaves at once
    server: _HttpServer

    def log_message(self, format: str, *args: Any) -> None:
        pass

    def send_error(self, code: int, message: str | None = None, explain: str | None = None) -> None:
        """Protocol errors (bad request line, unsupported method) as OpenAI-style JSON."""
        self.close_connection = True
        self._send(_json_response(code, error_body(message or explain or "bad request", "invalid_request_error")))

    def _send(self, response: Response) -> None:
        """Status line, headers and body in one write (two writes on a keep-alive connection wait for the
        client's delayed ACK: ~40 ms a request under Nagle's algorithm, which is off here anyway)."""
        if response.body is None:
            self.close_connection = True
            return
        headers = [("Server", self.version_string()), ("Date", self.date_time_string()), *response.headers,
                   ("Content-Type", response.content_type), ("Content-Length", str(len(response.body)))]
        if self.close_connection:
            headers.append(("Connection", "close"))
        phrase = self.responses.get(response.status, ("",))[0]
        head = f"{self.protocol_version} {response.status} {phrase}\r\n" + "".join(f"{k}: {v}\r\n" for k, v in headers)
        try:
            self.wfile.write(head.encode("latin-1", "strict") + b"\r\n" + response.body)
            self.wfile.flush()
        except OSError:  # the client went away (e.g. it timed out during a hang)
            self.close_connection = True

    def _path(self) -> str:
        return self.path.split("?", 1)[0].rstrip("/") or "/"

    def do_GET(self) -> None:
        standin = self.server.standin
        standin._count("requests")
        path = self._path()
        if path == "/v1/models":
            self._send(standin.unauthorized(self.headers.get("Authorization")) or standin.models_response())
        elif path == "/stats":
            self._send(standin.stats_response())
        else:
            self._send(standin.not_found("GET", path))

    def do_POST(self) -> None:
        standin = self.server.standin
        standin._count("requests")
        raw = self._body()
        if raw is None:
            return
        path = self._path()
        if path == "/v1/chat/completions":
            refusal = standin.unauthorized(self.headers.get("Authorization"))
            self._send(refusal or standin.chat_response(raw, dict(self.headers.items())))
        else:
            self._send(standin.not_found("POST", path))

    def _body(self) -> bytes | None:
        """The request body, or None after answering 400/411/413 (the connection is then closed)."""
        if "chunked" in self.headers.get("Transfer-Encoding", "").lower():
            self._refuse(400, "chunked request bodies are not supported; send Content-Length")
            return None
        try:
            length = int(self.headers.get("Content-Length", ""))
        except ValueError:
            self._refuse(411, "a Content-Length header is required")
            return None
        if not 0 <= length <= MAX_BODY_BYTES:
            self._refuse(413, f"request body over {MAX_BODY_BYTES} bytes")
            return None
        return self.rfile.read(length)

    def _refuse(self, status: int, message: str) -> None:
        """Answer an error before the body was read, and close the connection."""
        self.close_connection = True
        self._send(self.server.standin._refused(RequestError(status, message)))
