"""The visualisation stream: what observers watch, published so that they can never slow the world.

The world worker mirrors what a viewer needs under ``agos/<run>/viz/<worker>/`` (runtime/keys.py: the
key names the world worker's slot, never the episode; every payload names its episode in
``episode_id``, and one slot carries its worker's episodes one after the other):
``events`` (``EpisodeStarted`` and every ``StepEvent``: applied action, pose, oracle flags),
``coord`` (the coordination truth: candidates, poses, budget), ``frame/<role>`` (one
:class:`VizFrame` per RGB view of an observation: a JPEG of at most ``THUMB_PX`` pixels a side, a few
KB), ``spec`` (the episode spec, at its start) and ``result`` (a copy of the record, at its end).
``full/<role>`` carries the views at full resolution (:func:`full_frames`), made only while
something subscribes to that key (``agos record --full``). All of it goes out with congestion
control DROP, express and low priority (``ZenohBus.publish_viz``): a slow or stuck observer loses
samples, the world never waits for it. Control traffic (``slot/<worker>/...``) stays reliable with BLOCK for
those that must not miss anything (evaluator, orchestrator, agents).

A viewer follows one episode by the payload's ``episode_id`` (:func:`episode_of_payload` reads just
that field), not by the key: a frame of the worker's next episode may arrive on the same key right
after the previous episode's record.

Frames are made on a background thread from the latest observation only (:class:`FrameStream`;
OpenCV releases the GIL), and only while someone subscribes to them, so even an attached viewer
costs the decision loop next to nothing.
"""

from __future__ import annotations

import logging
import threading
from typing import TYPE_CHECKING, Any

import cv2
import msgspec
import numpy as np

from agos.runtime.codec import decode
from agos.runtime.schemas import CameraIntrinsics, ImageFrame, Observation, VizFrame

if TYPE_CHECKING:
    from agos.runtime.bus import Bus

log = logging.getLogger(__name__)
THUMB_PX = 160
"""Longest side of a frame on the visualisation stream."""
JPEG_QUALITY = 70
MIN_INTERVAL_S = 0.1
"""At most one frame per this much wall time from one worker (both roles together)."""


def decode_viz(payload: bytes) -> Any:
    """Any payload of the visualisation stream (the same decoder as every other message)."""
    return decode(payload)


class _Episode(msgspec.Struct):
    """Only the ``episode_id`` of a message (every other field skipped unread)."""

    episode_id: str | None = None


_EPISODE = msgspec.msgpack.Decoder(_Episode)


def episode_of_payload(payload: bytes | bytearray | memoryview) -> str | None:
    """The ``episode_id`` a payload names, without decoding the rest of it (an image's bytes are
    skipped): None for a payload that names none, or is not a msgpack map. Not a check of the
    message: what it returns may still be no valid id (``keys.check_chunk``)."""
    try:
        return _EPISODE.decode(payload).episode_id
    except (ValueError, RecursionError):  # not msgpack, not a map, an episode_id that is not a string
        return None


def thumbnail(obs: Observation, size_px: int = THUMB_PX) -> VizFrame | None:
    """The observation's first RGB view (UAV nadir, UGV forward or first of six), scaled down."""
    frame = next((f for f in obs.images if f.kind == "rgb"), None)
    return None if frame is None else _thumbnail(obs, frame, size_px)


def thumbnails(obs: Observation, size_px: int = THUMB_PX) -> list[VizFrame]:
    """Every RGB view of the observation (the six views at a STOP_OBSERVE), scaled down."""
    frames = (_thumbnail(obs, f, size_px) for f in obs.images if f.kind == "rgb")
    return [f for f in frames if f is not None]


def full_frames(obs: Observation) -> list[VizFrame]:
    """Every RGB view of the observation as the agent got it (``viz/<worker>/full/<role>``): no decoding,
    the frames share the observation's bytes."""
    return [_viz_frame(obs, f) for f in obs.images if f.kind == "rgb"]


def _viz_frame(obs: Observation, image: ImageFrame) -> VizFrame:
    return VizFrame(run_id=obs.run_id, episode_id=obs.episode_id, role=obs.role, decision_index=obs.decision_index,
                    sim_time_s=obs.sim_time_s, pose=obs.pose, image=image)


