"""``agos vlm-standin``: an OpenAI-compatible chat-completion server on loopback, for tests, the demo
and new users who have no model.

The transport half lives here; the decisions come from a *responder*: a callable that takes the
request taken apart by :func:`agos.agents.vlm.protocol.split_request` and returns the reply object
(e.g. ``{"action": "WAIT", "reason": "..."}``). By default it is
``agos.agents.vlm.standin_brain.respond`` (OpenCV perception, no ground truth), imported when the
server is built.

Endpoints (under ``/v1``, as vLLM and SGLang serve them):

* ``GET /v1/models``: the configured model names in OpenAI list format.
* ``POST /v1/chat/completions``: an OpenAI ``chat.completion`` object; ``usage.prompt_tokens`` is
  estimated as text characters / 4 plus, per image, one token per 28x28 pixels (each side rounded
  to a multiple of 28, as Qwen2.5-VL does); ``completion_tokens`` as reply characters / 4.
  Errors use OpenAI's ``{"error": {"message", "type", "param", "code"}}`` body: an unknown model is
  a 404 naming it, a malformed body a 400 saying what is wrong, more images than ``max_images`` a
  400 whose message starts like vLLM's (``At most N image(s) may be provided in one prompt.``).
  With ``response_format`` (``json_schema`` or ``json_object``) the content is plain JSON; without
  it the JSON is wrapped as models often do (markdown fences, a leading sentence) with probability
  ``wrap_p``. ``max_tokens`` is honoured: a longer reply is cut and ends with ``finish_reason="length"``.
* ``GET /stats``: request, outcome and error counts (see :meth:`StandinServer.stats`).

Latency and faults are drawn per valid chat-completion request, in arrival order, from RNGs seeded
by ``seed``: the same seed and request order give the same outcomes and reply texts. Requests that
are rejected (400/404) draw nothing. Outcomes (``FAULT_KINDS`` plus ``"ok"``):

* ``ok``: the responder's JSON after ``latency_ms`` + U(0, ``jitter_ms``) (the responder's own time
  counts toward it).
* ``429``: at once, with ``Retry-After`` (seconds) and ``retry-after-ms`` headers (``retry_after_s``).
* ``500``: at once, an OpenAI-style server error.
* ``timeout``: the answer comes after ``hang_s`` (a client with a shorter timeout gives up; the late
  answer is then written to a closed connection and dropped).
* ``malformed``: 200 whose content is not JSON (truncated JSON or prose).
* ``fenced``: 200 with the JSON inside markdown fences followed by a sentence.
* ``empty``: 200 with content ``""`` or ``null``.
* ``length``: 200 with ``finish_reason="length"`` and truncated JSON.
* ``garbage``: 200 whose HTTP body is an HTML page, not JSON (a proxy's error page).

The server is a ``ThreadingHTTPServer`` (HTTP/1.1, keep-alive): every connection has its own thread,
so sleeps never hold up other requests, and the responder is called from several threads at once.
"""

from __future__ import annotations

import argparse
import base64
import binascii
import contextlib
import ipaddress
import json
import math
import random
import signal
import socket
import sys
import threading
import time
from collections import Counter, deque
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from agos.agents.vlm.protocol import SplitRequest

Responder = Callable[["SplitRequest"], dict[str, Any]]

DEFAULT_MODELS = ("agos-standin",)
OK = "ok"
FAULT_KINDS = ("429", "500", "timeout", "malformed", "fenced", "empty", "length", "garbage")
"""Injectable faults, in the order their probabilities are stacked on the unit interval."""
OUTCOMES = (OK, *FAULT_KINDS)
TOKEN_PIXELS = 28
MAX_BODY_BYTES = 64 * 1024 * 1024
RECORDED = 64
"""How many recent chat-completion requests :attr:`StandinServer.recorded` keeps."""

LEADS = ("Here is my decision:", "Based on the images, this is the best action now.", "Sure! I will act as follows:")
TRAILS = ("I chose this because it is what the current views support.", "Let me know if you need anything else.",
          "Note: the target may be partly occluded.")
