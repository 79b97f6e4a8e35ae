"""Metric closures of the two roles' graphs, and the moves that realise a closure arc.

UAV: the active grid nodes, a move going to any node of the 3x3 neighbourhood (the world's
UAV options), its length the straight distance; a flight between two waypoints is the shortest
such chain (ties by node id), its time the length over the UAV's speed. UGV: the directed fine
road graph; a drive is the shortest road path, its time the length over the UGV's speed (the
world's timing, ``EpisodeConfig.uav_speed_mps`` / ``ugv_speed_mps``).
"""

from __future__ import annotations

import heapq
import math

import networkx as nx
import numpy as np

from agos.world.towns.roadgraph import RoadGraphs
from agos.world.towns.uavgrid import UavGrid


def uav_flight(grid: UavGrid, active: set[str], start: str) -> tuple[dict[str, float], dict[str, str]]:
    """Shortest flight lengths from ``start`` to every reachable active node, and each node's
    predecessor on its flight (Dijkstra over neighbour moves, ties by node id)."""
    best = {start: 0.0}
    before: dict[str, str] = {}
    heap = [(0.0, start)]
    done: set[str] = set()
    while heap:
        dist, node = heapq.heappop(heap)
        if node in done:
            continue
        done.add(node)
        here = grid.nodes[node].position_world_m
        for other in sorted(grid.neighbours(node, active)):
            there = grid.nodes[other].position_world_m
            d = dist + math.hypot(there[0] - here[0], there[1] - here[1])
            if d < best.get(other, math.inf) - 1e-9:
                best[other], before[other] = d, node
                heapq.heappush(heap, (d, other))
    return best, before


def uav_path(before: dict[str, str], start: str, goal: str) -> list[str]:
    """Node ids from ``start`` to ``goal`` (both included) on a flight tree of :func:`uav_flight`."""
    path = [goal]
    while path[-1] != start:
        path.append(before[path[-1]])
    return path[::-1]


def uav_times(grid: UavGrid, active: set[str], nodes: list[str], speed_mps: float) -> np.ndarray:
    """(n, n) flight times between ``nodes`` (inf where no flight exists)."""
    out = np.full((len(nodes), len(nodes)), np.inf)
    for i, a in enumerate(nodes):
        lengths, _ = uav_flight(grid, active, a)
        for j, b in enumerate(nodes):
            if b in lengths:
                out[i, j] = lengths[b] / speed_mps
    return out


def ugv_times(roads: RoadGraphs, nodes: list[int], speed_mps: float) -> np.ndarray:
    """(n, n) road driving times between ``nodes`` on the fine graph (inf where no path)."""
    out = np.full((len(nodes), len(nodes)), np.inf)
    for i, a in enumerate(nodes):
        lengths = nx.single_source_dijkstra_path_length(roads.fine, a, weight="length_m")
        for j, b in enumerate(nodes):
            if b in lengths:
                out[i, j] = lengths[b] / speed_mps
    return out


def distances_to(roads: RoadGraphs, goal: int) -> dict[int, float]:
    """Road distance from every node that can reach ``goal`` to it."""
    return nx.single_source_dijkstra_path_length(roads.fine.reverse(copy=False), goal, weight="length_m")
