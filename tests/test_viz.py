"""The visualisation stream's frames (agos/runtime/viz.py); the e2e proof that observers on it
cannot slow the world is in test_e2e_faults.py."""

from __future__ import annotations

import msgspec
import numpy as np

from agos.runtime import keys
from agos.runtime.bus import Inbox, MemoryBus
from agos.runtime.codec import decode_image, encode, encode_jpeg, encode_png
from agos.runtime.schemas import CameraIntrinsics, CoordinationState, ImageFrame, Observation, Pose
from agos.runtime.viz import THUMB_PX, FrameStream, VizFrame, decode_viz, episode_of_payload, thumbnail


def _obs(encoding: str = "jpeg", size: int = 512) -> Observation:
    rgb = np.zeros((size, size, 3), np.uint8)
    rgb[: size // 2, :, 0] = 255  # red top half, so orientation and colour survive
    data = encode_jpeg(rgb) if encoding == "jpeg" else encode_png(rgb)
    intr = CameraIntrinsics(width_px=size, height_px=size, fx_px=400.0, fy_px=400.0, cx_px=size / 2, cy_px=size / 2)
    frames = [ImageFrame(name="nadir", kind="depth", encoding="png", data=encode_png(np.zeros((4, 4), np.uint16))),
              ImageFrame(name="nadir", kind="rgb", encoding=encoding, data=data, intrinsics=intr,
                         world_from_camera=[float(i) for i in range(16)])]
    pose = Pose(position_world_m=(1.0, 2.0, 80.0), yaw_rad=0.0)
    return Observation(run_id="r", episode_id="e", role="uav", decision_index=4, sim_time_s=30.0, pose=pose,
                       mode="aerial", images=frames, references=[], legal_actions=["WAIT"], waypoint_options=[],
                       region_world_m=(0.0, 0.0, 1.0, 1.0),
                       coordination=CoordinationState(run_id="r", episode_id="e", sim_time_s=30.0))


def test_thumbnail_is_small_and_true() -> None:
    for encoding, size in (("jpeg", 512), ("png", 300), ("jpeg", 100)):
        frame = thumbnail(_obs(encoding, size))
        assert frame is not None and frame.role == "uav" and frame.decision_index == 4
        image = decode_image(frame.image.data)
        assert max(image.shape[:2]) == min(size, THUMB_PX)
        assert image[2, 2, 0] > 200 and image[-3, 2, 0] < 50  # red on top
        assert frame.image.world_from_camera == [float(i) for i in range(16)]
        assert len(encode(frame)) < 8000
        assert decode_viz(encode(frame)) == frame


def test_no_rgb_view_no_frame() -> None:
    obs = _obs()
    assert thumbnail(msgspec.structs.replace(obs, images=obs.images[:1])) is None


def test_decode_viz_reads_other_messages() -> None:
    state = CoordinationState(run_id="r", episode_id="e", sim_time_s=1.0)
    assert decode_viz(encode(state)) == state


def test_episode_of_payload_reads_the_episode_alone() -> None:
    """Keys name world workers, not episodes: a viewer follows an episode by the payload's field."""
    frame = thumbnail(_obs())
    assert frame is not None and episode_of_payload(encode(frame)) == "e"
    assert episode_of_payload(encode(CoordinationState(run_id="r", episode_id="e2", sim_time_s=1.0))) == "e2"
    assert episode_of_payload(msgspec.msgpack.encode({"type": "run_manifest", "run_id": "r"})) is None
    for bad in (b"\x93garbage", b"", msgspec.msgpack.encode([1, 2]), msgspec.msgpack.encode({"episode_id": 7})):
        assert episode_of_payload(bad) is None


def test_frame_stream_makes_frames_only_for_someone() -> None:
    bus = MemoryBus()
    stream = FrameStream(bus, min_interval_s=0.0)
    key = keys.viz_frame("r", "w", "uav")
    stream.offer(key, _obs())  # nobody watches: nothing made, no thread
    assert stream._thread is None and not bus.published
    inbox = Inbox()
    bus.subscribe(keys.viz_all(), inbox)
    stream.offer(key, _obs())
    sample = inbox.get(5.0)
    assert sample is not None and sample.key == key
    assert isinstance(decode_viz(sample.payload), VizFrame)
    stream.forget(key)
    stream.close()