PROSE = ("I am not able to decide from these images; the target is not clearly visible.",
         "The best action is to wait and look again")


class FaultSpecError(ValueError):
    """A fault specification is wrong; the message names the bad entry."""


class RequestError(Exception):
    """A request the server refuses: HTTP status and an OpenAI-style error body."""

    def __init__(self, status: int, message: str, *, kind: str = "BadRequestError", param: str | None = None) -> None:
        super().__init__(message)
        self.status, self.message, self.kind, self.param = status, message, kind, param

    def body(self) -> dict[str, Any]:
        return error_body(self.message, self.kind, self.status, self.param)


def error_body(message: str, kind: str, code: int | str, param: str | None = None) -> dict[str, Any]:
    """OpenAI's error object."""
    return {"error": {"message": message, "type": kind, "param": param, "code": code}}


# --- faults ---------------------------------------------------------------------------------------


def check_faults(faults: Mapping[str, float] | None) -> dict[str, float]:
    """Validated fault probabilities: known kinds, each in [0, 1], summing to at most 1."""
    out: dict[str, float] = {}
    for kind, p in (faults or {}).items():
        kind = str(kind)
        if kind not in FAULT_KINDS:
            raise FaultSpecError(f"unknown fault {kind!r} (known: {', '.join(FAULT_KINDS)})")
        if not isinstance(p, int | float) or isinstance(p, bool) or not 0.0 <= float(p) <= 1.0:
            raise FaultSpecError(f"fault {kind!r}: probability {p!r} is not a number in [0, 1]")
        out[kind] = float(p)
    total = sum(out.values())
    if total > 1.0 + 1e-9:
        raise FaultSpecError(f"fault probabilities sum to {total:g}, more than 1")
    return out


def parse_faults(spec: str) -> dict[str, float]:
    """``"429=0.1,500=0.05,timeout=0.02"`` -> ``{"429": 0.1, ...}``; FaultSpecError names a bad entry."""
    faults: dict[str, float] = {}
    for entry in (e.strip() for e in spec.split(",")):
        if not entry:
            continue
        kind, sep, value = (s.strip() for s in entry.partition("="))
        if not sep:
            raise FaultSpecError(f"bad fault entry {entry!r}: expected KIND=PROBABILITY, e.g. 429=0.1")
        if kind in faults:
            raise FaultSpecError(f"bad fault entry {entry!r}: {kind!r} given twice")
        try:
            faults[kind] = float(value)
        except ValueError:
            raise FaultSpecError(f"bad fault entry {entry!r}: {value!r} is not a probability") from None
        try:
            check_faults({kind: faults[kind]})
        except FaultSpecError as exc:
            raise FaultSpecError(f"bad fault entry {entry!r}: {exc}") from None
    return check_faults(faults)


def draw_outcome(u: float, faults: Mapping[str, float]) -> str:
    """The outcome for a uniform draw ``u`` in [0, 1): faults stacked in ``FAULT_KINDS`` order, then ok."""
    edge = 0.0
    for kind in FAULT_KINDS:
        edge += faults.get(kind, 0.0)
        if u < edge:
            return kind
    return OK


def _fault_rng(seed: int) -> random.Random:
    return random.Random(f"agos-vlm-standin:{seed}:faults")


def fault_sequence(faults: Mapping[str, float], seed: int, n: int) -> list[str]:
    """The outcomes of the first ``n`` unscripted requests of a server with these faults and seed."""
    rng, checked = _fault_rng(seed), check_faults(faults)
    return [draw_outcome(rng.random(), checked) for _ in range(n)]


# --- images and tokens ------------------------------------------------------------------------------

_SOF = {0xC0, 0xC1, 0xC2, 0xC3, 0xC5, 0xC6, 0xC7, 0xC9, 0xCA, 0xCB, 0xCD, 0xCE, 0xCF}


