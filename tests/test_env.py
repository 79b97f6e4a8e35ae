"""agos.Env (agos/env.py): the same record as the process path for every scripted policy on two link
profiles, the configuration agos eval would build, one-line errors for calls out of order and for
illegal actions (nothing applied), the world's counted WAIT with ``illegal="wait"``, episode files.

The process path here is a world worker and two agent services over the in-memory bus
(tests/support/bus_path.py: every message encoded and read back as over zenoh); flat look, small
images and a short budget keep each pair of episodes to a second or two.
"""

from __future__ import annotations

from pathlib import Path

import msgspec
import pytest

from agos import Env, EnvStateError, IllegalActionError, episode_config
from agos.agents.contract import Policy, action_for
from agos.agents.registry import make_policy
from agos.deploy.run.configure import run_episode_config as eval_config
from agos.runtime.episode_config import EpisodeConfig
from agos.runtime.schemas import Action, EpisodeRecord, Observation, Role
from agos.runtime.settings import AgosConfig
from agos.world.episodes.files import EpisodeFileError, write_episodes
from agos.world.episodes.sampling import sample_episode
from agos.world.sim.scene import Scene, pb
from agos.world.towns.asset import open_town

from support.bus_path import BusPath
from support.episodes import SMALL_CAMERAS

BUDGET = 10
VOLATILE = ("run_id", "worker_id", "wall_time_s", "provenance")
"""What differs between two plays of one episode anywhere (docs/LIBRARY.md), and what made the record (the
commit may move on between two plays on a working checkout)."""


@pytest.fixture(scope="module")
def world():
    """grid-s7 in the flat look, and a mid episode of it (its UAV annotates within the budget)."""
    town = open_town("grid-s7")
    with Scene(town.layout, look="flat") as scene:
        yield town, scene, sample_episode(town, scene, "mid", 0, seed=2, stream=1)


@pytest.fixture(scope="module")
def bus_path(tmp_path_factory):
    with pytest.MonkeyPatch.context() as patch, BusPath() as path:
        patch.setenv("AGOS_HEALTH_DIR", str(tmp_path_factory.mktemp("health")))
        yield path


def _summary(record: EpisodeRecord) -> dict:
    return {k: v for k, v in msgspec.to_builtins(record).items() if k not in VOLATILE}


@pytest.mark.parametrize("link", ["ideal", "lossy"])
@pytest.mark.parametrize("policy", ["heuristic", "oracle", "expert", "random"])
def test_the_env_gives_the_record_of_the_process_path(policy: str, link: str, world, bus_path: BusPath) -> None:
    town, scene, spec = world
    config = episode_config(policies=policy, comm=link, look="flat", decision_budget=BUDGET, cameras=SMALL_CAMERAS)
    settings = AgosConfig(world=EpisodeConfig(look="flat", cameras=SMALL_CAMERAS))  # what agos eval builds from them
    assert config == eval_config(settings, policies={"uav": policy, "ugv": policy}, comm=link, decision_budget=BUDGET)
    with Env(spec, config, scene=scene, town=town) as env:
        record = env.play({r: make_policy(policy, r) for r in ("uav", "ugv")})
    over_bus = bus_path.play(spec, config, {"uav": policy, "ugv": policy})
    assert (record.status, over_bus.status) == ("finished", "finished")
    assert record.comm_profile == link and record.step_log
    assert _summary(record) == _summary(over_bus)


def test_an_episode_played_again_gives_the_same_record(world) -> None:
    """The second play reuses the first one's setup renders (references, SPL's path): the same record."""
    town, scene, spec = world
    with Env(spec, episode_config(policies="oracle", look="flat", decision_budget=BUDGET, cameras=SMALL_CAMERAS), scene=scene,
             town=town) as env:
        first, second = (_summary(env.play({r: make_policy("oracle", r) for r in ("uav", "ugv")})) for _ in range(2))
    assert first == second and first["termination"] == "confirmed"


