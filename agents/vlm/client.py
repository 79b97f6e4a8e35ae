"""An async client for OpenAI-compatible chat-completion endpoints (vLLM, SGLang, Ollama,
llama.cpp server, hosted APIs), for VLM policies.

* Images go as ``image_url`` parts with base64 data URLs (JPEG for RGB, PNG otherwise).
* Structured output: ``response_format`` with a JSON schema when the backend supports it
  (``structured=True``); the reply is always validated by the caller anyway.
* Retries on 408, 409, 429, 5xx, timeouts and connection errors: honour ``retry-after-ms``, then
  ``Retry-After`` (seconds) or LiteLLM's renamed ``llm_provider-retry-after``, else exponential
  back-off with full jitter; at most ``max_retries``.
* At most ``concurrency`` requests in flight per client.
* :meth:`preflight` reads ``/models`` so a run fails before it starts when the endpoint cannot be
  reached, refuses the key or does not serve the model, with one line saying which
  (agents/vlm/endpoint.py); a 401/403 to any request says the same about the key.
* The API key is read from an environment variable and is never logged or returned.

Every call returns a :class:`Reply` with the text, ``finish_reason``, token usage, latency and the
number of HTTP attempts: retries are counted apart from decisions (DS never includes them); and the
sizes of the request body posted and of the reply body received (what ``--model-link`` carries).
"""

from __future__ import annotations

import asyncio
import base64
import contextlib
import functools
import json
import os
import random
import time
from collections.abc import Awaitable, Callable
from dataclasses import dataclass, field
from typing import Any, Protocol

import httpx

from agos.agents.vlm.endpoint import key_failure, listing_failure, model_failure, server_message, transport_failure
from agos.runtime.settings import DEFAULTS

_VLM = DEFAULTS.vlm
"""The ``[vlm]`` defaults, which a client made without options takes."""


@dataclass(frozen=True)
class CallTag:
    """Which decision asks: its stream (``<episode>/<role>``) and, for messages, its index."""

    episode_id: str
    role: str
    decision_index: int

    @property
    def stream(self) -> str:
        return f"{self.episode_id}/{self.role}"


class ReplyCache(Protocol):
    """What the client asks of a record/replay cache (agents/vlm/cache.py's ``ReplyCache``; a protocol
    here so that the client does not import the cache, which imports the client's replies)."""

    async def complete(self, body: dict[str, Any], call: CallTag | None,
                       send: Callable[[dict[str, Any]], Awaitable[Reply]]) -> Reply: ...


RETRY_STATUS = {408, 409, 429, 500, 502, 503, 504}
OUTAGE_KINDS = ("outage", "auth")
"""``VlmError`` kinds that are outages of the endpoint, not answers to the request (:attr:`VlmError.outage`)."""


class VlmError(RuntimeError):
    """The endpoint could not give an answer (after retries); the message says why, never the key."""

    def __init__(self, message: str, *, attempts: int = 0, kind: str = "http") -> None:
        super().__init__(message)
        self.attempts = attempts
        """HTTP requests made before giving up."""
        self.kind = kind
        """What failed (agents/vlm/endpoint.py's ``KINDS``): refused, unreachable, timeout, auth, model, http,
        or ``outage``: no answer after the retry budget (connection errors, timeouts, 408/409/429/5xx,
        unusable bodies)."""

    @property
    def outage(self) -> bool:
        """The endpoint gave no answer (``outage``) or refused the key (``auth``): an infrastructure
        failure, never the model's decision (agents/contract.py::EndpointOutage). Other kinds (a 400,
        a 404: the request itself was refused) cost the decision a fallback WAIT."""
        return self.kind in OUTAGE_KINDS


@dataclass
class Reply:
    text: str | None
    finish_reason: str | None
    prompt_tokens: int | None
    completion_tokens: int | None
    latency_s: float
    attempts: int
    raw: dict[str, Any] = field(default_factory=dict, repr=False)
    request_bytes: int = 0
    """The request body posted (:func:`request_body`), bytes."""
    reply_bytes: int = 0
    """The reply body received, bytes (a replayed reply: its stored body's, the same when it was
    recorded by this version: agents/vlm/cache.py)."""
    body_text: str | None = field(default=None, repr=False)
    """The reply body as the endpoint sent it (UTF-8), for the cache; None when not UTF-8 or not from the endpoint."""


def image_part(data: bytes, encoding: str) -> dict[str, Any]:
    mime = "image/jpeg" if encoding == "jpeg" else "image/png"
    return {"type": "image_url", "image_url": {"url": f"data:{mime};base64,{base64.b64encode(data).decode()}"}}


