"""agos's heuristic agents through the PettingZoo API (docs/LIBRARY.md): each asked role's heuristic
reads the world's observation (``env.pending``) and its action goes in as its action index
(``agos.spaces.index_of``; the messages it would send have no index and stay behind).

    python -m examples.heuristic_pettingzoo --seed 3
"""

from __future__ import annotations

import argparse

from agos.agents.registry import make_policy
from agos.pettingzoo import parallel_env
from agos.runtime.episode_config import EpisodeConfig
from agos.runtime.schemas import EpisodeRecord, Role
from agos.spaces import index_of


def main(*, seed: int = 0, config: EpisodeConfig | None = None) -> tuple[dict[Role, float], EpisodeRecord]:
    """One generated episode; each role's summed reward and the episode's record."""
    env = parallel_env(config=config)
    policies = {role: make_policy("heuristic", role) for role in env.possible_agents}
    observations, _ = env.reset(seed=seed)
    returns = dict.fromkeys(env.possible_agents, 0.0)
    while env.agents:
        actions = {}
        for role, obs in env.pending.items():  # the roles asked this round, as the world shows them
            index = index_of(obs, policies[role].act(obs))
            actions[role] = index if index is not None else 0  # 0: WAIT
            assert observations[role]["action_mask"][actions[role]]
        observations, rewards, _, _, _ = env.step(actions)  # terminations, truncations, infos
        returns = {role: returns[role] + rewards[role] for role in returns}
    record = env.record
    for policy in policies.values():
        policy.end_episode(record.episode_id)
    env.close()
    return returns, record


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seed", type=int, default=0)
    returns, record = main(seed=parser.parse_args().seed)
    print(f"{record.episode_id}: {record.termination}, returns {returns}")
