"""A stand-in policy with a fixed decision latency, for benchmarks and fault tests.

``standin-200ms`` waits 200 ms (asynchronously, like a remote model) and then takes a plain
legal action: the first waypoint option if it may move, else WAIT. It never looks at images.
Not to be confused with ``agos vlm-standin`` (:mod:`agos.agents.vlm.standin`), a stand-in *model
server* that VLM policies ask over HTTP; this is a policy of its own that asks nothing.
"""

from __future__ import annotations

import asyncio
import time

from agos.agents.contract import Policy, action_for
from agos.runtime.schemas import Action, Observation, Role


class FixedLatencyPolicy(Policy):
    name = "standin"

    def __init__(self, role: Role, latency_s: float) -> None:
        self.role, self.latency_s = role, latency_s
        self.inline = latency_s == 0  # standin-0ms: answered on the receiving thread (agents/agent_service.py)

    def _choose(self, obs: Observation) -> Action:
        move = "MOVE_TO_UAV_WAYPOINT" if obs.role == "uav" else "MOVE_TO_ROAD_WAYPOINT"
        if move in obs.legal_actions and obs.waypoint_options:
            return action_for(obs, move, waypoint_id=obs.waypoint_options[0].waypoint_id)
        return action_for(obs, "WAIT")

    async def act_async(self, obs: Observation) -> Action:
        if self.latency_s > 0:  # standin-0ms answers at once, without a pass through the event loop
            await asyncio.sleep(self.latency_s)
        return self._choose(obs)

    def act(self, obs: Observation) -> Action:
        if self.latency_s > 0:  # time.sleep(0) still gives up the CPU: tens of microseconds
            time.sleep(self.latency_s)
        return self._choose(obs)

    def end_episode(self, episode_id: str) -> None:
        pass