def _jpeg_size(data: bytes) -> tuple[int, int] | None:
    i = 2
    while i + 9 <= len(data):
        if data[i] != 0xFF:
            return None
        marker = data[i + 1]
        if marker == 0xFF:
            i += 1
        elif marker == 0x01 or 0xD0 <= marker <= 0xD8:
            i += 2
        elif marker in _SOF:
            return int.from_bytes(data[i + 7:i + 9], "big"), int.from_bytes(data[i + 5:i + 7], "big")
        else:
            i += 2 + int.from_bytes(data[i + 2:i + 4], "big")
    return None


def image_size(data: bytes) -> tuple[int, int] | None:
    """(width, height) of an encoded image: read from the PNG or JPEG header, else decoded by OpenCV;
    None when it is not an image."""
    if data[:8] == b"\x89PNG\r\n\x1a\n" and data[12:16] == b"IHDR":
        return int.from_bytes(data[16:20], "big"), int.from_bytes(data[20:24], "big")
    if data[:2] == b"\xff\xd8":
        size = _jpeg_size(data)
        if size is not None and size[0] > 0 and size[1] > 0:
            return size
    import cv2
    import numpy as np

    image = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED) if data else None
    return None if image is None else (int(image.shape[1]), int(image.shape[0]))


def image_tokens(width: int, height: int) -> int:
    """One token per 28x28 pixels, each side rounded to a multiple of 28 (at least one)."""
    return max(1, round(width / TOKEN_PIXELS)) * max(1, round(height / TOKEN_PIXELS))


def text_tokens(text_or_chars: str | int) -> int:
    """About four characters per token."""
    chars = text_or_chars if isinstance(text_or_chars, int) else len(text_or_chars)
    return math.ceil(chars / 4)


# --- request parsing --------------------------------------------------------------------------------


@dataclass(frozen=True)
class ChatRequest:
    """A validated chat-completion body."""

    body: dict[str, Any]
    model: str
    messages: list[dict[str, Any]]
    structured: bool
    """``response_format`` asked for JSON (``json_schema`` or ``json_object``)."""
    max_tokens: int | None
    text_chars: int
    image_sizes: tuple[tuple[int, int], ...]

    @property
    def prompt_tokens(self) -> int:
        return text_tokens(self.text_chars) + sum(image_tokens(w, h) for w, h in self.image_sizes)


def _json_object(raw: bytes) -> dict[str, Any]:
    try:
        body = json.loads(raw)
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise RequestError(400, f"request body is not valid JSON: {exc}") from None
    if not isinstance(body, dict):
        raise RequestError(400, f"request body must be a JSON object, not {type(body).__name__}")
    return body


def _model(body: dict[str, Any], models: Sequence[str]) -> str:
    model = body.get("model")
    if not isinstance(model, str) or not model:
        raise RequestError(400, "'model' is required (a string)", param="model")
    if model not in models:
        raise RequestError(404, f"The model `{model}` does not exist. This server serves: {', '.join(models)}.",
                           kind="NotFoundError", param="model")
    return model


def _structured(body: dict[str, Any]) -> bool:
    fmt = body.get("response_format")
    if fmt is None:
        return False
    kind = fmt.get("type") if isinstance(fmt, dict) else None
    if kind not in ("text", "json_object", "json_schema"):
        raise RequestError(400, "'response_format.type' must be one of text, json_object, json_schema", param="response_format")
    if kind == "json_schema" and not isinstance(fmt.get("json_schema"), dict):
        raise RequestError(400, "'response_format.json_schema' must be an object", param="response_format")
    return kind != "text"


def _max_tokens(body: dict[str, Any]) -> int | None:
    for key in ("max_completion_tokens", "max_tokens"):
        value = body.get(key)
        if value is None:
            continue
        if not isinstance(value, int) or isinstance(value, bool) or value < 1:
            raise RequestError(400, f"'{key}' must be a positive integer", param=key)
        return value
    return None


