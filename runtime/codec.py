"""msgpack encoding of the wire messages, and image encoding helpers.

``encode`` writes a model as a plain msgpack map (bytes stay raw bytes, tuples become arrays);
``decode`` reads any agos payload back into its model through one discriminated union.

:class:`Encoder` and :class:`Decoder` do the same for a stream of messages on the decision hot
path: the parts of an observation that stay the same over an episode (``REPEATED``: reference
views, the searchable area) are packed and validated once, not every decision. Their payloads are
the same msgpack maps (field order aside), so ``decode`` reads them and they read ``encode``'s.
"""

from __future__ import annotations

from typing import Any, get_args

import cv2
import msgpack
import numpy as np
from pydantic import TypeAdapter, ValidationError

from agos.runtime.schemas import WireMessage

_ADAPTER: TypeAdapter[Any] = TypeAdapter(WireMessage)
_MODELS = {model.model_fields["type"].default: model for model in get_args(get_args(WireMessage)[0])}

REPEATED: dict[str, tuple[str, ...]] = {"observation": ("references", "active_uav_waypoints")}
"""Top-level fields, per message ``type``, that usually repeat unchanged within an episode."""
_REPEATED_NAMES = frozenset(name for names in REPEATED.values() for name in names)


class DecodeError(ValueError):
    """A payload that is not a valid agos message; the text names the field."""


def encode(message: Any) -> bytes:
    """Serialize a wire model to msgpack bytes."""
    return msgpack.packb(message.model_dump(mode="python"), use_bin_type=True)


def decode(payload: bytes) -> Any:
    """Parse msgpack bytes into the wire model named by its ``type``."""
    try:
        data = msgpack.unpackb(payload, raw=False)
    except (ValueError, msgpack.ExtraData, msgpack.FormatError, msgpack.StackError) as exc:
        raise DecodeError(f"payload is not msgpack: {exc}") from exc
    if not isinstance(data, dict):
        raise DecodeError("payload is not a msgpack map")
    try:
        return _ADAPTER.validate_python(data)
    except ValidationError as exc:
        first = exc.errors()[0]
        where = ".".join(str(p) for p in first["loc"]) or "<root>"
        raise DecodeError(f"field {where}: {first['msg']} (type={data.get('type')!r})") from exc


class Encoder:
    """``encode`` for one sender's stream: a ``REPEATED`` field equal to the one last sent (the
    same objects, else ``==``) reuses its packed bytes instead of being dumped and packed again."""

    def __init__(self) -> None:
        self._packed: dict[tuple[str, str], tuple[Any, bytes]] = {}

    def encode(self, message: Any) -> bytes:
        fields = REPEATED.get(getattr(message, "type", ""), ())
        if not fields:
            return encode(message)
        parts = []
        for name in fields:
            value = getattr(message, name)
            hit = self._packed.get((message.type, name))
            if hit is None or not _same(value, hit[0]):
                dumped = message.model_dump(mode="python", include={name})[name]
                snapshot = list(value) if isinstance(value, list) else value
                hit = (snapshot, msgpack.packb(name) + msgpack.packb(dumped, use_bin_type=True))
                self._packed[(message.type, name)] = hit
            parts.append(hit[1])
        body = msgpack.packb(message.model_dump(mode="python", exclude=set(fields)), use_bin_type=True)
        size = _MAP_HEADER_SIZE[body[0] >> 4 if body[0] < 0x90 else body[0]]
        count = int.from_bytes(body[1:size], "big") if size > 1 else body[0] & 0x0F
        return b"".join([_map_header(count + len(parts)), memoryview(body)[size:], *parts])


_MAP_HEADER_SIZE = {0x8: 1, 0xDE: 3, 0xDF: 5}


def _map_header(count: int) -> bytes:
    if count < 16:
        return bytes([0x80 | count])
    return b"\xde" + count.to_bytes(2, "big") if count < 1 << 16 else b"\xdf" + count.to_bytes(4, "big")


def _same(value: Any, snapshot: Any) -> bool:
    """``value == snapshot``, quicker for lists of models (the fields of a model are its ``__dict__``)."""
    if isinstance(value, list):
        return len(value) == len(snapshot) and all(
            a is b or (type(a) is type(b) and getattr(a, "__dict__", a) == getattr(b, "__dict__", b))
            for a, b in zip(value, snapshot, strict=True))
    return value is snapshot or value == snapshot


class Decoder:
    """``decode`` for one receiver's stream: a ``REPEATED`` field whose bytes equal those last seen
    for the same episode is not unpacked and validated again; its validated value is reused.

    Decoded messages may therefore share those parts (the same model objects) with earlier ones:
    treat them as read-only. Anything unusual (not a map, an error) goes through :func:`decode`,
    so errors read the same. ``capacity`` bounds the cache (oldest episode entries dropped).
    """

    def __init__(self, capacity: int = 256) -> None:
        self.capacity = capacity
        self._seen: dict[tuple[str, str, str], tuple[bytes, Any]] = {}

    def decode(self, payload: bytes) -> Any:
        try:
            data, raws = self._unpack(payload)
            kind = data.get("type")
            model = _MODELS.get(kind) if isinstance(kind, str) else None
            if model is None:
                raise ValueError("not a known type")
        except Exception:
            return decode(payload)  # the canonical result or error
        episode = str(data.get("episode_id"))
        fresh = []
        for name, raw in raws.items():
            hit = self._seen.get((kind, episode, name)) if name in REPEATED.get(kind, ()) else None
            if hit is not None and hit[0] == raw:
                data[name] = hit[1]
            else:
                data[name] = msgpack.unpackb(raw, raw=False)
                fresh.append((name, raw))
        try:
            message = model.model_validate(data)
        except ValidationError:
            return decode(payload)
        for name, raw in fresh:
            if name in REPEATED.get(kind, ()):
                self._remember((kind, episode, name), raw, getattr(message, name))
        return message

    def forget(self, episode_id: str) -> None:
        for key in [k for k in self._seen if k[1] == episode_id]:
            del self._seen[key]

    def _remember(self, key: tuple[str, str, str], raw: bytes, value: Any) -> None:
        self._seen.pop(key, None)
        self._seen[key] = (raw, value)
        while len(self._seen) > self.capacity:
            del self._seen[next(iter(self._seen))]

    @staticmethod
    def _unpack(payload: bytes) -> tuple[dict[str, Any], dict[str, bytes]]:
        """The top-level map, with the repeatable fields left as raw bytes."""
        unpacker = msgpack.Unpacker(raw=False, max_buffer_size=max(len(payload), 1))
        unpacker.feed(payload)
        data: dict[str, Any] = {}
        raws: dict[str, bytes] = {}
        for _ in range(unpacker.read_map_header()):
            name = unpacker.unpack()
            if name in _REPEATED_NAMES:
                start = unpacker.tell()
                unpacker.skip()
                raws[name] = payload[start:unpacker.tell()]
            else:
                data[name] = unpacker.unpack()
        if unpacker.tell() != len(payload):
            raise ValueError("extra data after the map")
        return data, raws


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
