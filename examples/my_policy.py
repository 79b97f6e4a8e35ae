"""Your own agent in about 30 lines: docs/AGENTS.md, "Write your own agent".

    agos eval --policy examples.my_policy:Explorer          # from the repository root
    agos eval --policy-uav heuristic --policy-ugv examples.my_policy:Explorer
    agos agent --role ugv --policy examples.my_policy:Explorer --connect tcp/HOST:PORT --run RUN
"""

from __future__ import annotations

from agos.agents.contract import Policy, action_for
from agos.runtime.schemas import Action, Observation, Role


class Explorer(Policy):
    """Each role moves to the waypoint option it has been sent to least often this episode, and
    waits when it may not move. It looks at no image: your perception goes in :meth:`act`."""

    name = "explorer"  # in logs and decision traces
    inline = True  # act takes microseconds and does no I/O: answered on the thread that received it

    def __init__(self, role: Role) -> None:
        super().__init__(role)
        self.visits: dict[str, dict[str, int]] = {}  # episode -> waypoint id -> times chosen

    def end_episode(self, episode_id: str) -> None:
        self.visits.pop(episode_id, None)  # the episode is over: forget it

    def act(self, obs: Observation) -> Action:
        move = "MOVE_TO_UAV_WAYPOINT" if obs.role == "uav" else "MOVE_TO_ROAD_WAYPOINT"
        if move not in obs.legal_actions or not obs.waypoint_options:
            return action_for(obs, "WAIT", rationale="may not move now")
        visits = self.visits.setdefault(obs.episode_id, {})
        choice = min(obs.waypoint_options, key=lambda w: visits.get(w.waypoint_id, 0))
        visits[choice.waypoint_id] = visits.get(choice.waypoint_id, 0) + 1
        return action_for(obs, move, waypoint_id=choice.waypoint_id, rationale=f"least visited: {choice.kind}")
