"""agos.vector: two environments in subprocesses, in lockstep (make_vector_env: Gymnasium's
AsyncVectorEnv over agos.gymnasium.RoleEnv) and asynchronously (AsyncEnvPool: send to some, recv
whichever answered); each resets itself when its episode ends, an error names its environment, and
close stops the processes, a stuck one too. The throughput of 2 against 1 is a benchmark
(bench/bench_env.py), not a test."""

from __future__ import annotations

import time
from typing import Any

import numpy as np
import pytest

from agos import episode_config
from agos.env import EnvStateError
from agos.vector import AsyncEnvPool, EnvWorkerError, make_vector_env
from agos.world.episodes.sampling import sample_episode
from agos.world.sim.scene import Scene
from agos.world.towns.asset import open_town

from support.episodes import SMALL_CAMERAS
from support.stalling import Stalling

pytestmark = pytest.mark.e2e


@pytest.fixture(scope="module")
def small() -> dict[str, Any]:
    """RoleEnv arguments: two easy grid-s7 episodes, 64-pixel images, a 4-decision budget."""
    town = open_town("grid-s7")
    with Scene(town.layout, look="flat") as scene:
        specs = [sample_episode(town, scene, "easy", k, seed=5) for k in range(2)]
    config = episode_config(look="flat", decision_budget=4,
                            cameras=SMALL_CAMERAS)
    return {"role": "ugv", "episodes": specs, "config": config, "text": False}


def test_two_environments_in_subprocesses_step_and_reset_on_their_own(small: dict[str, Any]) -> None:
    envs = make_vector_env(2, partner="heuristic", **small)
    try:
        obs, _ = envs.reset(seed=0)
        assert obs["rgb"].shape == (2, 6, 64, 64, 3) and obs["action_mask"].shape == (2, 17)
        assert obs["rgb"][:, 1].any(axis=(1, 2, 3)).all()  # each world rendered its UGV's forward view
        ended, restarted = np.zeros(2, bool), np.zeros(2, bool)
        for _ in range(8):  # a 4-decision budget, both roles deciding: each episode ends within a few steps
            actions = np.array([envs.single_action_space.sample(mask=obs["action_mask"][i]) for i in range(2)])
            just_ended = ended.copy()
            obs, rewards, terminations, truncations, _ = envs.step(actions)
            restarted |= just_ended & (obs["state"][:, -1] == 1.0)  # the step after its end: reset, asked again
            ended = terminations | truncations
            assert rewards.shape == (2,) and np.isin(rewards, (0.0, 1.0)).all()
        assert restarted.all()
    finally:
        envs.close()
    assert envs.closed


def test_pool_steps_whichever_environment_answered_resets_and_names_a_failing_one(small: dict[str, Any]) -> None:
    with AsyncEnvPool(2, partner="heuristic", **small) as pool:
        pool.reset(seed=0)
        ready = pool.recv(min_envs=2)
        assert ready.env_ids.tolist() == [0, 1] and ready.observations["rgb"].shape == (2, 6, 64, 64, 3)
        assert (ready.rewards == 0).all() and not (ready.terminations | ready.truncations).any()
        space, ended, restarted, answers = pool.single_action_space, set(), set(), 0

        def step_those_ready() -> Any:
            nonlocal answers
            pool.send([space.sample(mask=m) for m in ready.observations["action_mask"]], ready.env_ids)
            with pytest.raises(EnvStateError, match=f"env {ready.env_ids[-1]} is still stepping"):
                pool.send([0], ready.env_ids[-1:])
            answered = pool.recv()
            answers += len(answered.env_ids)
            for row, env_id in enumerate(answered.env_ids.tolist()):
                if env_id in ended:  # its action was ignored: the new episode's first observation
                    assert answered.observations["state"][row, -1] == 1.0 and answered.rewards[row] == 0.0
                    restarted.add(env_id)
                ended.discard(env_id)
                if answered.terminations[row] or answered.truncations[row]:
                    ended.add(env_id)
            return answered

        # A 4-decision budget ends each episode within a few of its steps, but which environment answers
        # first is the machine's choice: step until both have restarted (200 rounds: a hang bound only).
        for _ in range(200):
            ready = step_those_ready()
            if restarted == {0, 1} and answers >= 10:
                break
        assert restarted == {0, 1} and answers >= 10
        while all(i in ended for i in ready.env_ids.tolist()):  # an action to these would only reset them
            ready = step_those_ready()
        stepping = next(i for i in ready.env_ids.tolist() if i not in ended)
        pool.send([999], [stepping])  # outside Discrete(17): RoleEnv raises in the subprocess
        with pytest.raises(EnvWorkerError, match=f"^env {stepping}: ValueError: ugv action index 999") as error:
            pool.recv(min_envs=2)  # the other environment's answer, if it is stepping, and this one's error
        assert error.value.env_id == stepping and "action_from_index" in error.value.worker_traceback
        assert pool.closed and not any(p.is_alive() for p in pool.processes)


def test_pool_close_does_not_hang_on_a_stuck_environment(small: dict[str, Any]) -> None:
    pool = AsyncEnvPool(1, close_timeout_s=0.5, partner=Stalling("uav"), **small)
    pool.reset(seed=0)
    pool.recv()
    pool.send([0], [0])  # the partner is asked too, and never answers
    with pytest.raises(TimeoutError, match=r"still stepping: \[0\]"):
        pool.recv(timeout_s=0.5)
    hang_bound_s = 30.0  # a hang, not a speed: close gives a stuck environment close_timeout_s (0.5 s), then ends it
    started = time.monotonic()
    pool.close()
    assert time.monotonic() - started < hang_bound_s and not pool.processes[0].is_alive()
    with pytest.raises(EnvStateError, match="closed"):
        pool.send([0], [0])