def _image_bytes(part: dict[str, Any], where: str) -> bytes:
    url = (part.get("image_url") or {}).get("url") if isinstance(part.get("image_url"), dict) else None
    if not isinstance(url, str):
        raise RequestError(400, f"{where}: image_url.url is missing")
    if not url.startswith("data:") or ";base64," not in url[:100]:
        raise RequestError(400, f"{where}: only base64 data URLs (data:image/jpeg;base64,...) are supported, not {url[:40]!r}")
    try:
        return base64.b64decode(url.split(",", 1)[1], validate=True)
    except (binascii.Error, ValueError):
        raise RequestError(400, f"{where}: the data URL is not valid base64") from None


def _parts(message: Any, m: int) -> list[tuple[str, dict[str, Any]]]:
    if not isinstance(message, dict):
        raise RequestError(400, f"messages[{m}] must be an object", param="messages")
    if not isinstance(message.get("role"), str):
        raise RequestError(400, f"messages[{m}].role is required (a string)", param="messages")
    content = message.get("content")
    if content is None:
        return []
    if isinstance(content, str):
        return [(f"messages[{m}].content", {"type": "text", "text": content})]
    if not isinstance(content, list):
        raise RequestError(400, f"messages[{m}].content must be a string or a list of parts", param="messages")
    out = []
    for p, part in enumerate(content):
        where = f"messages[{m}].content[{p}]"
        if not isinstance(part, dict) or part.get("type") not in ("text", "image_url"):
            kind = part.get("type") if isinstance(part, dict) else type(part).__name__
            raise RequestError(400, f"{where}: unsupported content part {kind!r} (text and image_url are)", param="messages")
        if part["type"] == "text" and not isinstance(part.get("text"), str):
            raise RequestError(400, f"{where}: a text part needs a string 'text'", param="messages")
        out.append((where, part))
    return out


def too_many_images_message(count: int, limit: int) -> str:
    """vLLM's wording (its first sentence), so a preflight that knows vLLM learns the limit."""
    return (f"At most {limit} image(s) may be provided in one prompt. This request has {count}. "
            f"(agos vlm-standin: --max-images; vLLM: --limit-mm-per-prompt)")


def parse_chat_body(raw: bytes, models: Sequence[str], max_images: int | None = None) -> ChatRequest:
    """Validate a chat-completion body; RequestError (400, or 404 for an unknown model) says what is wrong."""
    body = _json_object(raw)
    model = _model(body, models)
    messages = body.get("messages")
    if not isinstance(messages, list) or not messages:
        raise RequestError(400, "'messages' must be a non-empty list", param="messages")
    if body.get("stream"):
        raise RequestError(400, "streaming is not supported by agos vlm-standin; send stream=false", param="stream")
    structured, max_tokens = _structured(body), _max_tokens(body)
    parts = [wp for m, message in enumerate(messages) for wp in _parts(message, m)]
    images = [(where, part) for where, part in parts if part["type"] == "image_url"]
    if max_images is not None and len(images) > max_images:
        raise RequestError(400, too_many_images_message(len(images), max_images), param="messages")
    sizes = []
    for where, part in images:
        size = image_size(_image_bytes(part, where))
        if size is None:
            raise RequestError(400, f"{where}: the image is not a JPEG or PNG (cannot read its size)", param="messages")
        sizes.append(size)
    chars = sum(len(part["text"]) for _, part in parts if part["type"] == "text")
    return ChatRequest(body, model, messages, structured, max_tokens, chars, tuple(sizes))


def split_messages(chat: ChatRequest) -> SplitRequest:
    """The request as the responder sees it (:func:`~agos.agents.vlm.protocol.split_request`); 400 when
    agos's layout is broken (e.g. the STATE line is not JSON)."""
    from agos.agents.vlm.protocol import split_request

    try:
        return split_request(chat.messages)
    except (ValueError, binascii.Error) as exc:
        raise RequestError(400, f"cannot read the request layout: {exc}", param="messages") from None


# --- replies ----------------------------------------------------------------------------------------


def _prefix(text: str, rng: random.Random) -> str:
    """A proper prefix of ``text`` (never valid JSON when ``text`` is a JSON object)."""
    return text[:rng.randint(1, max(1, len(text) - 2))]


