"""UGV road graphs (paper Appendix A.1), built from any :class:`~agos.world.towns.lanes.LaneNetwork`.

Fine graph: every lane sampled about every 2 m (equal spacing per lane, at most 2 m), edges in
the direction of travel, the last node of a lane joined to the first node of each successor, and
on multi-lane roads one lane-change edge per neighbouring lane and lane section (from 40 % of the
lane's length to the node of the neighbour about 8 m further on).

Decision graph: structural anchors — junction entries (last node before a junction connector),
junction exits (first node after one), dead ends (no way on, or only a turnaround), forks and
merges — plus cruise anchors that split each anchor-free corridor into pieces of about 10 m.
Each decision edge keeps the fine nodes between its two anchors.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import networkx as nx
import numpy as np

from agos.world.towns.lanes import TURNAROUND, LaneNetwork

FINE_SPACING_M = 2.0
CRUISE_SPACING_M = 10.0


@dataclass
class DecisionEdge:
    source: int
    target: int
    fine_nodes: list[int]
    """Fine nodes from source to target, both included."""
    length_m: float


@dataclass
class RoadGraphs:
    positions_world_m: np.ndarray
    """(N, 2) fine-node positions."""
    fine: nx.DiGraph
    """Directed fine graph; edge attribute ``length_m``."""
    anchors: dict[int, str]
    """Decision anchor fine-node id -> kind (``cruise``, ``junction_entry``, ...)."""
    node_lane: list[str] = field(default_factory=list)
    """Lane id of each fine node."""
    covered: np.ndarray = field(default_factory=lambda: np.zeros(0, bool))
    """(N,) True where the node is under a deck (hidden from the air)."""
    decision_edges: dict[tuple[int, int], DecisionEdge] = field(default_factory=dict)
    decision: nx.DiGraph = field(default_factory=nx.DiGraph)

    @staticmethod
    def anchor_id(node: int) -> str:
        return f"R{node}"

    @staticmethod
    def parse_anchor_id(waypoint_id: str) -> int:
        if not waypoint_id.startswith("R") or not waypoint_id[1:].isdigit():
            raise ValueError(f"{waypoint_id!r} is not a road waypoint id (R<number>)")
        return int(waypoint_id[1:])

    def nearest_fine_node(self, xy: tuple[float, float]) -> int:
        d = np.linalg.norm(self.positions_world_m - np.asarray(xy), axis=1)
        return int(np.argmin(d))

    def anchor_array(self) -> tuple[np.ndarray, np.ndarray]:
        ids = np.fromiter(sorted(self.anchors), dtype=int)
        return ids, self.positions_world_m[ids]

    def heading_at(self, node: int) -> float:
        """Direction of travel at a fine node (along its first out-edge, else its in-edge)."""
        succ = sorted(self.fine.successors(node))
        if succ:
            a, b = node, succ[0]
        else:
            a, b = min(self.fine.predecessors(node)), node
        d = self.positions_world_m[b] - self.positions_world_m[a]
        return math.atan2(d[1], d[0])

    def path_length_m(self, nodes: list[int]) -> float:
        p = self.positions_world_m[nodes]
        return float(np.linalg.norm(np.diff(p, axis=0), axis=1).sum()) if len(nodes) > 1 else 0.0


def build_road_graphs(network: LaneNetwork) -> RoadGraphs:
    positions: list[np.ndarray] = []
    node_lane: list[str] = []
    covered: list[bool] = []
    first: dict[str, int] = {}
    last: dict[str, int] = {}
    fine = nx.DiGraph()
    lane_ids = sorted(network.lanes)
    for lane_id in lane_ids:
        lane = network.lanes[lane_id]
        pts = _sample(lane.centre_m, keep_end=not lane.successors)
        start = len(node_lane)
        positions.append(pts)
        node_lane.extend([lane_id] * len(pts))
        covered.extend([lane.covered] * len(pts))
        ids = list(range(start, start + len(pts)))
        fine.add_nodes_from(ids)
        fine.add_edges_from(zip(ids, ids[1:], strict=False))
        first[lane_id], last[lane_id] = ids[0], ids[-1]
    for lane_id in lane_ids:
        for succ in network.lanes[lane_id].successors:
            fine.add_edge(last[lane_id], first[succ])
    pos = np.concatenate(positions)
    for lane_id in lane_ids:
        for other in network.lanes[lane_id].lane_changes:
            edge = _lane_change(pos, first, last, lane_id, other)
            if edge is not None:
                fine.add_edge(*edge)
    for u, v in fine.edges():
        fine.edges[u, v]["length_m"] = float(np.linalg.norm(pos[v] - pos[u]))

    anchors = _structural_anchors(network, fine, first, last, node_lane)
    _cruise_anchors(fine, pos, anchors, node_lane, network)
    graphs = RoadGraphs(pos, fine, anchors, node_lane, np.asarray(covered, dtype=bool))
    _build_decision_graph(graphs)
    return graphs


def _lane_change(pos: np.ndarray, first: dict[str, int], last: dict[str, int], a: str, b: str) -> tuple[int, int] | None:
    """One lane-change edge from lane ``a`` (at 40 % of its nodes) to the node of lane ``b`` about
    8 m further along; None when a lane is too short for it."""
    a_nodes = np.arange(first[a], last[a] + 1)
    b_nodes = np.arange(first[b], last[b] + 1)
    if len(a_nodes) < 10 or len(b_nodes) < 10:
        return None
    src = int(a_nodes[int(len(a_nodes) * 0.4)])
    direction = pos[min(src + 1, last[a])] - pos[src]
    norm = float(np.linalg.norm(direction))
    if norm == 0:
        return None
    goal = pos[src] + direction / norm * 8.0
    dst = int(b_nodes[int(np.argmin(np.linalg.norm(pos[b_nodes] - goal, axis=1)))])
    if dst in (first[b], last[b]) or np.linalg.norm(pos[dst] - pos[src]) > 12.0:
        return None
    return src, dst


def _sample(centre: np.ndarray, *, keep_end: bool) -> np.ndarray:
    """Equally spaced points at most FINE_SPACING_M apart; the end point only where the lane ends
    for good (otherwise the successor's first node stands there)."""
    seg = np.linalg.norm(np.diff(centre, axis=0), axis=1)
    arc = np.concatenate([[0.0], np.cumsum(seg)])
    n = max(1, math.ceil(arc[-1] / FINE_SPACING_M))
    s = np.linspace(0.0, arc[-1], n + 1)
    if not keep_end:
        s = s[:-1]
    return np.stack([np.interp(s, arc, centre[:, 0]), np.interp(s, arc, centre[:, 1])], axis=1)


def _structural_anchors(network: LaneNetwork, fine: nx.DiGraph, first: dict[str, int], last: dict[str, int],
                        node_lane: list[str]) -> dict[int, str]:
    anchors: dict[int, str] = {}
    lanes = network.lanes
    for lane_id, lane in lanes.items():
        if lane.in_junction:
            continue
        succ = [lanes[s] for s in lane.successors]
        if succ and all(s.road_id == TURNAROUND for s in succ):
            anchors[last[lane_id]] = "dead_end"
        elif any(s.in_junction for s in succ):
            anchors[last[lane_id]] = "junction_entry"
    for lane in lanes.values():
        if lane.in_junction:
            for succ_id in lane.successors:
                if not lanes[succ_id].in_junction:
                    anchors.setdefault(first[succ_id], "junction_exit")
    for n in fine.nodes():
        if n in anchors:
            continue
        if fine.out_degree(n) == 0:
            anchors[n] = "dead_end"
        elif fine.out_degree(n) > 1:
            anchors[n] = "fork"
        elif fine.in_degree(n) > 1:
            anchors[n] = "merge"
    return anchors


def _cruise_anchors(fine: nx.DiGraph, pos: np.ndarray, anchors: dict[int, str], node_lane: list[str],
                    network: LaneNetwork) -> None:
    """Split every corridor between anchors (outside junctions) into ~10 m pieces."""
    in_junction = [network.lanes[lane].in_junction for lane in node_lane]
    visited: set[int] = set()

    def walk(start: int) -> None:
        for nxt in sorted(fine.successors(start)):
            chain = [start]
            node = nxt
            while node not in anchors and not in_junction[node] and node not in visited and fine.out_degree(node) == 1:
                chain.append(node)
                visited.add(node)
                node = next(iter(fine.successors(node)))
            if node not in anchors and not in_junction[node] and node not in visited:
                chain.append(node)  # the corridor ends at a node with no single way on
                visited.add(node)
            arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(pos[chain], axis=0), axis=1))])
            end_len = arc[-1] + (float(np.linalg.norm(pos[node] - pos[chain[-1]])) if node != chain[-1] else 0.0)
            pieces = max(1, round(end_len / CRUISE_SPACING_M))
            for k in range(1, pieces):
                idx = int(np.argmin(np.abs(arc - end_len * k / pieces)))
                if 0 < idx < len(chain):
                    anchors[chain[idx]] = "cruise"

    for start in sorted(anchors):
        walk(start)
    # corridors not reached from any anchor (rings without junctions): seed one anchor each
    for n in sorted(fine.nodes()):
        if n not in visited and n not in anchors and not in_junction[n]:
            anchors[n] = "cruise"
            walk(n)


def _build_decision_graph(graphs: RoadGraphs) -> None:
    fine, decision = graphs.fine, graphs.decision
    for anchor, kind in graphs.anchors.items():
        decision.add_node(anchor, kind=kind)
    for anchor in sorted(graphs.anchors):
        for first in sorted(fine.successors(anchor)):
            chain, seen = [anchor, first], {anchor, first}
            while chain[-1] not in graphs.anchors:
                succ = list(fine.successors(chain[-1]))
                if len(succ) != 1 or succ[0] in seen:
                    break
                chain.append(succ[0])
                seen.add(succ[0])
            if chain[-1] in graphs.anchors:
                edge = DecisionEdge(anchor, chain[-1], chain, graphs.path_length_m(chain))
                graphs.decision_edges[(anchor, chain[-1])] = edge
                decision.add_edge(anchor, chain[-1], length_m=edge.length_m)