def request_body(body: dict[str, Any]) -> bytes:
    """The bytes posted for a request ``body``: compact UTF-8 JSON (what httpx's ``json=`` would send)."""
    return json.dumps(body, ensure_ascii=False, separators=(",", ":"), allow_nan=False).encode("utf-8")


TEMPERATURE = 0.0
"""The sampling temperature of every request (greedy: the same request asks for the same answer)."""


class VlmClient:
    def __init__(self, base_url: str, model: str, *, api_key_env: str = _VLM.api_key_env,
                 timeout_s: float = _VLM.timeout_s, max_retries: int = _VLM.max_retries, concurrency: int = _VLM.concurrency,
                 structured: bool = _VLM.structured, max_tokens: int = _VLM.max_tokens,
                 backoff_base_s: float = 0.5, backoff_max_s: float = 20.0, transport: httpx.AsyncBaseTransport | None = None,
                 rng: random.Random | None = None, cache: ReplyCache | None = None) -> None:
        self.base_url = base_url.rstrip("/")
        self.cache = cache
        """Record/replay of requests (``--vlm-cache``); None: every request goes to the endpoint."""
        self.model = model
        self.api_key_env, self.timeout_s = api_key_env, timeout_s
        self.max_retries, self.structured, self.max_tokens = max_retries, structured, max_tokens
        self.backoff_base_s, self.backoff_max_s = backoff_base_s, backoff_max_s
        self._limit = asyncio.Semaphore(concurrency)
        self._rng = rng or random.Random()
        key = os.environ.get(api_key_env)
        self._secret = key or None
        headers = {"Authorization": f"Bearer {key}"} if key else {}
        self._http = httpx.AsyncClient(base_url=self.base_url, headers=headers, timeout=timeout_s, transport=transport)
        self.listing: list[dict[str, Any]] | None = None
        """The entries of the last ``/models`` answer :meth:`preflight` accepted (a run card keeps them)."""

    async def close(self) -> None:
        await self._http.aclose()

    async def preflight(self, timeout_s: float | None = None) -> list[str]:
        """Models the server offers. Raises VlmError with one line (agents/vlm/endpoint.py) when it is
        unreachable or refuses the connection, gives no answer within ``timeout_s`` (default: the
        client's), answers 401/403, answers anything but a model list, or does not list ``model``."""
        timeout = self.timeout_s if timeout_s is None else timeout_s
        try:
            response = await self._http.get("/models", timeout=timeout)
        except httpx.HTTPError as exc:
            kind, line = transport_failure(self.base_url, exc, timeout)
            raise VlmError(self._redact(line), kind=kind, attempts=1) from None
        said = self._redact(server_message(response))
        if response.status_code in (401, 403):
            raise VlmError(key_failure(self.base_url, response.status_code, self.api_key_env, self._secret is not None, said),
                           kind="auth", attempts=1)
        try:
            data = response.json().get("data") if response.is_success else None
        except (ValueError, AttributeError):
            data = None
        if not isinstance(data, list):
            raise VlmError(listing_failure(self.base_url, response, said), kind="http", attempts=1)
        models = [str(m.get("id")) for m in data if isinstance(m, dict)]
        if self.model not in models:
            raise VlmError(model_failure(self.base_url, self.model, models), kind="model", attempts=1)
        self.listing = [m for m in data if isinstance(m, dict)]
        return models

    def _body(self, messages: list[dict[str, Any]], schema: dict[str, Any] | None) -> dict[str, Any]:
        body: dict[str, Any] = {"model": self.model, "messages": messages, "max_tokens": self.max_tokens,
                                "temperature": TEMPERATURE}
        if schema is not None and self.structured:
            body["response_format"] = {"type": "json_schema", "json_schema": {"name": "action", "schema": schema}}
        return body

    def _delay(self, attempt: int, response: httpx.Response | None) -> float:
        if response is not None:
            ms = response.headers.get("retry-after-ms")
            if ms is not None:
                try:
                    return min(self.backoff_max_s, float(ms) / 1000.0)
                except ValueError:
                    pass
            for name in ("retry-after", "llm_provider-retry-after"):  # LiteLLM renames the provider's header
                seconds = response.headers.get(name)
                if seconds is not None:
                    try:
                        return min(self.backoff_max_s, max(0.0, float(seconds)))
                    except ValueError:
                        pass
        return self._rng.uniform(0.0, min(self.backoff_max_s, self.backoff_base_s * 2 ** attempt))

    async def complete(self, messages: list[dict[str, Any]], *, schema: dict[str, Any] | None = None,
                       call: CallTag | None = None, deadline: float | None = None) -> Reply:
        """The model's reply to ``messages``. With a ``cache`` (agents/vlm/cache.py), the cache answers
        or records the request; ``call`` names the decision asking (its replay stream and index).
        ``deadline`` (``time.monotonic()`` seconds): no attempt or retry goes past it; a request still
        unanswered then is a VlmError of kind ``outage``, as when the retries run out."""
        body = self._body(messages, schema)
        send = self._send if deadline is None else functools.partial(self._send, deadline=deadline)
        reply = await (self.cache.complete(body, call, send) if self.cache is not None else send(body))
        reply.request_bytes = len(request_body(body))  # the same for a replayed reply: the body is the same
        return reply

    async def _send(self, body: dict[str, Any], deadline: float | None = None) -> Reply:
        """``body`` posted to the endpoint, with retries (see the module docstring), within ``deadline``."""
        started = time.monotonic()
        last_error = "no attempt"
        made = 0
        content = request_body(body)
        async with self._limit:
            for attempt in range(self.max_retries + 1):
                response = None
                left = None if deadline is None else deadline - time.monotonic()
                if left is not None and left <= 0:
                    break
                made += 1
                try:
                    response = await self._http.post("/chat/completions", content=content,
                                                      headers={"Content-Type": "application/json"},
                                                      timeout=self.timeout_s if left is None else min(self.timeout_s, left))
                    if response.status_code in RETRY_STATUS:
                        last_error = f"HTTP {response.status_code}"
                    elif response.status_code in (401, 403):
                        raise VlmError(key_failure(self.base_url, response.status_code, self.api_key_env,
                                                   self._secret is not None, self._redact(server_message(response))),
                                       attempts=attempt + 1, kind="auth")
                    elif response.is_error:
                        raise VlmError(f"{self.base_url}: HTTP {response.status_code}: {self._redact(server_message(response))}",
                                       attempts=attempt + 1)
                    else:
                        reply = self._reply(response.json(), started, attempt + 1)
                        reply.reply_bytes = len(response.content)
                        with contextlib.suppress(UnicodeDecodeError):
                            reply.body_text = response.content.decode("utf-8")
                        return reply
                except httpx.HTTPError as exc:  # timeouts, connection and protocol errors, undecodable bodies
                    last_error = type(exc).__name__
                except ValueError as exc:  # a 200 whose body is not JSON, or not a chat completion
                    last_error = self._redact(f"invalid reply body ({exc})")
                if attempt < self.max_retries:
                    delay = self._delay(attempt, response)
                    if deadline is not None and time.monotonic() + delay >= deadline:
                        break
                    await asyncio.sleep(delay)
        cut = " within the decision's time" if made < self.max_retries + 1 else ""
        raise VlmError(f"{self.base_url}: no answer after {made} attempt{'' if made == 1 else 's'}{cut} ({last_error})",
                       attempts=made, kind="outage")

    def _redact(self, text: str) -> str:
        """Error text with the API key removed (a server may echo the request's headers)."""
        return text.replace(self._secret, "<redacted>") if self._secret else text

    @staticmethod
    def _reply(data: Any, started: float, attempts: int) -> Reply:
        """A chat completion body -> Reply; ValueError when its shape is not one (retried like a bad body)."""
        if not isinstance(data, dict):
            raise ValueError(f"expected a JSON object, got {type(data).__name__}")
        choices = data.get("choices")
        choice = choices[0] if isinstance(choices, list) and choices else None
        if not isinstance(choice, dict):
            raise ValueError("no choices[0] object")
        raw_message = choice.get("message")
        message: dict[str, Any] = raw_message if isinstance(raw_message, dict) else {}
        content = message.get("content")
        if isinstance(content, list):  # content parts: keep the text ones
            content = "".join(str(p.get("text", "")) for p in content if isinstance(p, dict))
        elif content is not None and not isinstance(content, str):
            content = str(content)
        raw_usage = data.get("usage")
        usage: dict[str, Any] = raw_usage if isinstance(raw_usage, dict) else {}
        reason = choice.get("finish_reason")
        return Reply(text=content, finish_reason=reason if isinstance(reason, str) else None,
                     prompt_tokens=_count(usage.get("prompt_tokens")), completion_tokens=_count(usage.get("completion_tokens")),
                     latency_s=round(time.monotonic() - started, 4), attempts=attempts, raw=data)


def _count(value: Any) -> int | None:
    try:
        return None if value is None else max(0, int(value))
    except (TypeError, ValueError):
        return None
