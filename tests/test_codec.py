"""msgpack wire codec (agos/runtime/codec.py) over the schemas (agos/runtime/schemas.py)."""

from __future__ import annotations

import json
from pathlib import Path

import msgpack
import msgspec
import numpy as np
import pytest

from agos.runtime.codec import (
    DecodeError,
    decode,
    decode_as,
    decode_image,
    encode,
    encode_into,
    encode_jpeg,
    encode_png,
    from_json,
    to_json,
)
from agos.runtime.schemas import (
    SCHEMA_VERSION,
    Action,
    CameraIntrinsics,
    Candidate,
    CandidateOutcome,
    CoordinationState,
    DecisionTrace,
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
    WireMessage,
)

RAW = bytes(range(256)) + b"\x89PNG\r\n\x1a\n\x00\xff"  # not valid UTF-8: must stay bytes
EXAMPLES = Path(__file__).resolve().parents[1] / "docs" / "examples"


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


def _spec() -> EpisodeSpec:
    return EpisodeSpec(
        episode_id="grid-s7-easy-000-v1", town=TownRef(generator="grid", seed=7, town_id="grid-s7"),
        asset_sha256="cd" * 32, difficulty="easy", region_world_m=(0.0, 0.0, 150.0, 150.0),
        target=VehicleSpec(model="sedan", colour="red", position_world_m=(1.0, 2.0, 0.0), yaw_rad=1.5),
        uav_start_waypoint="U1_1", ugv_start_waypoint="R7", active_uav_waypoints=["U1_1", "U1_2"], seed=3,
    )


def _grant() -> JobGrant:
    return JobGrant(episode=_spec())


MESSAGES = [_action, _record, _observation, _grant]


def _as_map(value):
    """What a payload should hold, built independently of the codec: a struct as the map of its
    fields (its ``type`` tag too), tuples as lists."""
    if isinstance(value, msgspec.Struct):
        config = type(value).__struct_config__
        names = value.__struct_fields__
        defaults = dict(zip(names[len(names) - len(value.__struct_defaults__):], value.__struct_defaults__, strict=True))

        def default(name: str) -> object:
            d = defaults.get(name, msgspec.NODEFAULT)
            return d.factory() if isinstance(d, msgspec._core.Factory) else d

        fields = {name: _as_map(getattr(value, name)) for name in names  # omit_defaults: defaults are left out
                  if not (config.omit_defaults and getattr(value, name) == default(name))}
        return {"type": config.tag, **fields} if config.tag is not None else fields
    if isinstance(value, (list, tuple)):
        return [_as_map(v) for v in value]
    if isinstance(value, dict):
        return {k: _as_map(v) for k, v in value.items()}
    return value


@pytest.mark.parametrize("make", MESSAGES)
def test_payload_is_the_plain_map_of_the_fields(make) -> None:
    """msgpack-python reads a payload into the map of the message's fields, ``type`` first, and
    packs that map into the same bytes (so the sizes the link model charges are those of the map)."""
    message = make()
    plain = msgpack.unpackb(encode(message), raw=False)
    assert plain == _as_map(message)
    assert list(plain)[:2] == ["type", "v"] and list(plain)[2:] == list(type(message).__struct_fields__)[1:]
    assert encode(message) == msgpack.packb(plain, use_bin_type=True)


def test_payloads_keep_their_size_and_content() -> None:
    """The same bytes as the pydantic models wrote before the structs (msgpack-python's packing of
    ``model_dump``), but for the order of ``v`` and ``type``: lengths taken from that version."""
    # + the attempt field (key and value); the action also + outage (8, key and nil) and 2 for its 16th field (a
    # map16 header, no longer a fixmap); the observation also +
    # decision_timeout_s (20), expert (8) and teammate_reference (20), keys and nil, and its coordination
    # state's confirmations_used (20) and max_confirmations (19), keys and values
    for make, size in ((_action, 202 + 9 + 8 + 2), (_observation, 1767 + 9 + 20 + 8 + 20 + 20 + 19)):
        plain = msgpack.unpackb(encode(make()), raw=False)
        old_order = {"v": plain.pop("v"), "type": plain.pop("type"), **plain}
        assert len(encode(make())) == len(msgpack.packb(old_order, use_bin_type=True)) == size
    assert msgpack.unpackb(encode(_action()), raw=False) == {
        "type": "action", "v": SCHEMA_VERSION, "run_id": "r1", "episode_id": "e1", "role": "ugv", "decision_index": 3, "attempt": 1,
        "action": "GO_TO_CANDIDATE", "waypoint_id": None, "cell": None, "candidate_id": "C002",
        "message": "heading there", "rationale": "closest", "agent_wall_latency_s": 0.25, "trace": None, "outage": None}


