"""Compiled mirrors (agos/runtime/structs.py): the same fields as the models, and never more lenient.

The differential test mutates real payloads at random and checks that the hot-path ``Decoder``
(mirrors) and the canonical ``decode`` (pydantic) agree on every one: the same values, or the
same error. A mirror may refuse what pydantic accepts (it then hands over to pydantic), never the
reverse.
"""

from __future__ import annotations

import random
from typing import Any, get_args

import msgpack
import msgspec
import pytest
from pydantic import BaseModel

from agos.runtime.codec import DecodeError, Decoder, Encoder, decode, encode, encode_checked
from agos.runtime.schemas import Action, Observation, WireMessage
from agos.runtime.structs import mirror, to_model
from tests.test_codec import MESSAGES, _big_observation

WIRE_MODELS = list(get_args(get_args(WireMessage)[0]))


@pytest.mark.parametrize("model", WIRE_MODELS, ids=lambda m: m.__name__)
def test_every_wire_model_has_an_exact_mirror(model: type[BaseModel]) -> None:
    struct = mirror(model)
    assert struct.__name__ == model.__name__
    assert struct.__struct_fields__ == tuple(model.model_fields)  # same names, same order
    assert mirror(model) is struct  # made once


@pytest.mark.parametrize("make", MESSAGES)
def test_mirror_reads_what_the_model_wrote(make) -> None:
    message = make()
    struct = msgspec.msgpack.decode(encode(message), type=mirror(type(message)))
    assert encode(struct) == encode(message)  # and writes it back byte for byte
    assert to_model(struct) == message


def test_mirror_reads_like_the_model() -> None:
    obs = _big_observation()
    struct = Decoder().decode(Encoder().encode(obs))
    assert struct.pose.position_world_m == obs.pose.position_world_m == (10.0, 20.0, 80.0)
    assert struct.coordination.poses["uav"].yaw_rad == 0.5
    assert struct.coordination.candidates[0].polygon_world_m == [(0.0, 0.0), (1.0, 0.0), (1.0, 1.0)]
    assert struct.images[0].intrinsics.fx_px == 443.4
    assert struct.oracle is None and struct.grid_rows == "ABCDE"  # defaults filled in as by pydantic


def test_mirror_image_bytes_are_views_of_the_payload() -> None:
    """Decoding copies no image bytes: they are read-only views into the payload (or, for the
    cached repeated parts, into the decoder's own copy of their bytes), equal to the model's."""
    obs = _big_observation()
    payload = Encoder().encode(obs)
    struct = Decoder().decode(payload)
    image = struct.images[0].data
    assert isinstance(image, memoryview) and image.readonly and image.obj is payload
    assert image == obs.images[0].data and bytes(image) == obs.images[0].data
    assert all(ref.data.obj is not payload for ref in struct.references)  # the cache outlives the payload
    assert to_model(struct) == obs and isinstance(to_model(struct).images[0].data, bytes)


def test_a_model_with_constraints_aliases_or_lax_config_is_not_mirrored() -> None:
    from pydantic import ConfigDict, Field

    class Bounded(BaseModel):
        count: int = Field(ge=0)

    class Aliased(BaseModel):
        count: int = Field(alias="n")

    class Stripped(BaseModel):
        model_config = ConfigDict(str_strip_whitespace=True)
        name: str

    for model, why in ((Bounded, "constraints"), (Aliased, "alias"), (Stripped, "str_strip_whitespace")):
        with pytest.raises(TypeError, match=why):
            mirror(model)


def test_decoded_observations_pickle_and_own_their_lists() -> None:
    import copy
    import pickle

    decoder, payload = Decoder(), Encoder().encode(_big_observation())
    first = decoder.decode(payload)
    assert isinstance(first, mirror(Observation)) and type(pickle.loads(pickle.dumps(first))) is mirror(Observation)
    assert to_model(pickle.loads(pickle.dumps(first))) == _big_observation()
    assert to_model(copy.deepcopy(first)) == _big_observation()
    first.active_uav_waypoints.pop()  # a policy's own business: the next decision still gets all 16
    assert len(decoder.decode(payload).active_uav_waypoints) == len(_big_observation().active_uav_waypoints) == 16


WRONG_VALUES: list[Any] = ["x", "", 7, -1, 2.5, True, None, [], [1.0, 2.0], {}, {"k": 1}, b"\x00"]


def _leaves(node: Any, path: tuple = ()) -> list[tuple]:
    if isinstance(node, dict):
        return [path] + [leaf for k, v in node.items() for leaf in _leaves(v, (*path, k))]
    if isinstance(node, list):
        return [path] + [leaf for i, v in enumerate(node) for leaf in _leaves(v, (*path, i))]
    return [path]


def _mutate(data: dict, rng: random.Random) -> dict:
    path = rng.choice([p for p in _leaves(data) if p])
    parent = data
    for step in path[:-1]:
        parent = parent[step]
    last, how = path[-1], rng.random()
    if how < 0.1 and isinstance(parent, dict):
        del parent[last]
    elif how < 0.2 and isinstance(parent, dict):
        parent[f"extra_{rng.randrange(100)}"] = 1
    else:
        parent[last] = rng.choice(WRONG_VALUES)
    return data


def _agree(payload: bytes, decoder: Decoder, label: object = "") -> str:
    """Both decoders give the same model, or the same error; which of the two it was."""
    try:
        expected = decode(payload)
    except DecodeError as exc:
        with pytest.raises(DecodeError) as got:
            decoder.decode(payload)
        assert str(got.value) == str(exc), label
        return "refused"
    assert to_model(decoder.decode(payload)) == expected, label
    return "accepted"


