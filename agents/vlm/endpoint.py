"""What an OpenAI-compatible endpoint's failure means, as one line that says what to change.

:class:`~agos.agents.vlm.client.VlmClient` raises these lines (in a ``VlmError`` whose ``kind`` is one
of :data:`KINDS`) from its preflight, and for 401/403 answers to any request; ``agos eval``/``demo``/
``sweep`` print them before any process starts (deploy/run/plan.py), an agent service logs them.

* ``refused``: nothing listens on the host and port (connection refused);
* ``unreachable``: the host name does not resolve, the network or host cannot be reached, or the
  server closed the connection without an HTTP answer (TLS to a plain-HTTP port, the wrong scheme);
* ``timeout``: no connection, or no answer, within the timeout;
* ``auth``: 401/403, naming the API-key variable and whether it is set;
* ``model``: the endpoint answers but does not list the model (the line lists what it serves);
* ``http``: any other answer that is not a model list (a 404 names the usual ``/v1`` suffix).
* ``outage``: a chat request got no answer after the client's retries (connection errors, timeouts,
  408/409/429/5xx): the episode pauses instead of scoring a WAIT (agents/contract.py::EndpointOutage).

No line ever holds the API key: callers redact the server's text before it is quoted here.
"""

from __future__ import annotations

import socket
from http import HTTPStatus
from typing import Any
from urllib.parse import urlsplit

import httpx

KINDS = ("refused", "unreachable", "timeout", "auth", "model", "http", "outage")
QUOTED_CHARS = 160
"""At most this much of a server's own error message is quoted in a line."""


def _address(url: str) -> tuple[str, str]:
    """(host, host:port) of a base URL, the port defaulted by the scheme."""
    parts = urlsplit(url)
    host = parts.hostname or "?"
    try:
        port = parts.port or (443 if parts.scheme == "https" else 80)
    except ValueError:
        return host, parts.netloc
    return host, f"{host}:{port}"


def _os_error(exc: BaseException) -> OSError | None:
    """The operating system's error under an httpx exception: the deepest in its cause chain (anyio
    wraps a refused connection in a plain ``OSError('All connection attempts failed')``)."""
    seen: set[int] = set()
    found: OSError | None = None
    current: BaseException | None = exc
    while current is not None and id(current) not in seen:
        if isinstance(current, OSError):
            found = current
        seen.add(id(current))
        current = current.__cause__ or current.__context__
    return found


def transport_failure(url: str, exc: httpx.HTTPError, timeout_s: float, what: str = "/models") -> tuple[str, str]:
    """``(kind, line)`` for a request to ``url`` that got no HTTP answer (``exc``, after ``timeout_s``)."""
    host, where = _address(url)
    if isinstance(exc, httpx.ConnectTimeout):
        return "timeout", (f"{url}: {where} did not accept a connection within {timeout_s:g} s (a host that is down, or "
                           "a firewall dropping packets); check --vlm-base-url, or raise --vlm-timeout")
    if isinstance(exc, httpx.TimeoutException):
        return "timeout", (f"{url}: {where} accepted the connection but did not answer {what} within {timeout_s:g} s "
                           "(overloaded, or still loading the model?); raise --vlm-timeout to wait longer")
    cause = _os_error(exc)
    if isinstance(cause, ConnectionRefusedError):
        return "refused", (f"{url}: connection refused: nothing listens on {where}; start the model server there, "
                           "or fix --vlm-base-url")
    if isinstance(cause, socket.gaierror):
        return "unreachable", (f"{url}: cannot resolve the host name {host!r} ({cause.strerror or cause}); "
                               "fix --vlm-base-url")
    if isinstance(exc, httpx.ConnectError):
        reason = (cause.strerror if cause is not None and cause.strerror else str(exc)) or type(exc).__name__
        return "unreachable", f"{url}: cannot reach {where} ({reason}); check --vlm-base-url and the network"
    if isinstance(exc, httpx.RemoteProtocolError | httpx.ReadError | httpx.WriteError):
        return "unreachable", (f"{url}: {where} closed the connection without an HTTP answer ({exc or type(exc).__name__}); "
                               "is it an OpenAI-compatible server, and is the scheme (http or https) right?")
    return "http", f"{url}: {type(exc).__name__}: {exc}"


def server_message(response: httpx.Response) -> str:
    """The server's own words: OpenAI's ``error.message`` (or ``detail``/``message``), else the body's
    start; at most ``QUOTED_CHARS`` characters, on one line."""
    text = ""
    try:
        body: Any = response.json()
    except ValueError:
        body = None
    if isinstance(body, dict):
        error = body.get("error")
        found = error.get("message") if isinstance(error, dict) else error if isinstance(error, str) else None
        found = found or body.get("detail") or body.get("message")
        text = found if isinstance(found, str) else ""
    if not text:
        text = response.text
    text = " ".join(text.split())
    return text if len(text) <= QUOTED_CHARS else text[:QUOTED_CHARS - 3] + "..."


def _status(code: int) -> str:
    try:
        return f"{code} {HTTPStatus(code).phrase}"
    except ValueError:
        return str(code)


def key_failure(url: str, status: int, key_env: str, key_set: bool, said: str = "") -> str:
    """The line for a 401/403 answer: which variable the key comes from and whether it is set.
    ``said``: the server's message (already redacted), quoted when there is one."""
    quoted = f" ({said})" if said else ""
    if key_set:
        return (f"{url} answered {_status(status)}{quoted}: it refused the API key in {key_env} (set); check its "
                f"value, or name the variable that holds the right key with --vlm-api-key-env")
    return (f"{url} answered {_status(status)}{quoted}: it needs an API key and {key_env} is not set; "
            f"export {key_env}=<key>, or name the variable that holds it with --vlm-api-key-env")


def model_failure(url: str, model: str, served: list[str]) -> str:
    """The line for an endpoint that answers but does not list ``model``."""
    listed = ", ".join(served) if served else "no model at all"
    return f"{url}: model {model!r} is not served there; its /models lists: {listed}; pick one with --model"


def listing_failure(url: str, response: httpx.Response, said: str) -> str:
    """The line for a ``/models`` answer that is neither a model list nor 401/403."""
    if response.status_code == 404:
        return (f"{url}/models answered 404 Not Found: no OpenAI-compatible API at this base URL; it usually ends "
                "in /v1 (e.g. http://HOST:8000/v1)")
    if response.is_success:
        return (f"{url}/models answered {_status(response.status_code)} without a model list ({said or 'empty'}); "
                "is --vlm-base-url an OpenAI-compatible API (it usually ends in /v1)?")
    return f"{url}/models answered {_status(response.status_code)}" + (f": {said}" if said else "")