def test_numpy_values_are_written_as_numbers_and_lists() -> None:
    assert encode({"x": np.float32(0.5), "n": np.int64(3), "a": np.arange(3)}) == msgpack.packb(
        {"x": 0.5, "n": 3, "a": [0, 1, 2]})
    pose = Pose(position_world_m=(np.float64(1.0), np.float32(2.0), 3.0), yaw_rad=np.float32(0.5))
    assert encode(pose) == encode(Pose(position_world_m=(1.0, 2.0, 3.0), yaw_rad=0.5))


def test_encode_into_reuses_a_buffer() -> None:
    buffer = bytearray(b"old content, longer than nothing")
    encode_into(_action(), buffer)
    assert bytes(buffer) == encode(_action())


@pytest.mark.parametrize("make", MESSAGES)
def test_round_trip(make) -> None:
    message = make()
    back = decode(encode(message))
    assert type(back) is type(message)
    assert back == message


def test_decode_as_reads_one_type_and_refuses_others() -> None:
    assert decode_as(encode(_action()), Action) == _action()
    with pytest.raises(DecodeError, match="type"):
        decode_as(encode(_record()), Action)


def test_decoded_numbers_take_the_declared_types() -> None:
    """A sender may write an int where a float is declared (a struct is not checked when built);
    the receiver reads a float, and tuples where tuples are declared."""
    data = msgpack.unpackb(encode(_action()), raw=False)
    data["agent_wall_latency_s"] = 1
    back = decode(msgpack.packb(data))
    assert back.agent_wall_latency_s == 1.0 and isinstance(back.agent_wall_latency_s, float)
    assert isinstance(decode(encode(_observation())).pose.position_world_m, tuple)


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
    assert back.error is None and back.candidate_tools


def test_payload_is_plain_msgpack_map() -> None:
    def no_ext(code, data):  # any ext type in the payload would make plain decoding fail
        raise AssertionError(f"unexpected msgpack ext type {code}")

    plain = msgpack.unpackb(encode(_observation()), raw=False, ext_hook=no_ext)
    assert isinstance(plain, dict)
    assert plain["v"] == SCHEMA_VERSION == 3
    assert plain["type"] == "observation"
    assert plain["images"][0]["data"] == RAW
    assert isinstance(plain["images"][0]["data"], bytes)
    assert plain["pose"]["position_world_m"] == [10.0, 20.0, 80.0]  # tuples become arrays
    assert plain["region_world_m"] == [-75.0, -75.0, 75.0, 75.0]
    assert plain["coordination"]["type"] == "coordination_state"  # a nested message keeps its tag


def test_payload_built_without_structs_decodes() -> None:
    payload = msgpack.packb({"v": SCHEMA_VERSION, "type": "job_request", "worker_id": "w9"}, use_bin_type=True)
    request = decode(payload)
    assert type(request).__name__ == "JobRequest"
    assert request.worker_id == "w9"


def test_every_message_type_decodes_by_its_tag() -> None:
    for kind in WireMessage.__args__:
        assert isinstance(kind.__struct_config__.tag, str)
    tags = [kind.__struct_config__.tag for kind in WireMessage.__args__]
    assert len(set(tags)) == len(tags)


def _action_dict() -> dict:
    return msgpack.unpackb(encode(_action()), raw=False)


