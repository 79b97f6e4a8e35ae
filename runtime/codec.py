"""msgpack encoding of the wire messages, and image encoding helpers.

``encode`` writes a model as a plain msgpack map (bytes stay raw bytes, tuples become arrays);
``decode`` reads any agos payload back into its model through one discriminated union.
"""

from __future__ import annotations

from typing import Any

import cv2
import msgpack
import numpy as np
from pydantic import TypeAdapter, ValidationError

from agos.runtime.schemas import WireMessage

_ADAPTER: TypeAdapter[Any] = TypeAdapter(WireMessage)


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
