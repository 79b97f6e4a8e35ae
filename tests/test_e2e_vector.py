"""agos.vector.make_vector_env: two environments in subprocesses (Gymnasium's AsyncVectorEnv over
agos.gymnasium.RoleEnv) step together, each resets itself when its episode ends, and close stops the
processes. The throughput of 2 against 1 is a benchmark (bench/bench_env.py), not a test."""

from __future__ import annotations

import numpy as np
import pytest

from agos import episode_config
from agos.vector import make_vector_env
from agos.world.episodes.sampling import sample_episode
from agos.world.sim.scene import Scene
from agos.world.towns.asset import open_town

pytestmark = pytest.mark.e2e


def test_two_environments_in_subprocesses_step_and_reset_on_their_own() -> None:
    town = open_town("grid-s7")
    with Scene(town.layout, look="flat") as scene:
        specs = [sample_episode(town, scene, "easy", k, seed=5) for k in range(2)]
    config = episode_config(look="flat", decision_budget=4,
                            cameras={"nadir_px": 64, "ground_px": 64, "reference_px": 32, "map_px": 64})
    envs = make_vector_env(2, role="ugv", partner="heuristic", episodes=specs, config=config, text=False)
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