def test_play_takes_one_source_for_both_roles_keeps_what_was_asked_and_abandons_on_an_error(world) -> None:
    """``play`` with a DecisionSource (one object answering every role asked), ``seen`` and
    ``worker_id``; a policy's exception abandons the episode: propagated, its vehicles out of the
    scene, each policy told the end, the Env ready for the next reset."""
    town, scene, spec = world
    config = episode_config(look="flat", decision_budget=4, cameras=SMALL_CAMERAS)

    class Both:  # a central controller: WAIT for every role asked
        def decide(self, observations: dict[Role, Observation]) -> dict[Role, Action | None]:
            return {role: action_for(obs, "WAIT") for role, obs in observations.items()}

    ended: list[str] = []

    class Failing(Policy):
        def act(self, obs: Observation) -> Action:
            raise RuntimeError(f"{self.role} cannot decide")

        def end_episode(self, episode_id: str) -> None:
            ended.append(self.role)

    bodies = pb.getNumBodies(physicsClientId=scene.client)
    seen: list[Observation] = []
    with Env(spec, config, worker_id="me", scene=scene, town=town) as env:
        record = env.play(Both(), seen=seen)
        assert (record.worker_id, record.termination, record.fallbacks) == ("me", "budget_exhausted", 0)
        assert [(o.role, o.decision_index) for o in seen][:2] == [("uav", 1), ("ugv", 1)] and len(seen) == 4
        with pytest.raises(RuntimeError, match="uav cannot decide"):
            env.play({r: Failing(r) for r in ("uav", "ugv")})
        assert ended == ["uav", "ugv"] and not env.pending and not env.done
        assert pb.getNumBodies(physicsClientId=scene.client) == bodies
        assert env.play(Both()).termination == "budget_exhausted"


def test_calls_out_of_order_say_which_call_comes_next(world) -> None:
    town, scene, spec = world
    env = Env(spec, episode_config(look="flat", decision_budget=2, cameras=SMALL_CAMERAS), scene=scene, town=town)
    with pytest.raises(EnvStateError, match=r"step\(\) before reset\(\): call reset\(\) first"):
        env.step({})
    with pytest.raises(EnvStateError, match="no episode has ended yet"):
        _ = env.record
    first = env.reset()
    assert sorted(first) == ["uav", "ugv"] and env.pending.keys() == first.keys()
    result = env.step({role: env.action(role, "WAIT") for role in first})
    assert result.done and result.record is env.record and env.record.termination == "budget_exhausted"
    assert [e.role for e in result.events] == ["uav", "ugv"] and not env.pending
    with pytest.raises(EnvStateError, match=r"is over \(budget_exhausted\): call reset\(\)"):
        env.step({})
    again = env.reset()  # the same episode from its start
    assert again["uav"].decision_index == 1 and again["uav"].pose == first["uav"].pose
    env.close()
    env.close()  # a second close does nothing
    with pytest.raises(EnvStateError, match=r"reset\(\) after close\(\)"):
        env.reset()
    assert scene.client >= 0, "an Env never closes a scene it was given"


def test_an_illegal_action_is_refused_in_one_line_and_nothing_is_applied(world) -> None:
    town, scene, spec = world
    with Env(spec, episode_config(look="flat", cameras=SMALL_CAMERAS), scene=scene, town=town) as env:
        obs = env.reset()
        uav, ugv = env.action("uav", "WAIT"), env.action("ugv", "WAIT")
        refusals = {
            "CONFIRM is not legal now": {"uav": env.action("uav", "CONFIRM"), "ugv": ugv},
            "waypoint 'U0_0x' is not an option now": {"uav": env.action("uav", "MOVE_TO_UAV_WAYPOINT",
                                                                         waypoint_id="U0_0x"), "ugv": ugv},
            "grid cell 'F9' is not one of A1..E5": {"uav": env.action("uav", "ANNOTATE_CANDIDATE", cell="F9"), "ugv": ugv},
            "ugv decision 1: no action given": {"uav": uav},
            "answers decision uav#2": {"uav": msgspec.structs.replace(uav, decision_index=2), "ugv": ugv},
        }
        for expected, actions in refusals.items():
            with pytest.raises(IllegalActionError, match=expected) as refused:
                env.step(actions)
            assert "\n" not in str(refused.value)
        assert env.pending == obs  # nothing applied: the same round is still asked
        move = env.action("uav", "MOVE_TO_UAV_WAYPOINT", waypoint_id=obs["uav"].waypoint_options[0].waypoint_id)
        result = env.step({"uav": move, "ugv": env.action("ugv", "STOP_OBSERVE")})
        assert [e.applied for e in result.events] == ["MOVE_TO_UAV_WAYPOINT", "STOP_OBSERVE"]
        assert list(result.observations) == ["ugv"]  # its 2 s stop is over, the UAV still flies
        with pytest.raises(IllegalActionError, match=r"uav not asked this round \(asked: ugv\)"):
            env.step({"ugv": env.action("ugv", "WAIT"), "uav": uav})
        with pytest.raises(IllegalActionError, match="REJECT: candidate 'C001' is not one the UGV holds open"):
            env.step({"ugv": env.action("ugv", "REJECT", candidate_id="C001")})
        result = env.step({"ugv": None})  # None: no action, the world's counted WAIT
        assert [(e.applied, e.fallback_reason) for e in result.events] == [("WAIT", "no action before the deadline")]