def test_missing_field_is_named() -> None:
    data = _action_dict()
    del data["decision_index"]
    with pytest.raises(DecodeError, match=r"field decision_index: .*missing required"):
        decode(msgpack.packb(data))


def test_wrong_type_is_named() -> None:
    data = _action_dict()
    data["role"] = "tank"
    with pytest.raises(DecodeError, match="field role: Invalid enum value 'tank'"):
        decode(msgpack.packb(data))
    data = _action_dict()
    data["decision_index"] = "three"
    with pytest.raises(DecodeError, match="field decision_index: Expected `int`, got `str`"):
        decode(msgpack.packb(data))


def test_nested_wrong_type_is_named() -> None:
    data = msgpack.unpackb(encode(_record()), raw=False)
    data["candidates"][1]["distance_to_polygon_m"] = "far"
    with pytest.raises(DecodeError, match=r"field candidates\.1\.distance_to_polygon_m: Expected `float`"):
        decode(msgpack.packb(data))
    data = msgpack.unpackb(encode(_observation()), raw=False)
    del data["coordination"]["candidates"][0]["cell"]
    with pytest.raises(DecodeError, match=r"field coordination\.candidates\.0\.cell: .*missing"):
        decode(msgpack.packb(data))


def test_unknown_type_is_refused() -> None:
    with pytest.raises(DecodeError, match=r"field type: .*'teleport'"):
        decode(msgpack.packb({"v": SCHEMA_VERSION, "type": "teleport", "run_id": "r"}))


def test_missing_type_is_named() -> None:
    with pytest.raises(DecodeError, match=r"field type: .*missing required"):
        decode(msgpack.packb({"v": SCHEMA_VERSION, "run_id": "r"}))


def test_extra_field_rejected() -> None:
    data = _action_dict()
    data["bogus"] = 1
    with pytest.raises(DecodeError, match=r"field bogus: .*unknown"):
        decode(msgpack.packb(data))


@pytest.mark.parametrize("payload", [msgpack.packb([1, 2, 3]), msgpack.packb("action"), msgpack.packb(5),
                                     msgpack.packb(None), b"\x92\x01"])
def test_non_map_payload(payload: bytes) -> None:
    with pytest.raises(DecodeError, match="not a msgpack map"):
        decode(payload)


@pytest.mark.parametrize("payload", [b"", b"\xc1", encode(_action()) + b"\x00",
                                     encode(_action()).replace(b"\xa2r1", b"\xa2\xff\xfe", 1)])  # not UTF-8
def test_non_msgpack_payload(payload: bytes) -> None:
    with pytest.raises(DecodeError, match="not msgpack"):
        decode(payload)


def test_too_deep_payload_is_refused() -> None:
    head = msgpack.packb({"type": "job_grant", "v": SCHEMA_VERSION, "episode": None})
    deep = b"\x84" + head[1:] + b"\xa6config" + b"\x81\xa1a" * 3000 + b"\xc0"  # config: any map
    with pytest.raises(DecodeError, match="nested too deeply"):
        decode(deep)


def test_decode_error_is_value_error() -> None:
    assert issubclass(DecodeError, ValueError)


# --- JSON: records in result files, episode specs in split files --------------------------------


@pytest.mark.parametrize("make", [_record, _spec])
def test_json_round_trip(make) -> None:
    message = make()
    text = to_json(message)
    assert json.loads(text) == json.loads(json.dumps(_as_map(message)))
    assert from_json(text, type(message)) == message


def test_records_written_before_the_structs_still_read() -> None:
    """Result files and example summaries written by the pydantic models (``v`` before ``type``)
    read into the struct, and write back the same keys and values."""
    for line in (EXAMPLES / "heuristic-512px.jsonl").read_text().splitlines()[:5]:
        record = from_json(line, EpisodeRecord)
        old, new = json.loads(line), json.loads(to_json(record))
        assert {key: new[key] for key in old} == old


