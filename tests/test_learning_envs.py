"""The learning interfaces (agos/pettingzoo.py, agos/gymnasium.py, agos/spaces.py): PettingZoo's own
``parallel_api_test`` and ``parallel_seed_test`` (the latter on generated episodes, seeded by
``reset(seed=...)``), Gymnasium's ``check_env`` on a role with a partner, the action mask against the
world's own legality check, the index mapping both ways, rewards and ends, and the no-op mask of a
role not asked. Flat look, 64-pixel images and short budgets keep it to seconds.
"""

from __future__ import annotations

import importlib
import sys
import warnings

import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env
from pettingzoo.test import parallel_api_test, parallel_seed_test

from agos import episode_config
from agos.agents.registry import make_policy
from agos.env import EnvStateError, action_problem
from agos.gymnasium import RoleEnv
from agos.pettingzoo import STEP_COST, parallel_env
from agos.runtime.schemas import Observation
from agos.spaces import ACTION_NAMES, STATE_FIELDS, action_count, action_from_index, index_of
from agos.world.episodes.sampling import sample_episode
from agos.world.sim.scene import Scene
from agos.world.towns.asset import open_town

from support.episodes import SMALL_CAMERAS

ASKED = STATE_FIELDS.index("asked")


@pytest.fixture(scope="module")
def scene():
    """grid-s7 in the flat look, for one environment at a time."""
    with Scene(open_town("grid-s7").layout, look="flat") as built:
        yield built


@pytest.fixture(scope="module")
def episodes(scene):
    """Two mid episodes of grid-s7 (flat): the oracle's UAV annotates in the first decision."""
    return [sample_episode(open_town("grid-s7"), scene, "mid", k, seed=2, stream=1) for k in range(2)]


def _config(budget: int = 12, **tools):
    return episode_config(look="flat", decision_budget=budget, cameras=SMALL_CAMERAS, **tools)


def test_pettingzoo_parallel_api_test_passes(episodes, scene) -> None:
    env = parallel_env(episodes, _config(), scene=scene)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # PettingZoo's test warns about what it does not assert
        parallel_api_test(env, num_cycles=100)
    env.close()


def test_pettingzoo_parallel_seed_test_passes_on_generated_episodes() -> None:
    parallel_seed_test(lambda: parallel_env(config=_config(), difficulties=["easy"]))


def test_gymnasium_check_env_passes_for_a_role_with_a_partner(episodes, scene) -> None:
    env = RoleEnv("ugv", partner="oracle", episodes=episodes[:1], config=_config(), scene=scene)
    assert env.parallel.config.tools.oracle  # the partner's world-side tool is on
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        check_env(env, skip_render_check=True)
    env.close()


def test_the_mask_is_the_worlds_legality_and_indices_map_both_ways(episodes, scene) -> None:
    """Every observation of an oracle episode and of a heuristic one: an index is in the mask exactly
    when agos.Env would accept its action, and each action the policies took maps to an index that
    names it back (messages aside)."""
    seen: list[Observation] = []
    for policy in ("oracle", "heuristic"):
        env = parallel_env(episodes[:1], _config(10, policies=policy), text=False, scene=scene)
        policies = {role: make_policy(policy, role) for role in env.possible_agents}
        obs, _ = env.reset(seed=0)
        while env.agents:
            actions = {}
            for role, o in env.pending.items():
                seen.append(o)
                mask = obs[role]["action_mask"]
                for index in range(action_count(role)):
                    assert bool(mask[index]) == (action_problem(o, action_from_index(o, index)) is None), \
                        (role, index, ACTION_NAMES[role][index], o.legal_actions)
                actions[role] = policies[role].act(o)
                index = index_of(o, actions[role])
                assert index is not None and mask[index]
                back = action_from_index(o, index)
                assert (back.action, back.waypoint_id, back.cell) == \
                    (actions[role].action, actions[role].waypoint_id, (actions[role].cell or "").upper() or None)
            obs, *_ = env.step_actions(actions)
        env.close()
    assert {"ANNOTATE_CANDIDATE", "GO_TO_CANDIDATE", "MOVE_TO_UAV_WAYPOINT"} <= \
        {a for o in seen for a in o.legal_actions}


