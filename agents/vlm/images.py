"""The images a VLM policy sends, sized and encoded as ``[vlm] image_max_px`` and ``jpeg_quality`` say:
the lever on what a decision's request weighs on the link to the model (docs/COMMS.md, "The link to
the model").

:func:`as_sent` returns the observation with every image the prompt may send (camera views, the
grid view, the map, the target's references, the teammate's top view) shrunk so that its longest
side is at most ``image_max_px`` (area averaging) and/or re-encoded as JPEG at ``jpeg_quality``; the
camera intrinsics and the metres per pixel of a shrunk image are scaled with it, so the prompt's
numbers still describe the pixels sent. An image with transparency (the target's references, whose
background is see-through) is only shrunk, and stays PNG: JPEG cannot carry it. Depth and semantic
images are never sent and stay as they are. With both settings None (the default) the observation
is returned unchanged, so requests, and the replay cache's keys (which hash the images' bytes), are
those of before; a change of either setting changes every key it touches.
"""

from __future__ import annotations

import cv2
import msgspec

from agos.runtime.codec import decode_image, encode_jpeg, encode_png
from agos.runtime.schemas import CameraIntrinsics, ImageFrame, Observation

SENT_KINDS = frozenset({"rgb", "rgb_grid", "map"})


def as_sent(obs: Observation, max_px: int | None, jpeg_quality: int | None) -> Observation:
    """``obs`` with its images as the model is to be sent them (see the module)."""
    if max_px is None and jpeg_quality is None:
        return obs

    def one(frame: ImageFrame) -> ImageFrame:
        return sized(frame, max_px, jpeg_quality)

    teammate = obs.teammate_reference
    return msgspec.structs.replace(obs, images=[one(f) for f in obs.images], references=[one(f) for f in obs.references],
                                   teammate_reference=None if teammate is None else one(teammate))


def sized(frame: ImageFrame, max_px: int | None, jpeg_quality: int | None) -> ImageFrame:
    """One image shrunk to ``max_px`` on its longest side and/or re-encoded as JPEG at ``jpeg_quality``
    (None: as it is); a frame of another kind, or that needs neither, is returned as it is."""
    if frame.kind not in SENT_KINDS:
        return frame
    image = decode_image(frame.data)
    h, w = image.shape[:2]
    scale = min(1.0, max_px / max(h, w)) if max_px is not None else 1.0
    if scale >= 1.0 and jpeg_quality is None:
        return frame
    intrinsics, metres_per_px = frame.intrinsics, frame.metres_per_px
    if scale < 1.0:
        nw, nh = max(1, round(w * scale)), max(1, round(h * scale))
        image = cv2.resize(image, (nw, nh), interpolation=cv2.INTER_AREA)
        sx, sy = nw / w, nh / h
        if intrinsics is not None:
            intrinsics = CameraIntrinsics(width_px=nw, height_px=nh, fx_px=intrinsics.fx_px * sx, fy_px=intrinsics.fy_px * sy,
                                          cx_px=intrinsics.cx_px * sx, cy_px=intrinsics.cy_px * sy)
        if metres_per_px is not None:
            metres_per_px = metres_per_px / sx
    alpha = image.ndim == 3 and image.shape[2] == 4
    if jpeg_quality is not None and (not alpha or frame.kind == "map"):  # the map's alpha carries nothing (request.py)
        data, encoding = encode_jpeg(image[:, :, :3] if alpha else image, quality=jpeg_quality), "jpeg"
    elif frame.encoding == "jpeg":
        data, encoding = encode_jpeg(image), "jpeg"  # the renderer's own quality (runtime/codec.py's default)
    else:
        data, encoding = encode_png(image), "png"
    return msgspec.structs.replace(frame, data=data, encoding=encoding, intrinsics=intrinsics, metres_per_px=metres_per_px)