def test_hot_path_decoder_agrees_with_pydantic_on_mutated_payloads() -> None:
    rng = random.Random(7)
    originals = [msgpack.unpackb(encode(_big_observation()), raw=False),
                 msgpack.unpackb(encode(Observation.model_validate(
                     {**_big_observation().model_dump(), "oracle": {"target_world_m": (1.0, 2.0), "target_in_view": True,
                                                                    "confirm_would_succeed": False}})), raw=False)]
    agreed = {"accepted": 0, "refused": 0}
    for case in range(400):
        data = _mutate(msgpack.unpackb(msgpack.packb(rng.choice(originals)), raw=False), rng)
        if rng.random() < 0.3:
            data = _mutate(data, rng)
        payload = msgpack.packb(data, use_bin_type=True)
        decoder = Decoder()
        if rng.random() < 0.5:  # with the repeated parts already cached from a valid observation
            decoder.decode(encode(_big_observation()))
        agreed[_agree(payload, decoder, case)] += 1
    assert agreed["accepted"] > 20 and agreed["refused"] > 200  # both branches well exercised


@pytest.mark.parametrize("name", list(Observation.model_fields))
def test_hot_path_decoder_agrees_without_each_top_level_field(name: str) -> None:
    """Fields with defaults may be left out, except ``type``: pydantic dispatches on it."""
    data = msgpack.unpackb(encode(_big_observation()), raw=False)
    del data[name]
    _agree(msgpack.packb(data, use_bin_type=True), Decoder())


def _action_with_trace() -> Action:
    return Action.model_validate({**_action().model_dump(), "trace": {
        "policy": "agos-agent", "model": "m", "stage": "uav", "image_bytes": {"nadir": 10}, "raw_reply": "{}",
        "parsed_action": "WAIT", "fallback": False, "prompt_sha256": "ab" * 32}})


def _action() -> Action:
    return Action(run_id="r", episode_id="e", role="ugv", decision_index=4, action="MOVE_TO_ROAD_WAYPOINT",
                  waypoint_id="R12", rationale="closer to C001", agent_wall_latency_s=0.01)


@pytest.mark.parametrize("name", list(Action.model_fields))
def test_action_decoder_agrees_without_each_field(name: str) -> None:
    """Actions are read straight into their mirror, whose ``type`` is required there (structs.tagged)."""
    data = msgpack.unpackb(encode(_action_with_trace()), raw=False)
    del data[name]
    assert _agree(msgpack.packb(data, use_bin_type=True), Decoder(first="action")) == (
        "refused" if name in ("type", "run_id", "episode_id", "role", "decision_index", "action") else "accepted")


def test_action_decoder_agrees_with_pydantic_on_mutated_payloads() -> None:
    rng, agreed = random.Random(11), {"accepted": 0, "refused": 0}
    original = msgpack.unpackb(encode(_action_with_trace()), raw=False)
    for case in range(300):
        data = _mutate(msgpack.unpackb(msgpack.packb(original), raw=False), rng)
        agreed[_agree(msgpack.packb(data, use_bin_type=True), Decoder(first="action"), case)] += 1
    assert agreed["accepted"] > 20 and agreed["refused"] > 100


def test_decoded_actions_are_mirrors_that_pickle_and_convert() -> None:
    import copy
    import pickle

    got = Decoder(first="action").decode(encode(_action()))
    assert isinstance(got, mirror(Action)) and encode(got) == encode(_action())
    assert to_model(got) == _action()
    for twin in (pickle.loads(pickle.dumps(got)), copy.deepcopy(got)):
        assert type(twin) is mirror(Action) and twin == mirror(Action)(**msgspec.structs.asdict(got))


def test_prompts_from_compiled_mirrors_are_the_prompts_from_models(observations) -> None:
    """Over the bus a policy reads the observation's mirror (runtime/structs.py): every prompt of
    both prompt families, built along a whole episode, must be the same bytes as from the model."""
    from agos.agents.vlm import agos_prompts, baseline_prompts
    from agos.agents.vlm.request import Memory

    encoder, decoder = Encoder(), Decoder()
    keys = [(family.__name__, role) for family in (agos_prompts, baseline_prompts) for role in ("uav", "ugv")]
    memories, mirrored = {key: Memory() for key in keys}, {key: Memory() for key in keys}
    for obs in observations:
        twin = decoder.decode(encoder.encode(obs))
        assert type(twin) is not Observation  # the mirror, not the model
        for family in (agos_prompts, baseline_prompts):
            build = family.uav_prompt if obs.role == "uav" else family.ugv_prompt
            key = (family.__name__, obs.role)
            expected, got = build(obs, memories[key]), build(twin, mirrored[key])
            assert got.sha256() == expected.sha256() and got.messages() == expected.messages(), (key, obs.decision_index)


def test_heuristic_policies_act_alike_on_mirrors_and_models(observations) -> None:
    """The same decisions from a model and from its mirror, along a whole episode, both roles; a
    mirror observation is answered with a mirror action (action_for answers in kind) that passes
    the service's check and reads back as the model's action."""
    from agos.agents.registry import make_policy

    encoder, decoder = Encoder(), Decoder()
    on_models = {r: make_policy("heuristic", r) for r in ("uav", "ugv")}
    on_mirrors = {r: make_policy("heuristic", r) for r in ("uav", "ugv")}
    for obs in observations:
        twin = decoder.decode(encoder.encode(obs))
        expected, got = on_models[obs.role].act(obs), on_mirrors[obs.role].act(twin)
        assert type(expected) is Action and type(got) is mirror(Action)
        assert encode_checked(got) == encode(expected), (obs.role, obs.decision_index)
        assert to_model(got) == expected
