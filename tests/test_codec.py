"""msgpack wire codec (agos/runtime/codec.py) over the schemas (agos/runtime/schemas.py)."""

from __future__ import annotations

import msgpack
import numpy as np
import pytest

from agos.runtime.codec import DecodeError, Decoder, Encoder, decode, decode_image, encode, encode_jpeg, encode_png
from agos.runtime.schemas import (
    SCHEMA_VERSION,
    Action,
    CameraIntrinsics,
    Candidate,
    CandidateOutcome,
    CoordinationState,
    EpisodeRecord,
    EpisodeSpec,
    ImageFrame,
    JobGrant,
    MessageRecord,
    Observation,
    Pose,
    TownRef,
    VehicleSpec,
    Waypoint,
)
from agos.runtime.structs import mirror, to_model

RAW = bytes(range(256)) + b"\x89PNG\r\n\x1a\n\x00\xff"  # not valid UTF-8: must stay bytes


def _action() -> Action:
    return Action(run_id="r1", episode_id="e1", role="ugv", decision_index=3, action="GO_TO_CANDIDATE",
                  candidate_id="C002", message="heading there", rationale="closest", agent_wall_latency_s=0.25)


def _record() -> EpisodeRecord:
    return EpisodeRecord(
        run_id="r1", episode_id="e1", difficulty="hard", status="finished", termination="confirmed",
        success=True, ground_observed=True, n_confirm=1, ugv_path_length_m=123.5, shortest_path_length_m=98.25,
        final_distance_m=12.0, uav_budget=80, uav_first_visible_step=4,
        candidates=[
            CandidateOutcome(candidate_id="C001", cell="B2", center_world_m=(1.5, -2.0), status="rejected",
                             distance_to_polygon_m=31.0, center_error_m=40.5),
            CandidateOutcome(candidate_id="C002", cell="C3", center_world_m=(10.0, 20.0), status="confirmed",
                             distance_to_polygon_m=0.0, center_error_m=2.5),
        ],
        decisions_uav=9, decisions_ugv=7, fallbacks=1, sim_time_s=301.5, wall_time_s=12.75,
        worker_id="w-1", town_id="grid-s7", asset_sha256="ab" * 32, seed=42, renderer="tiny", error=None,
    )


def _observation() -> Observation:
    intr = CameraIntrinsics(width_px=512, height_px=512, fx_px=443.4, fy_px=443.4, cx_px=256.0, cy_px=256.0)
    frame = ImageFrame(name="nadir", kind="rgb", encoding="png", data=RAW, intrinsics=intr,
                       world_from_camera=[float(i) for i in range(16)])
    depth = ImageFrame(name="nadir", kind="depth", encoding="png", data=b"\x00\x01", depth_scale_m=0.005)
    pose = Pose(position_world_m=(10.0, 20.0, 80.0), yaw_rad=0.5)
    coord = CoordinationState(
        run_id="r1", episode_id="e1", sim_time_s=12.0,
        candidates=[Candidate(candidate_id="C001", cell="A1", polygon_world_m=[(0.0, 0.0), (1.0, 0.0), (1.0, 1.0)],
                              center_world_m=(0.5, 0.5), status="pending", created_sim_time_s=11.0,
                              approach_waypoint_id="R12")],
        messages=[MessageRecord(sender="uav", receiver="ugv", text="look at A1", sent_sim_time_s=10.0,
                                delivered_sim_time_s=10.5)],
        poses={"uav": pose},
    )
    return Observation(
        run_id="r1", episode_id="e1", role="uav", decision_index=2, sim_time_s=12.0, pose=pose, mode="aerial",
        images=[frame, depth], references=[], legal_actions=["MOVE_TO_UAV_WAYPOINT", "WAIT"],
        waypoint_options=[Waypoint(waypoint_id="U1_2", position_world_m=(40.0, 80.0, 80.0), kind="uav_grid")],
        region_world_m=(-75.0, -75.0, 75.0, 75.0), coordination=coord,
    )


def _grant() -> JobGrant:
    spec = EpisodeSpec(
        episode_id="grid-s7-easy-000-v1", town=TownRef(generator="grid", seed=7, town_id="grid-s7"),
        asset_sha256="cd" * 32, difficulty="easy", region_world_m=(0.0, 0.0, 150.0, 150.0),
        target=VehicleSpec(model="sedan", colour="red", position_world_m=(1.0, 2.0, 0.0), yaw_rad=1.5),
        uav_start_waypoint="U1_1", ugv_start_waypoint="R7", active_uav_waypoints=["U1_1", "U1_2"], seed=3,
    )
    return JobGrant(episode=spec)


