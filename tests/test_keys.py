"""Key layout of agos/runtime/keys.py."""

from __future__ import annotations

import pytest

from agos.runtime import keys

RUN = "run-7.a_b"
W = "host-412-ab12"


@pytest.mark.parametrize(
    ("key", "expected"),
    [
        (keys.manifest(RUN), "agos/run-7.a_b/ctl/manifest"),
        (keys.jobs(RUN), "agos/run-7.a_b/ctl/jobs"),
        (keys.lease(RUN), "agos/run-7.a_b/ctl/lease"),
        (keys.slot_live(RUN, W), "agos/run-7.a_b/slot/host-412-ab12/live"),
        (keys.slot_ready(RUN, W, "uav", "uav-9-ff00"), "agos/run-7.a_b/slot/host-412-ab12/ready/uav/uav-9-ff00"),
        (keys.obs(RUN, W, "uav"), "agos/run-7.a_b/slot/host-412-ab12/obs/uav"),
        (keys.act(RUN, W, "ugv"), "agos/run-7.a_b/slot/host-412-ab12/act/ugv"),
        (keys.coord_truth(RUN, W), "agos/run-7.a_b/slot/host-412-ab12/coord/truth"),
        (keys.coord_view(RUN, W, "uav"), "agos/run-7.a_b/slot/host-412-ab12/coord/view/uav"),
        (keys.message(RUN, W, "uav", "ugv"), "agos/run-7.a_b/slot/host-412-ab12/msg/uav/ugv"),
        (keys.events(RUN, W), "agos/run-7.a_b/slot/host-412-ab12/events"),
        (keys.result(RUN, W), "agos/run-7.a_b/slot/host-412-ab12/result"),
        (keys.result_ack(RUN, W), "agos/run-7.a_b/slot/host-412-ab12/ack"),
        (keys.slot_prefix(RUN, W), "agos/run-7.a_b/slot/host-412-ab12/"),
        (keys.live(RUN, "world", "w-01"), "agos/run-7.a_b/live/world/w-01"),
        (keys.live(RUN, "evaluator", "*"), "agos/run-7.a_b/live/evaluator/*"),
        (keys.asset("ab" * 32), "agos/assets/" + "ab" * 32),
        (keys.viz_events(RUN, W), "agos/run-7.a_b/viz/host-412-ab12/events"),
        (keys.viz_coord(RUN, W), "agos/run-7.a_b/viz/host-412-ab12/coord"),
        (keys.viz_frame(RUN, W, "ugv"), "agos/run-7.a_b/viz/host-412-ab12/frame/ugv"),
        (keys.viz_all(), "agos/*/viz/**"),
        (keys.viz_all(RUN), "agos/run-7.a_b/viz/**"),
    ],
)
def test_key_layout(key: str, expected: str) -> None:
    assert key == expected


def test_wildcards_for_subscriptions() -> None:
    assert keys.manifest("*") == "agos/*/ctl/manifest"
    assert keys.result(RUN, "*") == "agos/run-7.a_b/slot/*/result"
    assert keys.events("*", "*") == "agos/*/slot/*/events"


def test_no_key_names_an_episode() -> None:
    """Every key builder takes processes' ids (run, worker, role, agent), never an episode's: the key space
    a run uses is bounded by its processes (docs/ARCHITECTURE.md §2)."""
    import inspect

    for name, build in vars(keys).items():
        if inspect.isfunction(build) and build.__module__ == keys.__name__:
            assert not any("episode" in p for p in inspect.signature(build).parameters), name


def test_roles_constant() -> None:
    assert keys.ROLES == ("uav", "ugv")


BAD_IDS = ["a/b", "ru*n", "**", "a*", "two words", " lead", "dollar$", "$", "", "q?", "hash#"]


@pytest.mark.parametrize("bad", BAD_IDS)
def test_invalid_run_id_raises(bad: str) -> None:
    with pytest.raises(ValueError, match="run id"):
        keys.manifest(bad)
    with pytest.raises(ValueError, match="run id"):
        keys.obs(bad, W, "uav")


@pytest.mark.parametrize("bad", BAD_IDS)
def test_invalid_worker_id_raises(bad: str) -> None:
    for build in (keys.coord_truth, keys.events, keys.result, keys.result_ack, keys.slot_live, keys.viz_spec):
        with pytest.raises(ValueError, match="worker id"):
            build(RUN, bad)
    with pytest.raises(ValueError, match="worker id"):
        keys.act(RUN, bad, "ugv")
    with pytest.raises(ValueError, match="worker id"):
        keys.message(RUN, bad, "uav", "ugv")


