"""The random policy: a uniformly random legal action with random arguments.

Seeded by (episode id, role, decision index), so a run is reproducible. A floor for every metric.
"""

from __future__ import annotations

import zlib

import numpy as np

from agos.agents.contract import Policy, action_for
from agos.runtime.schemas import Action, Observation, Role


class RandomPolicy(Policy):
    name = "random"
    inline = True  # microseconds, no I/O: answered on the receiving thread (agents/agent_service.py)

    def __init__(self, role: Role) -> None:
        self.role = role

    def end_episode(self, episode_id: str) -> None:
        pass

    def act(self, obs: Observation) -> Action:
        rng = np.random.default_rng([zlib.crc32(obs.episode_id.encode()), 0 if obs.role == "uav" else 1, obs.decision_index])
        name = str(rng.choice(obs.legal_actions))
        active = next((c for c in obs.coordination.candidates if c.status in ("pending", "arrived")), None)
        if name in ("MOVE_TO_UAV_WAYPOINT", "MOVE_TO_ROAD_WAYPOINT"):
            return action_for(obs, name, waypoint_id=str(rng.choice([w.waypoint_id for w in obs.waypoint_options])))
        if name == "ANNOTATE_CANDIDATE":
            return action_for(obs, name, cell=f"{obs.grid_rows[int(rng.integers(len(obs.grid_rows)))]}"
                                               f"{int(rng.integers(obs.grid_cols)) + 1}")
        if name in ("GO_TO_CANDIDATE", "REJECT") and active is not None:
            return action_for(obs, name, candidate_id=active.candidate_id)
        return action_for(obs, name)