def test_json_errors_name_the_field() -> None:
    data = json.loads(to_json(_spec()))
    data["town"]["seed"] = "seven"
    with pytest.raises(DecodeError, match=r"field town\.seed: Expected `int`, got `str`"):
        from_json(json.dumps(data), EpisodeSpec)
    with pytest.raises(DecodeError, match="not JSON"):
        from_json("{not json", EpisodeSpec)


def test_traces_read_back_with_their_defaults() -> None:
    trace = DecisionTrace(policy="p", model="m", stage="search", prompt_sha256="0" * 64, image_bytes={"a": 1},
                          raw_reply=None, parsed_action="WAIT", fallback=False)
    action = msgspec.structs.replace(_action(), trace=trace)
    assert decode(encode(action)).trace == trace


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


@pytest.mark.parametrize("version", [1, 2, 4, 99])
def test_a_live_message_of_another_schema_version_is_refused_naming_both(version: int) -> None:
    from agos.runtime.codec import WireVersionError

    data = msgpack.unpackb(encode(_record()), raw=False)
    data["v"] = version
    for read in (decode, lambda p: decode_as(p, EpisodeRecord)):
        with pytest.raises(WireVersionError, match=f"wire schema version {version}, this process speaks version "
                                                   f"{SCHEMA_VERSION}") as caught:
            read(msgpack.packb(data))
        assert "\n" not in str(caught.value)
    data["unknown_field_of_a_later_version"] = 1  # what a later version may add: still named by its version
    with pytest.raises(WireVersionError):
        decode(msgpack.packb(data))


@pytest.mark.parametrize("version", [1, 2])
def test_stored_records_of_every_older_version_still_read(version: int) -> None:
    """Records in results files and SQLite of schema versions 1 and 2 (before localisation error, the
    model link and message faults: those fields absent) read with those fields empty."""
    stored = json.loads(to_json(_record()))
    stored["v"] = version
    for later in ("pose_error_profile", "pose_error", "model_link"):
        del stored[later]
    for entry in stored["ledger"]:
        entry.pop("fault", None)
    if stored.get("link"):
        for later in ("duplicated", "corrupted"):
            stored["link"].pop(later, None)
    record = from_json(json.dumps(stored), EpisodeRecord)
    assert record.v == version and msgspec.structs.replace(record, v=SCHEMA_VERSION) == _record()
    assert record.pose_error == {} and record.model_link is None and record.pose_error_profile == "exact"


def _fresh_message_types(n: int) -> tuple[type, bytes]:
    """A union of ``n`` new tagged structs with nested parts, never seen by msgspec, and the bytes of one."""

    class Part(msgspec.Struct):
        a: list[float]
        b: dict[str, int] | None = None

    kinds = [msgspec.defstruct(f"Kind{i}", [("parts", list[Part]), ("name", str)], tag=f"k{i}") for i in range(n)]
    union = kinds[0]
    for kind in kinds[1:]:
        union = union | kind
    return union, msgspec.msgpack.encode(kinds[-1](parts=[Part(a=[1.0])], name="x"))


def test_threads_making_their_first_decoders_at_once_do_not_crash_the_process() -> None:
    """msgspec fills in a struct's type information while it makes a decoder; two threads doing so at
    once crashed a human console (a segmentation fault). Decoders are made under a lock: here six
    threads ask at once for the decoder of types msgspec has not seen, 40 times, with the interpreter
    switching threads every few bytecodes (without the lock, 7 runs of this test in 10 crashed)."""
    import sys
    import threading

    from agos.runtime.codec import _decoder

    def race(union: type, payload: bytes) -> list[str]:
        start, names = threading.Barrier(6), []

        def first_decode() -> None:
            start.wait()
            names.append(_decoder(union).decode(payload).name)

        threads = [threading.Thread(target=first_decode) for _ in range(6)]
        for thread in threads:
            thread.start()
        for thread in threads:
            thread.join()
        return names

    switch_s = sys.getswitchinterval()
    sys.setswitchinterval(1e-6)
    try:
        for _ in range(40):
            assert race(*_fresh_message_types(12)) == ["x"] * 6
    finally:
        sys.setswitchinterval(switch_s)
