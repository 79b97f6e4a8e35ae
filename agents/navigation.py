"""Greedy road navigation from local options, shared by policies that must approach a point
without road-graph path planning (the no_rgpp ablation, the oracle, the heuristic fallback).

Each option is scored by its straight-line distance to the goal, plus a penalty for anchors
already visited in the episode, so the agent does not shuttle between two anchors.
"""

from __future__ import annotations

import math

from agos.runtime.schemas import Observation

REVISIT_PENALTY_M = 25.0


class Navigator:
    def __init__(self) -> None:
        self._visited: dict[str, dict[str, int]] = {}
        self._stops: dict[str, set[tuple[int, int]]] = {}

    def forget(self, episode_id: str) -> None:
        self._visited.pop(episode_id, None)
        self._stops.pop(episode_id, None)

    def towards(self, obs: Observation, goal: tuple[float, float]) -> str | None:
        """The road option to take towards ``goal``; None without options."""
        if not obs.waypoint_options:
            return None
        visited = self._visited.setdefault(obs.episode_id, {})

        def score(w) -> tuple[float, str]:
            d = math.dist(w.position_world_m[:2], goal)
            return d + REVISIT_PENALTY_M * visited.get(w.waypoint_id, 0), w.waypoint_id

        best = min(obs.waypoint_options, key=score)
        visited[best.waypoint_id] = visited.get(best.waypoint_id, 0) + 1
        return best.waypoint_id

    def _cell(self, obs: Observation) -> tuple[int, int]:
        x, y = obs.pose.position_world_m[:2]
        return round(x / 10), round(y / 10)

    def mark_stopped(self, obs: Observation) -> None:
        self._stops.setdefault(obs.episode_id, set()).add(self._cell(obs))

    def stopped_here(self, obs: Observation) -> bool:
        return self._cell(obs) in self._stops.get(obs.episode_id, set())
