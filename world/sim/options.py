"""Runtime feasible waypoint options (paper Appendix A.2).

UAV: the active nodes of the 3x3 neighbourhood of its nearest active node (at most 8).

UGV, from its current node on the fine graph:

* ``forward``: the next decision anchor on every branch (about 10 m of road);
* ``forward_far``: about 30 m along each branch, as long as the branch does not split;
* ``junction_exit``: when a junction entry lies within ``JUNCTION_LOOKAHEAD_M`` ahead, every exit
  of that junction (only manoeuvres that exist in the road graph);
* ``backward``: the anchor about 10 m back along the route actually driven, offered only when a
  legal (directed) path back exists, with that path's length.

Execution always follows the fine graph (:meth:`shortest_path`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import networkx as nx

from agos.world.towns.roadgraph import RoadGraphs
from agos.world.towns.uavgrid import UavGrid

NEAR_M = 10.0
FAR_M = 30.0
JUNCTION_LOOKAHEAD_M = 15.0
BACKWARD_M = 10.0
MAX_RETURN_PATH_M = 250.0


@dataclass(frozen=True)
class RoadOption:
    anchor: int
    path_length_m: float
    option: str
    """``forward``, ``forward_far``, ``junction_exit`` or ``backward``."""


def uav_options(grid: UavGrid, position_xy: tuple[float, float], active: set[str]) -> list[str]:
    centre = grid.nearest(position_xy, sorted(active))
    return grid.neighbours(centre, active)


def _next_anchors(roads: RoadGraphs, node: int) -> dict[int, float]:
    """Anchors reached first from ``node`` along every branch, with road distance."""
    if node in roads.anchors:
        return {n: roads.decision.edges[node, n]["length_m"] for n in roads.decision.successors(node)}
    out: dict[int, float] = {}
    frontier = [(node, 0.0)]
    seen = {node}
    while frontier:
        current, dist = frontier.pop()
        for nxt in roads.fine.successors(current):
            d = dist + roads.fine.edges[current, nxt]["length_m"]
            if nxt in roads.anchors:
                out[nxt] = min(out.get(nxt, d), d)
            elif nxt not in seen:
                seen.add(nxt)
                frontier.append((nxt, d))
    return out


def ugv_options(roads: RoadGraphs, node: int, route: list[int]) -> list[RoadOption]:
    options: dict[int, RoadOption] = {}

    def offer(anchor: int, length: float, kind: str) -> None:
        if anchor != node and (anchor not in options or options[anchor].path_length_m > length):
            options[anchor] = RoadOption(anchor, round(length, 3), kind)

    for nxt, length in sorted(_next_anchors(roads, node).items()):
        offer(nxt, length, "forward")
        far, total = nxt, length
        while total < FAR_M - NEAR_M / 2:
            succ = list(roads.decision.successors(far))
            if len(succ) != 1:
                break
            total += roads.decision.edges[far, succ[0]]["length_m"]
            far = succ[0]
        if far != nxt:
            offer(far, total, "forward_far")
    # junction exits when an entry is near ahead
    frontier = [(a, d) for a, d in _next_anchors(roads, node).items()] + ([(node, 0.0)] if node in roads.anchors else [])
    for anchor, dist in frontier:
        hops = [(anchor, dist)]
        while hops:
            a, d = hops.pop()
            if d > JUNCTION_LOOKAHEAD_M:
                continue
            if roads.anchors.get(a) == "junction_entry":
                for exit_ in roads.decision.successors(a):
                    offer(exit_, d + roads.decision.edges[a, exit_]["length_m"], "junction_exit")
            elif a != node or d == 0.0:
                succ = list(roads.decision.successors(a))
                if len(succ) == 1:
                    hops.append((succ[0], d + roads.decision.edges[a, succ[0]]["length_m"]))
    back = _backward_anchor(roads, route)
    if back is not None and back != node and back not in options:
        back_length: float | None
        try:
            back_length = nx.shortest_path_length(roads.fine, node, back, weight="length_m")
        except nx.NetworkXNoPath:
            back_length = None
        if back_length is not None and back_length <= MAX_RETURN_PATH_M:
            offer(back, back_length, "backward")
    return sorted(options.values(), key=lambda o: (o.option, o.path_length_m, o.anchor))


def _backward_anchor(roads: RoadGraphs, route: list[int]) -> int | None:
    """The first anchor at least ~BACKWARD_M back along the driven route."""
    if len(route) < 2:
        return None
    pos = roads.positions_world_m
    dist = 0.0
    for k in range(len(route) - 1, 0, -1):
        a, b = route[k], route[k - 1]
        dist += float(((pos[a] - pos[b]) ** 2).sum() ** 0.5)
        if dist >= BACKWARD_M * 0.8 and b in roads.anchors:
            return b
    return None


def shortest_path(roads: RoadGraphs, source: int, target: int) -> list[int]:
    """Fine-node path the UGV executes (raises networkx.NetworkXNoPath)."""
    return nx.shortest_path(roads.fine, source, target, weight="length_m")


def heading_after(roads: RoadGraphs, path: list[int], heading_rad: float) -> float:
    """The UGV's heading after driving ``path``: along its last edge (``heading_rad``, the heading
    before, when the path does not move)."""
    if len(path) < 2:
        return heading_rad
    a, b = roads.positions_world_m[path[-2]], roads.positions_world_m[path[-1]]
    return math.atan2(b[1] - a[1], b[0] - a[0])