MESSAGES = [_action, _record, _observation, _grant]


@pytest.mark.parametrize("make", MESSAGES)
def test_payload_is_the_models_dump_packed(make) -> None:
    """msgspec writes a model through its fields: byte for byte msgpack-python's packing of model_dump."""
    message = make()
    assert encode(message) == msgpack.packb(message.model_dump(mode="python"), use_bin_type=True)


def test_payload_holds_only_declared_fields() -> None:
    stray = _action()
    stray.__dict__["note"] = "not a field"  # stored beside the fields (model_copy refuses to)
    assert encode(stray) == encode(_action())


def test_numpy_scalars_are_written_as_numbers() -> None:
    assert encode({"x": np.float32(0.5), "n": np.int64(3)}) == msgpack.packb({"x": 0.5, "n": 3})


@pytest.mark.parametrize("make", MESSAGES)
def test_round_trip(make) -> None:
    message = make()
    back = decode(encode(message))
    assert type(back) is type(message)
    assert back == message


def test_observation_image_bytes_survive() -> None:
    back = decode(encode(_observation()))
    assert isinstance(back.images[0].data, bytes)
    assert back.images[0].data == RAW
    assert back.images[0].intrinsics.fx_px == 443.4
    assert back.coordination.candidates[0].polygon_world_m == [(0.0, 0.0), (1.0, 0.0), (1.0, 1.0)]
    assert back.coordination.poses["uav"].position_world_m == (10.0, 20.0, 80.0)


def test_record_candidates_survive() -> None:
    back = decode(encode(_record()))
    assert [c.candidate_id for c in back.candidates] == ["C001", "C002"]
    assert back.candidates[1].center_world_m == (10.0, 20.0)
    assert back.shortest_path_length_m == 98.25
    assert back.error is None


def test_payload_is_plain_msgpack_map() -> None:
    def no_ext(code, data):  # any ext type in the payload would make plain decoding fail
        raise AssertionError(f"unexpected msgpack ext type {code}")

    plain = msgpack.unpackb(encode(_observation()), raw=False, ext_hook=no_ext)
    assert isinstance(plain, dict)
    assert plain["v"] == SCHEMA_VERSION == 1
    assert plain["type"] == "observation"
    assert plain["images"][0]["data"] == RAW
    assert isinstance(plain["images"][0]["data"], bytes)
    assert plain["pose"]["position_world_m"] == [10.0, 20.0, 80.0]  # tuples become arrays
    assert plain["region_world_m"] == [-75.0, -75.0, 75.0, 75.0]

    action = msgpack.unpackb(encode(_action()), raw=False, ext_hook=no_ext)
    assert action["type"] == "action"
    assert action["v"] == 1
    assert action["decision_index"] == 3
    assert action["waypoint_id"] is None


def test_payload_built_without_models_decodes() -> None:
    payload = msgpack.packb({"v": 1, "type": "job_request", "worker_id": "w9"}, use_bin_type=True)
    request = decode(payload)
    assert type(request).__name__ == "JobRequest"
    assert request.worker_id == "w9"


def _action_dict() -> dict:
    return msgpack.unpackb(encode(_action()), raw=False)


def test_missing_field_is_named() -> None:
    data = _action_dict()
    del data["decision_index"]
    with pytest.raises(DecodeError, match="decision_index") as info:
        decode(msgpack.packb(data))
    assert "required" in str(info.value).lower()


def test_wrong_type_is_named() -> None:
    data = _action_dict()
    data["role"] = "tank"
    with pytest.raises(DecodeError, match="role"):
        decode(msgpack.packb(data))
    data = _action_dict()
    data["decision_index"] = "three"
    with pytest.raises(DecodeError, match="decision_index"):
        decode(msgpack.packb(data))


def test_nested_wrong_type_is_named() -> None:
    data = msgpack.unpackb(encode(_record()), raw=False)
    data["candidates"][1]["distance_to_polygon_m"] = "far"
    with pytest.raises(DecodeError, match=r"candidates\.1\.distance_to_polygon_m"):
        decode(msgpack.packb(data))


def test_unknown_type_is_named() -> None:
    with pytest.raises(DecodeError, match="type") as info:
        decode(msgpack.packb({"v": 1, "type": "teleport", "run_id": "r"}))
    assert "teleport" in str(info.value)


