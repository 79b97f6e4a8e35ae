"""Navigation helpers of the scripted policies.

:class:`Navigator`: greedy road navigation from local options, for policies that must approach a
point without road-graph path planning (the no_rgpp ablation, the heuristic and oracle fallbacks).
Each option is scored by its straight-line distance to the goal, plus a penalty for anchors
already visited in the episode, so the agent does not shuttle between two anchors.

:func:`uav_route`: the shortest flight over the episode's active UAV nodes (the searchable area
every UAV observation lists), moving as the world lets a UAV move: to a node of the 3x3
neighbourhood. The active nodes need not form one connected piece, nor a convex one, so flying
"towards" a point one greedy step at a time can get stuck where this does not.
"""

from __future__ import annotations

import heapq
import math

from agos.runtime.schemas import Observation, Waypoint

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


def uav_route(nodes: list[Waypoint], start: str, goal: str, spacing_m: float) -> list[str] | None:
    """Node ids of the shortest flight from ``start`` to ``goal`` (both included) over ``nodes``,
    where a move reaches any node at most one ``spacing_m`` away along each axis (the grid's 3x3
    neighbourhood); ties by node id. None when ``goal`` cannot be reached."""
    xy = {w.waypoint_id: (w.position_world_m[0], w.position_world_m[1]) for w in nodes}
    if start not in xy or goal not in xy:
        return None
    reach = 1.01 * spacing_m
    best = {start: 0.0}
    before: dict[str, str] = {}
    heap = [(0.0, start)]
    while heap:
        dist, node = heapq.heappop(heap)
        if node == goal:
            route = [goal]
            while route[-1] != start:
                route.append(before[route[-1]])
            return route[::-1]
        if dist > best[node]:
            continue
        x, y = xy[node]
        for other, (ox, oy) in sorted(xy.items()):
            if other == node or abs(ox - x) > reach or abs(oy - y) > reach:
                continue
            d = dist + math.hypot(ox - x, oy - y)
            if d < best.get(other, math.inf) - 1e-9:
                best[other], before[other] = d, node
                heapq.heappush(heap, (d, other))
    return None