def render_content(outcome: str, reply: dict[str, Any], *, structured: bool, wrap_p: float,
                   rng: random.Random) -> tuple[str | None, str]:
    """The message content and finish_reason a model would give for this outcome."""
    text = json.dumps(reply, ensure_ascii=False)
    if outcome == "malformed":
        return (_prefix(text, rng) if rng.random() < 0.7 else rng.choice(PROSE)), "stop"
    if outcome == "fenced":
        return f"```json\n{text}\n```\n{rng.choice(TRAILS)}", "stop"
    if outcome == "empty":
        return rng.choice(("", None)), "stop"
    if outcome == "length":
        return _prefix(text, rng), "length"
    if structured or rng.random() >= wrap_p:
        return text, "stop"
    style = rng.randrange(3)
    fenced = f"```json\n{text}\n```"
    return (fenced if style == 0 else f"{rng.choice(LEADS)}\n{text if style == 1 else fenced}"), "stop"


def cap_tokens(content: str | None, finish: str, max_tokens: int | None) -> tuple[str | None, str]:
    """Cut a reply longer than ``max_tokens`` (4 characters a token) and mark it ``length``."""
    if content is None or max_tokens is None or text_tokens(content) <= max_tokens:
        return content, finish
    return content[:max_tokens * 4], "length"


def completion_body(index: int, model: str, content: str | None, finish: str, prompt_tokens: int) -> dict[str, Any]:
    """An OpenAI ``chat.completion`` object."""
    completion = text_tokens(content or "")
    return {
        "id": f"chatcmpl-standin-{index}", "object": "chat.completion", "created": int(time.time()), "model": model,
        "system_fingerprint": "agos-vlm-standin",
        "choices": [{"index": 0, "message": {"role": "assistant", "content": content}, "logprobs": None, "finish_reason": finish}],
        "usage": {"prompt_tokens": prompt_tokens, "completion_tokens": completion, "total_tokens": prompt_tokens + completion},
    }


def wait_responder(request: SplitRequest) -> dict[str, Any]:
    """The fallback responder when ``standin_brain`` is not there: always WAIT (legal for both roles)."""
    return {"action": "WAIT", "reason": f"stand-in without a brain; saw {len(request.images)} labelled image(s)"}


def default_responder() -> Responder:
    """``agos.agents.vlm.standin_brain.respond``, or :func:`wait_responder` while that module does not exist."""
    try:
        from agos.agents.vlm.standin_brain import respond
    except ModuleNotFoundError as exc:
        if exc.name != "agos.agents.vlm.standin_brain":
            raise
        return wait_responder
    return respond