def test_missing_type_is_named() -> None:
    with pytest.raises(DecodeError, match="'type'"):
        decode(msgpack.packb({"v": 1, "run_id": "r"}))


def test_extra_field_rejected() -> None:
    data = _action_dict()
    data["bogus"] = 1
    with pytest.raises(DecodeError, match="bogus"):
        decode(msgpack.packb(data))


@pytest.mark.parametrize("payload", [msgpack.packb([1, 2, 3]), msgpack.packb("action"), msgpack.packb(5),
                                     msgpack.packb(None)])
def test_non_map_payload(payload: bytes) -> None:
    with pytest.raises(DecodeError, match="not a msgpack map"):
        decode(payload)


@pytest.mark.parametrize("payload", [b"", b"\xc1", b"\x92\x01", msgpack.packb({"v": 1}) + b"\x00"])
def test_non_msgpack_payload(payload: bytes) -> None:
    with pytest.raises(DecodeError, match="not msgpack"):
        decode(payload)


def test_decode_error_is_value_error() -> None:
    assert issubclass(DecodeError, ValueError)


# --- image helpers -------------------------------------------------------------------------------


def _rng() -> np.random.Generator:
    return np.random.default_rng(1234)


def test_png_rgb_uint8_exact() -> None:
    image = _rng().integers(0, 256, size=(17, 23, 3), dtype=np.uint8)
    data = encode_png(image)
    assert data[:8] == b"\x89PNG\r\n\x1a\n"
    back = decode_image(data)
    assert back.dtype == np.uint8
    assert back.shape == (17, 23, 3)
    np.testing.assert_array_equal(back, image)


def test_png_channel_order_is_rgb() -> None:
    image = np.zeros((4, 4, 3), np.uint8)
    image[..., 0] = 255  # pure red
    back = decode_image(encode_png(image))
    assert back[0, 0].tolist() == [255, 0, 0]


def test_png_depth_uint16_exact() -> None:
    depth = _rng().integers(0, 65536, size=(19, 11), dtype=np.uint16)
    depth[0, 0], depth[-1, -1] = 0, 65535
    back = decode_image(encode_png(depth))
    assert back.dtype == np.uint16
    assert back.shape == (19, 11)
    np.testing.assert_array_equal(back, depth)


def test_png_rgba_exact() -> None:
    image = _rng().integers(0, 256, size=(9, 13, 4), dtype=np.uint8)
    image[0, 0] = (10, 20, 30, 0)
    back = decode_image(encode_png(image))
    assert back.shape == (9, 13, 4)
    np.testing.assert_array_equal(back, image)
    assert back[0, 0].tolist() == [10, 20, 30, 0]


def test_png_gray_uint8_exact() -> None:
    image = _rng().integers(0, 256, size=(8, 8), dtype=np.uint8)
    back = decode_image(encode_png(image))
    assert back.dtype == np.uint8
    np.testing.assert_array_equal(back, image)


def test_jpeg_round_trip_close_and_rgb() -> None:
    image = np.zeros((32, 48, 3), np.uint8)
    image[:, :24] = (200, 30, 20)  # reddish left half
    image[:, 24:] = (20, 40, 210)  # bluish right half
    data = encode_jpeg(image, quality=95)
    assert data[:2] == b"\xff\xd8"
    back = decode_image(data)
    assert back.shape == image.shape
    assert back.dtype == np.uint8
    # away from the colour edge JPEG is close to the original, in RGB order
    assert np.abs(back[:, :16].astype(int) - image[:, :16]).max() <= 8
    assert np.abs(back[:, 32:].astype(int) - image[:, 32:]).max() <= 8


def test_decode_image_rejects_garbage() -> None:
    with pytest.raises(ValueError, match="could not be decoded"):
        decode_image(b"definitely not an image")


# ----- Encoder / Decoder: the decision hot path ------------------------------------------------


def _big_observation(decision_index: int = 2, episode_id: str = "e1") -> Observation:
    """An observation with reference views and a searchable area (the fields REPEATED caches)."""
    obs = _observation()
    refs = [ImageFrame(name=f"ref_{k}", kind="rgb", encoding="png", data=RAW + bytes([k]), metres_per_px=0.02)
            for k in range(3)]
    area = [Waypoint(waypoint_id=f"U{i}_{j}", position_world_m=(40.0 * i, 40.0 * j, 80.0), kind="uav_grid")
            for i in range(4) for j in range(4)]
    return obs.model_copy(update={"references": refs, "active_uav_waypoints": area, "decision_index": decision_index,
                                  "episode_id": episode_id})