def test_with_illegal_wait_an_illegal_action_is_the_worlds_counted_wait(world) -> None:
    town, scene, spec = world
    with Env(spec, episode_config(look="flat", decision_budget=2, cameras=SMALL_CAMERAS), scene=scene, town=town,
             illegal="wait") as env:
        env.reset()
        result = env.step({"uav": env.action("uav", "CONFIRM"), "ugv": env.action("ugv", "WAIT")})
    assert result.events[0].applied == "WAIT" and "CONFIRM is not legal now" in (result.events[0].fallback_reason or "")
    assert env.record.fallbacks == 1
    with pytest.raises(ValueError, match="illegal='skip'"):
        Env(spec, illegal="skip", scene=scene, town=town)  # type: ignore[arg-type]


def test_an_episode_file_and_an_index(world, tmp_path: Path) -> None:
    town, scene, spec = world
    other = msgspec.structs.replace(spec, episode_id="grid-s7-mid-001-v1", seed=spec.seed + 1)
    write_episodes(tmp_path / "eps.jsonl", [spec, other])
    config = episode_config(look="flat", decision_budget=1, cameras=SMALL_CAMERAS)
    with Env(tmp_path / "eps.jsonl", config, index=1, scene=scene, town=town) as env:
        assert env.spec == other and env.reset()["uav"].episode_id == other.episode_id
    with pytest.raises(IndexError, match=r"eps.jsonl: episode index 2 out of range \(the file has 2 episodes: 0..1\)"):
        Env(tmp_path / "eps.jsonl", config, index=2, scene=scene, town=town)
    (tmp_path / "bad.jsonl").write_text("{}\n")
    with pytest.raises(EpisodeFileError, match=r"bad\.jsonl:1"):
        Env(tmp_path / "bad.jsonl", config, scene=scene, town=town)
    with pytest.raises(ValueError, match="the scene was built with look 'flat' but the configuration's look is 'rich'"):
        Env(spec, EpisodeConfig(), scene=scene, town=town)


def test_a_noisy_robot_on_a_faulty_link_gives_the_record_of_the_process_path(world, bus_path: BusPath,
                                                                            tmp_path: Path) -> None:
    """Localisation error (a degraded zone too) and duplicated, garbled messages: the same seed gives the
    same record in one process as over the bus with the world and agents in their own processes."""
    town, scene, spec = world
    faulty = tmp_path / "faulty.toml"
    faulty.write_text("[latency]\nmean_s = 0.05\n[duplicate]\np = 0.2\n[corruption]\nchar_error_rate = 0.05\n")
    config = episode_config(policies="heuristic", comm=faulty, look="flat", decision_budget=BUDGET, cameras=SMALL_CAMERAS,
                            pose_error="urban-gnss")
    with Env(spec, config, scene=scene, town=town) as env:
        record = env.play({r: make_policy("heuristic", r) for r in ("uav", "ugv")})
    over_bus = bus_path.play(spec, config, {"uav": "heuristic", "ugv": "heuristic"})
    assert record.pose_error and record.link is not None and record.link.duplicated > 0
    assert _summary(record) == _summary(over_bus)