@pytest.mark.parametrize("bad", ["a/b", "x*y", "sp ace", "d$"])
def test_invalid_live_id_raises(bad: str) -> None:
    with pytest.raises(ValueError):
        keys.live(RUN, "agent", bad)


def test_check_chunk_returns_value_and_names_what() -> None:
    assert keys.check_chunk("A-z_0.9", what="thing") == "A-z_0.9"
    with pytest.raises(ValueError, match=r"thing 'a b'"):
        keys.check_chunk("a b", what="thing")


def test_slot_of_and_run_of_parse_built_keys() -> None:
    for key in (
        keys.obs(RUN, W, "uav"),
        keys.coord_view(RUN, W, "ugv"),
        keys.message(RUN, W, "ugv", "uav"),
        keys.result_ack(RUN, W),
        keys.viz_frame(RUN, W, "uav"),
    ):
        assert keys.slot_of(key) == W
        assert keys.run_of(key) == RUN
    assert keys.kind_of(keys.viz_frame(RUN, W, "uav")) == "frame/uav"
    assert keys.kind_of(keys.result(RUN, W)) == "result"
    assert keys.run_of(keys.manifest(RUN)) == RUN
    assert keys.run_of(keys.live(RUN, "orchestrator", "o1")) == RUN


@pytest.mark.parametrize(
    "key",
    ["other/r/slot/w/result", "agos/r/ctl/manifest", "agos/r/slot/w", "agos", "", "agos/r/live/world/w1"],
)
def test_slot_of_rejects_other_keys(key: str) -> None:
    with pytest.raises(ValueError, match="not a slot key"):
        keys.slot_of(key)


@pytest.mark.parametrize("key", ["other/r/ctl/manifest", "agos", "", "AGOS/r/ctl/jobs", "zenoh/agos/r"])
def test_run_of_rejects_non_agos_keys(key: str) -> None:
    with pytest.raises(ValueError, match="not an agos key"):
        keys.run_of(key)


def test_parse_slot_names_every_part_of_built_keys() -> None:
    assert keys.parse_slot(keys.obs(RUN, W, "uav")) == keys.SlotKey(RUN, W, "obs", ("uav",), False)
    assert keys.parse_slot(keys.coord_view(RUN, W, "ugv")) == keys.SlotKey(RUN, W, "coord", ("view", "ugv"), False)
    assert keys.parse_slot(keys.message(RUN, W, "ugv", "uav")).args == ("ugv", "uav")
    assert keys.parse_slot(keys.result(RUN, W)) == keys.SlotKey(RUN, W, "result", (), False)
    assert keys.parse_slot(keys.viz_frame(RUN, W, "uav")) == keys.SlotKey(RUN, W, "frame", ("uav",), True)
    assert keys.parse_slot(keys.viz_coord(RUN, W)).kind == "coord"
    with pytest.raises(ValueError, match="not a slot key"):
        keys.parse_slot(keys.live(RUN, "world", W))


def test_ready_of_reads_a_ready_token() -> None:
    ready = keys.ready_of(keys.slot_ready(RUN, W, "ugv", "ugv-9-ff00"))
    assert ready == ("ugv", "ugv-9-ff00") and ready.role == "ugv" and ready.agent == "ugv-9-ff00"
    for other in (keys.obs(RUN, W, "uav"), keys.slot_live(RUN, W), keys.viz_frame(RUN, W, "uav"), keys.jobs(RUN)):
        with pytest.raises(ValueError):
            keys.ready_of(other)


def test_live_of_reads_a_process_token() -> None:
    token = keys.live_of(keys.live(RUN, "agent", "uav-12-ab01"))
    assert token == keys.LiveToken(RUN, "agent", "uav-12-ab01") and token.ident == "uav-12-ab01"
    assert keys.live_of(keys.live(RUN, "world", W)).kind == "world"
    for other in (keys.slot_live(RUN, W), keys.router_live("z1"), keys.manifest(RUN), "agos/r/live/world/w/x"):
        with pytest.raises(ValueError, match="not a liveliness token"):
            keys.live_of(other)


def test_asset_of_reads_and_checks_the_hash() -> None:
    assert keys.asset_of(keys.asset("ab" * 32)) == "ab" * 32
    with pytest.raises(ValueError, match="asset hash"):
        keys.asset_of(keys.asset("*"))
    for other in (keys.manifest(RUN), "agos/assets/a/b", "other/assets/ab"):
        with pytest.raises(ValueError, match="not an asset key"):
            keys.asset_of(other)


def test_leaf_is_the_last_segment() -> None:
    assert [keys.leaf(k) for k in (keys.manifest(RUN), keys.lease(RUN), keys.result(RUN, W), keys.obs(RUN, W, "uav"))] \
        == ["manifest", "lease", "result", "uav"]
