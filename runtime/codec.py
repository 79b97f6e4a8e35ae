"""msgpack (and JSON) encoding of the wire messages, and image encoding helpers.

``encode`` writes a message (a struct of :mod:`agos.runtime.schemas`) as a plain msgpack map: the
``type`` tag first, then the fields in declaration order; bytes stay raw bytes, tuples become
arrays, numpy scalars and arrays become numbers and lists. ``decode`` reads any agos payload
into its struct, dispatching on ``type`` through :data:`~agos.runtime.schemas.WireMessage`;
``decode_as`` reads a payload of one known type. Both check every value while reading, in C, and
raise :class:`DecodeError` naming the field. msgspec does all of it; msgpack-python reads the
payloads into the same maps (tests/test_codec.py).
"""

from __future__ import annotations

import re
import threading
from typing import Any, TypeVar

import cv2
import msgspec
import numpy as np

from agos.runtime.schemas import SCHEMA_VERSION, WireMessage

T = TypeVar("T")


class DecodeError(ValueError):
    """A payload that is not a valid agos message; the text names the field."""


class WireVersionError(DecodeError):
    """A live message of another wire schema version than this process's (``schemas.SCHEMA_VERSION``):
    the text names both, and what to do."""

    def __init__(self, version: object) -> None:
        super().__init__(f"wire schema version {version!r}, this process speaks version {SCHEMA_VERSION}: "
                         "run one agos version in every process of a run")
        self.version = version


class _Versioned(msgspec.Struct):
    """Only the ``v`` of any map (other fields ignored): why a payload that failed to decode failed."""

    v: object = None


def _live(message: T) -> T:
    """``message`` if it is of this process's schema version (anything without a ``v`` passes)."""
    version = getattr(message, "v", SCHEMA_VERSION)
    if version != SCHEMA_VERSION:
        raise WireVersionError(version)
    return message


def _other_version(payload: bytes | bytearray | memoryview) -> WireVersionError | None:
    """For a payload that did not decode: a :class:`WireVersionError` when it says another version."""
    try:
        version = _decoder(_Versioned).decode(payload).v
    except (ValueError, RecursionError):
        return None
    return WireVersionError(version) if version is not None and version != SCHEMA_VERSION else None


def _plain(value: Any) -> Any:
    """What msgspec cannot write itself: numpy scalars as numbers, numpy arrays as lists."""
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    raise NotImplementedError(f"cannot encode a {type(value).__name__}")


_ENCODER = msgspec.msgpack.Encoder(enc_hook=_plain)
_JSON_ENCODER = msgspec.json.Encoder(enc_hook=_plain)


def encode(message: Any) -> bytes:
    """A message (or any plain value) as msgpack bytes."""
    return _ENCODER.encode(message)


def encode_into(message: Any, buffer: bytearray) -> None:
    """:func:`encode` into ``buffer`` (replacing its content): a sender that puts the payload at
    once reuses one buffer instead of allocating one per message."""
    _ENCODER.encode_into(message, buffer)


_DECODERS: dict[tuple[str, Any], Any] = {}
_MAKING_DECODERS = threading.Lock()


def _decoder(kind: Any, syntax: str = "msgpack") -> Any:
    """The msgspec decoder of ``kind`` for ``syntax`` (``msgpack`` or ``json``), made once. Made under
    a lock: msgspec (0.22) fills in the type information of the structs while it makes a decoder, and
    two threads doing so at once for the same structs crashed the process (a segmentation fault in
    the human console, whose two subscriber threads decoded their first observations together; 47
    processes in 400 when six threads decode their first message at once). Using a decoder needs no
    lock. The decoders made at import elsewhere (runtime/viz.py, world/episodes/files.py) are not
    covered: they are made when their module is first imported."""
    found = _DECODERS.get((syntax, kind))
    if found is None:
        with _MAKING_DECODERS:
            found = _DECODERS.get((syntax, kind))
            if found is None:
                found = _DECODERS[(syntax, kind)] = (msgspec.msgpack if syntax == "msgpack" else msgspec.json).Decoder(kind)
    return found