def _responder_name(responder: Responder) -> str:
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
                 log: Callable[[str], None] | None = None) -> None:
        if not models:
            raise ValueError("at least one model name is needed")
        if latency_ms < 0 or jitter_ms < 0 or retry_after_s < 0 or hang_s < 0:
            raise ValueError("latency, jitter, retry-after and hang times must be >= 0")
        if max_images is not None and max_images < 0:
            raise ValueError("max_images must be >= 0")
        if not 0.0 <= wrap_p <= 1.0:
            raise ValueError("wrap_p must be in [0, 1]")
        unknown = [s for s in script if s not in OUTCOMES]
        if unknown:
            raise FaultSpecError(f"unknown scripted outcome(s) {unknown} (known: {', '.join(OUTCOMES)})")
        self.responder = responder or default_responder()
        self.models = tuple(models)
        self.latency_s, self.jitter_s = latency_ms / 1000.0, jitter_ms / 1000.0
        self.faults = check_faults(faults)
        self.retry_after_s, self.hang_s, self.max_images, self.seed, self.wrap_p = retry_after_s, hang_s, max_images, seed, wrap_p
        self.log = log
        self.recorded: deque[Recorded] = deque(maxlen=RECORDED)
        self._script = deque(script)
        self._fault_rng, self._reply_rng = _fault_rng(seed), random.Random(f"agos-vlm-standin:{seed}:replies")
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

    def stats_response(self) -> Response:
        return _json_response(200, self.stats())

    def not_found(self, method: str, path: str) -> Response:
        return self._refused(RequestError(404, f"{method} {path} is not served (try GET /v1/models, "
                                                  "POST /v1/chat/completions, GET /stats)", kind="NotFoundError"))

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
            return _json_response(429, error_body("Rate limit reached (injected by agos vlm-standin)", "rate_limit_exceeded", 429),
                                  (("Retry-After", f"{self.retry_after_s:g}"), ("retry-after-ms", str(ms))))
        if plan.outcome == "500":
            return _json_response(500, error_body("Internal server error (injected by agos vlm-standin)", "server_error", 500))
        started = time.monotonic()
        if plan.outcome == "timeout" and self._closing.wait(self.hang_s):
            return Response(0, None)
        try:
            reply = self.responder(split)
            if not isinstance(reply, dict):
                raise TypeError(f"the responder returned {type(reply).__name__}, not a dict")
        except Exception as exc:  # a responder bug: answer 500 and say so, keep serving
            self._count("responder_errors")
            print(f"vlm-standin: responder {_responder_name(self.responder)} failed: {exc!r}", file=sys.stderr)
            return _json_response(500, error_body(f"stand-in responder failed: {type(exc).__name__}: {exc}", "server_error", 500))
        if self._closing.wait(max(0.0, plan.delay_s - (time.monotonic() - started))):
            return Response(0, None)
        if plan.outcome == "garbage":
            return Response(200, b"<html><body><h1>502 Bad Gateway</h1></body></html>", content_type="text/html")
        rng = random.Random(plan.seed + 1)
        content, finish = render_content(plan.outcome, reply, structured=chat.structured, wrap_p=self.wrap_p, rng=rng)
        if plan.outcome == OK:
            content, finish = cap_tokens(content, finish, chat.max_tokens)
        return _json_response(200, completion_body(plan.index, chat.model, content, finish, chat.prompt_tokens))


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
    server: _HttpServer

    def log_message(self, format: str, *args: Any) -> None:
        pass

    def send_error(self, code: int, message: str | None = None, explain: str | None = None) -> None:
        """Protocol errors (bad request line, unsupported method) as OpenAI-style JSON."""
        self.close_connection = True
        self._send(_json_response(code, error_body(message or explain or "bad request", "BadRequestError", code)))

    def _send(self, response: Response) -> None:
        if response.body is None:
            self.close_connection = True
            return
        try:
            self.send_response(response.status)
            for key, value in response.headers:
                self.send_header(key, value)
            self.send_header("Content-Type", response.content_type)
            self.send_header("Content-Length", str(len(response.body)))
            if self.close_connection:
                self.send_header("Connection", "close")
            self.end_headers()
            self.wfile.write(response.body)
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
            self._send(standin.models_response())
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
            self._send(standin.chat_response(raw, dict(self.headers.items())))
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


# --- command line ---------------------------------------------------------------------------------------


