"""A random policy's loop over ``agos.Env`` (docs/LIBRARY.md): each role asked takes a uniformly random
legal action with a random argument, until the episode ends.

    python -m examples.random_loop                      # a generated easy episode of grid-s7
    python -m examples.random_loop --episodes split.jsonl --index 3 --look flat
"""

from __future__ import annotations

import argparse
import random

from agos import Env, episode_config
from agos.runtime.episode_config import EpisodeConfig
from agos.runtime.schemas import Action, EpisodeRecord, Observation

CELLS = [f"{row}{col}" for row in "ABCDE" for col in range(1, 6)]


def random_action(obs: Observation, rng: random.Random, env: Env) -> Action:
    """A legal action for ``obs``: a random name among ``legal_actions`` and a random argument."""
    name = rng.choice(obs.legal_actions)
    open_ids = [c.candidate_id for c in obs.coordination.candidates
                if c.status in ("pending", "arrived") and (name != "GO_TO_CANDIDATE" or c.approach_waypoint_id)]
    if name.startswith("MOVE_TO_"):
        return env.action(obs.role, name, waypoint_id=rng.choice(obs.waypoint_options).waypoint_id)
    if name == "ANNOTATE_CANDIDATE":
        return env.action(obs.role, name, cell=rng.choice(CELLS))
    if name == "GO_TO_CANDIDATE" and not open_ids:
        return env.action(obs.role, "WAIT")
    if name in ("GO_TO_CANDIDATE", "REJECT") and open_ids:
        return env.action(obs.role, name, candidate_id=open_ids[0])
    return env.action(obs.role, name)


def main(episodes: str | None = None, *, index: int = 0, seed: int = 0,
         config: EpisodeConfig | None = None) -> EpisodeRecord:
    """Play one episode (of a file, or generated with ``seed``) with random actions; its record."""
    rng = random.Random(seed)
    with Env(episodes, config, index=index) if episodes else Env.generated(seed=seed, config=config) as env:
        observations = env.reset()
        while observations:  # the roles asked this round
            actions = {role: random_action(obs, rng, env) for role, obs in observations.items()}
            observations = env.step(actions).observations
        return env.record


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--episodes", help="an episode file (default: a generated episode)")
    parser.add_argument("--index", type=int, default=0)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--look", choices=["flat", "rich"], default="rich")
    args = parser.parse_args()
    record = main(args.episodes, index=args.index, seed=args.seed, config=episode_config(look=args.look))
    print(f"{record.episode_id}: {record.termination} after {record.decisions_uav + record.decisions_ugv} decisions")