def test_rewards_ends_infos_and_the_no_op_mask(episodes, scene) -> None:
    sparse = parallel_env(episodes[:1], _config(policies="oracle"), scene=scene)
    shaped = parallel_env(episodes[:1], _config(policies="oracle"), reward="shaped", scene=scene)
    totals = []
    for env in (sparse, shaped):
        policies = {role: make_policy("oracle", role) for role in env.possible_agents}
        obs, infos = env.reset(seed=0)
        assert "[image: aerial_grid]" in infos["uav"]["text"] and "Legal actions now:" in infos["ugv"]["text"]
        total = dict.fromkeys(env.possible_agents, 0.0)
        while env.agents:
            idle = [r for r in env.possible_agents if r not in env.pending]
            obs, rewards, terminations, truncations, infos = env.step_actions(
                {role: policies[role].act(o) for role, o in env.pending.items()})
            for role in idle:  # not asked: its last picture, the no-op mask, and nothing applied
                assert obs[role]["action_mask"].tolist() == [1] + [0] * (action_count(role) - 1)
                assert obs[role]["state"][ASKED] == 0.0 and infos[role]["applied"] is None
            total = {role: total[role] + rewards[role] for role in total}
        assert terminations == {"uav": True, "ugv": True} and truncations == {"uav": False, "ugv": False}
        assert infos["ugv"]["termination"] == "confirmed" and infos["ugv"]["success"]
        assert env.record.success
        totals.append((total, env.record))
        with pytest.raises(EnvStateError, match=r"after the episode ended \(no agents left\): call reset\(\)"):
            env.step({})
        env.close()
    (sparse_total, _), (shaped_total, record) = totals
    assert sparse_total == {"uav": 1.0, "ugv": 1.0}
    decisions = {"uav": record.decisions_uav, "ugv": record.decisions_ugv}
    for role in ("uav", "ugv"):  # each role: its step costs, the first sight of the target, the success
        assert shaped_total[role] == pytest.approx(1.0 + 0.2 - STEP_COST * decisions[role])


def test_an_index_outside_the_mask_is_the_worlds_counted_wait(episodes, scene) -> None:
    env = parallel_env(episodes[:1], _config(), text=False, scene=scene)
    obs, _ = env.reset(seed=0)
    ugv = env.pending["ugv"]
    move = action_count("ugv") - 1  # the last road slot: no option there
    assert obs["ugv"]["action_mask"][move] == 0
    with pytest.raises(ValueError, match=r"ugv action index 17 is outside Discrete\(17\)"):
        action_from_index(ugv, 17)
    _, _, terminations, _, infos = env.step({"uav": 0, "ugv": move})
    assert infos["ugv"]["applied"] == "WAIT" and "is not a road option now" in infos["ugv"]["fallback_reason"]
    assert not any(terminations.values()) and env.agents == ["uav", "ugv"]
    env.close()


def test_observations_hold_the_images_the_world_rendered(episodes, scene) -> None:
    env = parallel_env(episodes[:1], _config(), depth=True, semantic=True, text=False, scene=scene)
    obs, _ = env.reset(seed=0)
    uav, ugv = obs["uav"], obs["ugv"]
    assert uav["rgb"].shape == (64, 64, 3) and uav["depth"].shape == uav["semantic"].shape == (64, 64)
    assert ugv["rgb"].shape == (6, 64, 64, 3) and ugv["depth"].shape == (6, 64, 64)
    assert ugv["rgb"][1].any() and not ugv["rgb"][0].any()  # driving: the forward view in the front slot
    assert 70.0 < float(np.median(uav["depth"])) < 90.0  # the nadir camera flies about 80 m up
    assert uav["reference"].shape == (5, 32, 32, 3) and uav["reference"].any() and uav["map"].shape == (64, 64, 3)
    assert uav["state"][ASKED] == 1.0 and uav["waypoints"][:, 3].sum() == len(env.pending["uav"].waypoint_options)
    for role in ("uav", "ugv"):
        assert obs[role] in env.observation_space(role)
    env.close()


def test_without_the_learn_extra_the_import_says_what_to_install(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setitem(sys.modules, "gymnasium", None)  # None: as if not installed
    monkeypatch.delitem(sys.modules, "agos.spaces")  # imported afresh (put back after the test)
    with pytest.raises(ModuleNotFoundError, match=r"need gymnasium: pip install 'agos\[learn\]'"):
        importlib.import_module("agos.spaces")


@pytest.mark.parametrize("role", ["uav", "ugv"])
def test_gymnasium_make_builds_each_role_and_check_env_passes(role: str, episodes, scene) -> None:
    """``gymnasium.make("agos/UAV-v0")`` and ``("agos/UGV-v0")``: the registry's role, the caller's
    keyword arguments passed on; Gymnasium's own checker on the made environment."""
    import gymnasium

    import agos.gymnasium

    gymnasium.register_envs(agos.gymnasium)
    env = gymnasium.make(agos.gymnasium.ENV_IDS[role], partner="heuristic", episodes=episodes[:1], config=_config(),
                         scene=scene)
    assert isinstance(env.unwrapped, RoleEnv) and env.unwrapped.role == role
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        check_env(env.unwrapped, skip_render_check=True)
    obs, _ = env.reset(seed=1)
    obs, *_ = env.step(int(np.flatnonzero(obs["action_mask"])[0]))
    assert env.observation_space.contains(obs)
    env.close()
    made = gymnasium.make(f"agos.gymnasium:{agos.gymnasium.ENV_IDS[role]}", episodes=episodes[:1], config=_config(),
                          scene=scene)
    assert made.spec is not None and made.spec.kwargs["role"] == role
    made.close()