def faults_arg(text: str) -> dict[str, float]:
    """argparse type for ``--faults``."""
    try:
        return parse_faults(text)
    except FaultSpecError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def add_parser(sub: Any) -> argparse.ArgumentParser:
    """Add the ``vlm-standin`` subcommand to an ``add_subparsers()`` object."""
    p = sub.add_parser("vlm-standin", help="OpenAI-compatible stand-in VLM server on loopback (latency, injected faults)",
                       description="Serve /v1/models and /v1/chat/completions answered by the OpenCV stand-in brain.")
    p.add_argument("--host", default="127.0.0.1", help="address to listen on (default 127.0.0.1; there is no authentication)")
    p.add_argument("--port", type=int, default=8000, help="port (default 8000; 0 picks a free one and prints it)")
    p.add_argument("--model", action="append", help=f"model name to serve (repeatable; default {DEFAULT_MODELS[0]})")
    p.add_argument("--latency-ms", type=float, default=0.0, help="fixed reply latency")
    p.add_argument("--jitter-ms", type=float, default=0.0, help="extra latency, uniform in [0, jitter] (seeded)")
    p.add_argument("--faults", type=faults_arg, default={},
                   help=f"KIND=P,... with KIND in {', '.join(FAULT_KINDS)}, e.g. 429=0.1,500=0.05,timeout=0.02,fenced=0.2")
    p.add_argument("--retry-after-s", type=float, default=1.0, help="Retry-After of injected 429s (default 1)")
    p.add_argument("--hang-s", type=float, default=90.0, help="how long an injected timeout hangs (default 90)")
    p.add_argument("--max-images", type=int, help="refuse requests with more images, as vLLM's --limit-mm-per-prompt does")
    p.add_argument("--wrap-p", type=float, default=0.3,
                   help="without response_format: probability that the JSON comes in fences or after a sentence (default 0.3)")
    p.add_argument("--seed", type=int, default=0, help="seed of latency, fault and wrapping draws")
    p.add_argument("--verbose", "-v", action="store_true", help="one line per chat completion on stderr")
    return p


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="agos")
    add_parser(parser.add_subparsers(dest="command", required=True))
    return parser


def _announce(server: StandinServer, faults: Mapping[str, float]) -> None:
    model = server.models[0]
    fault_text = ",".join(f"{k}={v:g}" for k, v in faults.items()) or "none"
    print(f"agos vlm-standin: listening on {server.url}", flush=True)
    print(f"  models: {', '.join(server.models)}; responder: {_responder_name(server.responder)}", flush=True)
    print(f"  latency {server.latency_s * 1000:g} ms + up to {server.jitter_s * 1000:g} ms; faults {fault_text}; "
          f"max images {server.max_images if server.max_images is not None else 'unlimited'}; seed {server.seed}", flush=True)
    print(f"  point agos at it: --vlm-base-url {server.url} --model {model}", flush=True)
    try:
        loopback = server.host == "localhost" or ipaddress.ip_address(server.host).is_loopback
    except ValueError:
        loopback = False
    if not loopback:
        print(f"  warning: listening on {server.host}, not loopback; anyone who can reach it can use it", flush=True)


def run(args: argparse.Namespace) -> int:
    """Serve until SIGINT or SIGTERM; 0 on a clean stop, 2 when it cannot listen or a setting is wrong."""
    try:
        server = StandinServer(models=args.model or DEFAULT_MODELS, latency_ms=args.latency_ms, jitter_ms=args.jitter_ms,
                               faults=args.faults, retry_after_s=args.retry_after_s, hang_s=args.hang_s,
                               max_images=args.max_images, seed=args.seed, wrap_p=args.wrap_p, host=args.host, port=args.port,
                               log=(lambda line: print(line, file=sys.stderr, flush=True)) if args.verbose else None)
    except OSError as exc:
        print(f"vlm-standin error: cannot listen on {args.host}:{args.port}: {exc}", file=sys.stderr)
        return 2
    except ValueError as exc:
        print(f"vlm-standin error: {exc}", file=sys.stderr)
        return 2
    stop = threading.Event()
    in_main = threading.current_thread() is threading.main_thread()
    previous = signal.signal(signal.SIGTERM, lambda *_: stop.set()) if in_main else None
    try:
        with server:
            _announce(server, server.faults)
            while not stop.wait(0.5):
                pass
    except KeyboardInterrupt:
        pass
    finally:
        if in_main:
            signal.signal(signal.SIGTERM, previous)
    stats = server.stats()
    print(f"agos vlm-standin: stopped after {stats['chat_completions']} chat completions ({stats['faults']} injected faults)",
          flush=True)
    return 0


def main(argv: list[str] | None = None) -> int:
    """``python -m agos.agents.vlm.standin_server [options]``: the same as ``agos vlm-standin``."""
    return run(build_parser().parse_args(["vlm-standin", *(sys.argv[1:] if argv is None else argv)]))


if __name__ == "__main__":
    sys.exit(main())
