"""What the stand-in accepts: a chat-completion body validated the way vLLM would, and its token count.

:func:`parse_chat_body` refuses a bad body with a :class:`RequestError` (HTTP status and OpenAI's error
object); ``usage.prompt_tokens`` is estimated as text characters / 4 plus, per image, one token per
28x28 pixels (each side rounded to a multiple of 28, as Qwen2.5-VL does).
"""

from __future__ import annotations

import base64
import binascii
import json
import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from agos.agents.vlm.standin.schema import SchemaError, check_schema

if TYPE_CHECKING:
    from agos.agents.vlm.protocol import SplitRequest

TOKEN_PIXELS = 28
MAX_CHOICES = 128
"""The largest ``n`` (OpenAI's limit)."""


class RequestError(Exception):
    """A request the server refuses: HTTP status and an OpenAI error body (``type``, a string or null ``code``)."""

    def __init__(self, status: int, message: str, *, kind: str = "invalid_request_error", code: str | None = None,
                 param: str | None = None) -> None:
        super().__init__(message)
        self.status, self.message, self.kind, self.code, self.param = status, message, kind, code, param

    def body(self) -> dict[str, Any]:
        return error_body(self.message, self.kind, self.code, self.param)


def error_body(message: str, kind: str, code: str | None = None, param: str | None = None) -> dict[str, Any]:
    """OpenAI's error object: ``type`` as OpenAI names it (``invalid_request_error``, ``authentication_error``,
    ``rate_limit_error``, ``server_error``), ``code`` a string or null."""
    return {"error": {"message": message, "type": kind, "param": param, "code": code}}


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
    n: int = 1
    """Choices asked for (``n``)."""
    strict_schema: dict[str, Any] | bool | None = None
    """The schema of a ``json_schema`` response format with ``strict: true`` (checked against the subset of
    :mod:`~agos.agents.vlm.standin.schema`): every answer must conform to it, or the request is refused."""

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
                           code="model_not_found", param="model")
    return model


def _structured(body: dict[str, Any]) -> tuple[bool, dict[str, Any] | bool | None]:
    """Whether the answer must be plain JSON, and the strict schema it must conform to (None: not strict)."""
    fmt = body.get("response_format")
    if fmt is None:
        return False, None
    kind = fmt.get("type") if isinstance(fmt, dict) else None
    if kind not in ("text", "json_object", "json_schema"):
        raise RequestError(400, "'response_format.type' must be one of text, json_object, json_schema", param="response_format")
    if kind != "json_schema":
        return kind == "json_object", None
    spec = fmt.get("json_schema")
    if not isinstance(spec, dict):
        raise RequestError(400, "'response_format.json_schema' must be an object", param="response_format")
    if not spec.get("strict"):
        return True, None
    schema = spec.get("schema")
    try:
        check_schema(schema, "response_format.json_schema.schema")
    except SchemaError as exc:
        raise RequestError(400, f"Invalid schema for response_format {spec.get('name', '')!r}: {exc}",
                           param="response_format") from None
    return True, schema


def _choices(body: dict[str, Any]) -> int:
    n = body.get("n", 1)
    if n is None:
        return 1
    if not isinstance(n, int) or isinstance(n, bool) or not 1 <= n <= MAX_CHOICES:
        raise RequestError(400, f"'n' must be an integer from 1 to {MAX_CHOICES}, not {n!r}", param="n")
    return n


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
    (structured, strict_schema), max_tokens, n = _structured(body), _max_tokens(body), _choices(body)
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
    return ChatRequest(body, model, messages, structured, max_tokens, chars, tuple(sizes), n, strict_schema)


def split_messages(chat: ChatRequest) -> SplitRequest:
    """The request as the responder sees it (:func:`~agos.agents.vlm.protocol.split_request`); 400 when
    agos's layout is broken (e.g. the STATE line is not JSON)."""
    from agos.agents.vlm.protocol import split_request

    try:
        return split_request(chat.messages)
    except (ValueError, binascii.Error) as exc:
        raise RequestError(400, f"cannot read the request layout: {exc}", param="messages") from None