def test_encoder_payload_is_the_same_map_as_encode() -> None:
    encoder = Encoder()
    for k in range(3):  # a miss, then hits on the same objects, then equal copies
        obs = _big_observation(k + 1)
        if k == 2:
            obs = obs.model_copy(update={"active_uav_waypoints": [w.model_copy() for w in obs.active_uav_waypoints]})
        payload = encoder.encode(obs)
        assert payload == encode(obs)
        assert decode(payload) == obs


def test_encoder_notices_a_changed_repeated_field() -> None:
    encoder = Encoder()
    obs = _big_observation()
    encoder.encode(obs)
    changed = obs.model_copy(update={"active_uav_waypoints": obs.active_uav_waypoints[:-1]})
    assert decode(encoder.encode(changed)).active_uav_waypoints == obs.active_uav_waypoints[:-1]
    obs.references.append(obs.references[0])  # mutated in place: same list object, new content
    assert len(decode(encoder.encode(obs)).references) == 4


def test_encoder_falls_back_for_what_vars_cannot_write() -> None:
    """The encoder writes models with ``vars`` (C) and starts over with the full hook for anything
    else, such as a numpy scalar assigned after validation: the same bytes as ``encode`` either way."""
    obs = _big_observation()
    obs.pose.yaw_rad = np.float64(0.25)
    obs.coordination.decisions_used = np.int64(3)
    encoder = Encoder()
    assert encoder.encode(obs) == bytes(encoder.encode_reused(obs)) == encode(obs)
    assert decode(encode(obs)).coordination.decisions_used == 3


def test_model_copy_refuses_an_unknown_field() -> None:
    """pydantic would keep it beside the fields, unchecked, and it would go out on the wire."""
    with pytest.raises(ValueError, match="Observation has no field bogus"):
        _observation().model_copy(update={"decision_index": 2, "bogus": 1})
    assert _observation().model_copy(update={"decision_index": 2}).decision_index == 2


def test_encoder_passes_other_messages_through() -> None:
    assert Encoder().encode(_action()) == encode(_action())


def test_decoder_matches_decode_and_reuses_repeated_parts() -> None:
    decoder = Decoder()
    first = decoder.decode(encode(_big_observation(1)))
    second = decoder.decode(Encoder().encode(_big_observation(2)))
    assert isinstance(first, mirror(Observation))  # read straight into the compiled mirror
    assert to_model(first) == _big_observation(1) and to_model(second) == _big_observation(2)
    assert second.references[0] is first.references[0]  # validated once
    assert second.active_uav_waypoints[5] is first.active_uav_waypoints[5]
    other = decoder.decode(encode(_big_observation(1, episode_id="e2")))
    assert other.references[0] is not first.references[0]  # per episode
    changed = _big_observation(3)
    changed.active_uav_waypoints[0].kind = "moved"
    assert decoder.decode(encode(changed)).active_uav_waypoints[0].kind == "moved"
    decoder.forget("e1")
    assert decoder.decode(encode(_big_observation(4))).references[0] is not first.references[0]
    for make in MESSAGES:
        assert to_model(decoder.decode(encode(make()))) == make()


def test_decoder_errors_read_like_decode() -> None:
    decoder = Decoder()
    decoder.decode(encode(_big_observation()))
    data = msgpack.unpackb(encode(_big_observation()), raw=False)
    data["active_uav_waypoints"][1]["position_world_m"] = "north"
    bad = [msgpack.packb(data), b"", b"\xc1", msgpack.packb([1]), encode(_action()) + b"\x00",
           encode(_big_observation()).replace(b"\xa2e1", b"\xa2\xff\xfe", 1),  # a string that is not UTF-8
           b"\x91" * 2000 + b"\x00", b"\x82\xa4type\xabobservation\xa6run_id" + b"\x91" * 2000 + b"\x00",  # too deep
           msgpack.packb({"v": 1, "type": "teleport"})]
    for payload in bad:
        with pytest.raises(DecodeError) as expected:
            decode(payload)
        with pytest.raises(DecodeError) as got:
            decoder.decode(payload)
        assert str(got.value) == str(expected.value)


def test_decoder_cache_is_bounded() -> None:
    decoder = Decoder(capacity=4)
    for k in range(10):
        decoder.decode(encode(_big_observation(episode_id=f"e{k}")))
    assert len(decoder._seen) == 4