def _thumbnail(obs: Observation, frame: ImageFrame, size_px: int) -> VizFrame | None:
    side = max(frame.intrinsics.width_px, frame.intrinsics.height_px) if frame.intrinsics else 0
    reduce = next((n for n in (8, 4, 2) if side // n >= size_px), 1)  # JPEG decodes at 1/n for nearly free
    flag = {8: cv2.IMREAD_REDUCED_COLOR_8, 4: cv2.IMREAD_REDUCED_COLOR_4, 2: cv2.IMREAD_REDUCED_COLOR_2}.get(
        reduce, cv2.IMREAD_COLOR)
    bgr = cv2.imdecode(np.frombuffer(frame.data, np.uint8), flag)
    if bgr is None:
        return None
    scale = size_px / max(bgr.shape[:2])
    if scale < 1.0:
        bgr = cv2.resize(bgr, (max(1, round(bgr.shape[1] * scale)), max(1, round(bgr.shape[0] * scale))),
                         interpolation=cv2.INTER_AREA)
    ok, jpeg = cv2.imencode(".jpg", bgr, [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY])
    if not ok:
        return None
    return _viz_frame(obs, ImageFrame(name=frame.name, kind="rgb", encoding="jpeg", data=jpeg.tobytes(),
                                      intrinsics=_scaled(frame.intrinsics, bgr.shape[1], bgr.shape[0]),
                                      world_from_camera=frame.world_from_camera))


def _scaled(k: CameraIntrinsics | None, width_px: int, height_px: int) -> CameraIntrinsics | None:
    """The intrinsics of the same camera at ``width_px`` x ``height_px`` (a thumbnail: MCAP recordings
    give them as its CameraInfo)."""
    if k is None or not k.width_px or not k.height_px:
        return None
    sx, sy = width_px / k.width_px, height_px / k.height_px
    return CameraIntrinsics(width_px=width_px, height_px=height_px, fx_px=k.fx_px * sx, fy_px=k.fy_px * sy,
                            cx_px=k.cx_px * sx, cy_px=k.cy_px * sy)


class FrameStream:
    """Publishes thumbnails of observations on ``viz/<worker>/frame/<role>`` from a background thread.

    :meth:`offer` costs the caller a subscription check and a dict store: nothing when nobody
    watches; otherwise only the latest observation per key waits, older ones are skipped, and
    frames are made at most every ``min_interval_s``, so watching costs a bounded share of a core.
    """

    def __init__(self, bus: Bus, min_interval_s: float = MIN_INTERVAL_S) -> None:
        self.bus, self.min_interval_s = bus, min_interval_s
        self._pending: dict[str, Observation] = {}
        self._busy = False
        self._closed = False
        self._cond = threading.Condition()
        self._thread: threading.Thread | None = None

    def offer(self, key: str, obs: Observation) -> None:
        if not self.bus.watched(key):
            return
        with self._cond:
            if self._closed:
                return
            self._pending[key] = obs
            if self._thread is None:
                self._thread = threading.Thread(target=self._run, name="viz-frames", daemon=True)
                self._thread.start()
            self._cond.notify()

    def forget(self, key_prefix: str) -> None:
        """Drop what waits under ``key_prefix`` and wait for a frame in flight (a slot is given up)."""
        with self._cond:
            for key in [k for k in self._pending if k.startswith(key_prefix)]:
                del self._pending[key]
            self._cond.wait_for(lambda: not self._busy, timeout=5.0)

    def close(self) -> None:
        with self._cond:
            self._closed = True
            self._pending.clear()
            self._cond.notify_all()
        if self._thread is not None:
            self._thread.join(timeout=5.0)

    def _run(self) -> None:
        while True:
            with self._cond:
                self._cond.wait_for(lambda: self._pending or self._closed)
                if self._closed:
                    return
                key, obs = self._pending.popitem()
                self._busy = True
            try:
                for frame in thumbnails(obs):
                    self.bus.publish_viz(key, frame)
            except Exception:  # a visualisation problem must never touch the episode
                log.debug("frame for %s not published", key, exc_info=True)
            finally:
                with self._cond:
                    self._busy = False
                    self._cond.notify_all()
                    self._cond.wait_for(lambda: self._closed, timeout=self.min_interval_s)