def decode(payload: bytes | bytearray | memoryview) -> WireMessage:
    """Any agos payload from the bus as the message its ``type`` names; a message of another schema
    version raises :class:`WireVersionError`."""
    try:
        message = _decoder(WireMessage).decode(payload)  # the union of the tagged structs: one C pass
    except (ValueError, RecursionError) as exc:  # msgspec's errors, a bad UTF-8 string, nesting too deep
        raise _other_version(payload) or _error(exc, "msgpack") from None
    return _live(message)


def decode_as(payload: bytes | bytearray | memoryview, kind: type[T]) -> T:
    """A payload from the bus of a known message type (or any type msgspec reads) as that type; a
    message of another schema version raises :class:`WireVersionError`."""
    try:
        message = _decoder(kind).decode(payload)
    except (ValueError, RecursionError) as exc:
        raise _other_version(payload) or _error(exc, "msgpack") from None
    return _live(message)


def to_json(message: Any) -> bytes:
    """A message as JSON (records in result files, episode specs in split files)."""
    return _JSON_ENCODER.encode(message)


def from_json(data: bytes | str, kind: type[T]) -> T:
    """JSON of a known message type as that type; :class:`DecodeError` names the field. Stored
    messages of every version in ``schemas.SchemaVersion`` read (older records, split files)."""
    try:
        return _decoder(kind, "json").decode(data)
    except (ValueError, RecursionError) as exc:
        raise _error(exc, "JSON") from None


_AT = re.compile(r" - at `\$(?P<path>[^`]*)`$")
_NAMED = re.compile(r"^Object (?:missing required|contains unknown) field `(?P<name>[^`]*)`")


def field_path(exc: msgspec.ValidationError) -> tuple[str, str]:
    """(field, message) of a msgspec validation error: ``$.candidates[1].cell`` as
    ``candidates.1.cell``; for a missing or unknown field, the field itself."""
    text = str(exc)
    found = _AT.search(text)
    message = text[:found.start()] if found else text
    path = found.group("path") if found else ""
    path = re.sub(r"\[(\d+)\]", r".\1", path).lstrip(".")
    named = _NAMED.match(message)
    if named:
        path = f"{path}.{named.group('name')}" if path else named.group("name")
    return path, message


def _error(exc: BaseException, what: str) -> DecodeError:
    if isinstance(exc, msgspec.ValidationError):
        path, message = field_path(exc)
        if not path and message.startswith("Expected `object`"):
            return DecodeError(f"payload is not a {what} map ({message})")
        return DecodeError(f"field {path or '<root>'}: {message}")
    if isinstance(exc, RecursionError) or "recursion limit" in str(exc):
        return DecodeError(f"payload is not {what}: nested too deeply")
    return DecodeError(f"payload is not {what}: {exc}")


def encode_png(image: np.ndarray) -> bytes:
    """PNG bytes of an RGB (HxWx3), RGBA (HxWx4), uint8 or uint16 (HxW) image."""
    ok, buf = cv2.imencode(".png", _to_bgr(image))
    if not ok:
        raise ValueError("PNG encoding failed")
    return buf.tobytes()


def encode_jpeg(image: np.ndarray, quality: int = 90) -> bytes:
    """JPEG bytes of an RGB uint8 image."""
    ok, buf = cv2.imencode(".jpg", _to_bgr(image), [cv2.IMWRITE_JPEG_QUALITY, quality])
    if not ok:
        raise ValueError("JPEG encoding failed")
    return buf.tobytes()


def decode_image(data: bytes) -> np.ndarray:
    """Decode PNG or JPEG bytes into RGB / RGBA uint8 or single-channel uint8/uint16 arrays."""
    image = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED) if data else None
    if image is None:
        raise ValueError("image bytes could not be decoded")
    if image.ndim == 3 and image.shape[2] == 3:
        return cv2.cvtColor(image, cv2.COLOR_BGR2RGB)
    if image.ndim == 3 and image.shape[2] == 4:
        return cv2.cvtColor(image, cv2.COLOR_BGRA2RGBA)
    return image


def _to_bgr(image: np.ndarray) -> np.ndarray:
    if image.ndim == 3 and image.shape[2] == 3:
        return cv2.cvtColor(image, cv2.COLOR_RGB2BGR)
    if image.ndim == 3 and image.shape[2] == 4:
        return cv2.cvtColor(image, cv2.COLOR_RGBA2BGRA)
    return image
