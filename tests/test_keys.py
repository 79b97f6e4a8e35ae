"""Key layout of agos/runtime/keys.py."""

from __future__ import annotations

import pytest

from agos.runtime import keys

RUN = "run-7.a_b"
EP = "grid-s7-easy-000-v1"


@pytest.mark.parametrize(
    ("key", "expected"),
    [
        (keys.manifest(RUN), "agos/run-7.a_b/ctl/manifest"),
        (keys.jobs(RUN), "agos/run-7.a_b/ctl/jobs"),
        (keys.obs(RUN, EP, "uav"), "agos/run-7.a_b/ep/grid-s7-easy-000-v1/obs/uav"),
        (keys.act(RUN, EP, "ugv"), "agos/run-7.a_b/ep/grid-s7-easy-000-v1/act/ugv"),
        (keys.coord_truth(RUN, EP), "agos/run-7.a_b/ep/grid-s7-easy-000-v1/coord/truth"),
        (keys.coord_view(RUN, EP, "uav"), "agos/run-7.a_b/ep/grid-s7-easy-000-v1/coord/view/uav"),
        (keys.message(RUN, EP, "uav", "ugv"), "agos/run-7.a_b/ep/grid-s7-easy-000-v1/msg/uav/ugv"),
        (keys.events(RUN, EP), "agos/run-7.a_b/ep/grid-s7-easy-000-v1/events"),
        (keys.result(RUN, EP), "agos/run-7.a_b/ep/grid-s7-easy-000-v1/result"),
        (keys.result_ack(RUN, EP), "agos/run-7.a_b/ep/grid-s7-easy-000-v1/ack"),
        (keys.live(RUN, "world", "w-01"), "agos/run-7.a_b/live/world/w-01"),
        (keys.live(RUN, "evaluator", "*"), "agos/run-7.a_b/live/evaluator/*"),
        (keys.asset("ab" * 32), "agos/assets/" + "ab" * 32),
        (keys.viz_events(RUN, EP), "agos/run-7.a_b/viz/grid-s7-easy-000-v1/events"),
        (keys.viz_coord(RUN, EP), "agos/run-7.a_b/viz/grid-s7-easy-000-v1/coord"),
        (keys.viz_frame(RUN, EP, "ugv"), "agos/run-7.a_b/viz/grid-s7-easy-000-v1/frame/ugv"),
        (keys.viz_prefix(RUN, EP), "agos/run-7.a_b/viz/grid-s7-easy-000-v1/"),
        (keys.episode_prefix(RUN, EP), "agos/run-7.a_b/ep/grid-s7-easy-000-v1/"),
        (keys.viz_all(), "agos/*/viz/**"),
        (keys.viz_all(RUN), "agos/run-7.a_b/viz/**"),
    ],
)
def test_key_layout(key: str, expected: str) -> None:
    assert key == expected


def test_wildcards_for_subscriptions() -> None:
    assert keys.manifest("*") == "agos/*/ctl/manifest"
    assert keys.result(RUN, "*") == "agos/run-7.a_b/ep/*/result"
    assert keys.events("*", "*") == "agos/*/ep/*/events"


def test_roles_constant() -> None:
    assert keys.ROLES == ("uav", "ugv")


BAD_IDS = ["a/b", "ru*n", "**", "a*", "two words", " lead", "dollar$", "$", "", "q?", "hash#"]


@pytest.mark.parametrize("bad", BAD_IDS)
def test_invalid_run_id_raises(bad: str) -> None:
    with pytest.raises(ValueError, match="run id"):
        keys.manifest(bad)
    with pytest.raises(ValueError, match="run id"):
        keys.obs(bad, EP, "uav")


@pytest.mark.parametrize("bad", BAD_IDS)
def test_invalid_episode_id_raises(bad: str) -> None:
    for build in (keys.coord_truth, keys.events, keys.result, keys.result_ack):
        with pytest.raises(ValueError, match="episode id"):
            build(RUN, bad)
    with pytest.raises(ValueError, match="episode id"):
        keys.act(RUN, bad, "ugv")
    with pytest.raises(ValueError, match="episode id"):
        keys.message(RUN, bad, "uav", "ugv")


@pytest.mark.parametrize("bad", ["a/b", "x*y", "sp ace", "d$"])
def test_invalid_live_id_raises(bad: str) -> None:
    with pytest.raises(ValueError):
        keys.live(RUN, "agent", bad)


def test_check_chunk_returns_value_and_names_what() -> None:
    assert keys.check_chunk("A-z_0.9", what="thing") == "A-z_0.9"
    with pytest.raises(ValueError, match=r"thing 'a b'"):
        keys.check_chunk("a b", what="thing")


def test_episode_of_and_run_of_parse_built_keys() -> None:
    for key in (
        keys.obs(RUN, EP, "uav"),
        keys.coord_view(RUN, EP, "ugv"),
        keys.message(RUN, EP, "ugv", "uav"),
        keys.result_ack(RUN, EP),
    ):
        assert keys.episode_of(key) == EP
        assert keys.run_of(key) == RUN
    assert keys.run_of(keys.manifest(RUN)) == RUN
    assert keys.run_of(keys.live(RUN, "orchestrator", "o1")) == RUN
    assert keys.episode_of("agos/r/ep/e1") == "e1"


@pytest.mark.parametrize(
    "key",
    ["other/r/ep/e/result", "agos/r/ctl/manifest", "agos/r/ep", "agos", "", "agos/r/live/world/w1"],
)
def test_episode_of_rejects_non_episode_keys(key: str) -> None:
    with pytest.raises(ValueError, match="not an episode key"):
        keys.episode_of(key)


@pytest.mark.parametrize("key", ["other/r/ctl/manifest", "agos", "", "AGOS/r/ctl/jobs", "zenoh/agos/r"])
def test_run_of_rejects_non_agos_keys(key: str) -> None:
    with pytest.raises(ValueError, match="not an agos key"):
        keys.run_of(key)
