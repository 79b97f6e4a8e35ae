"""UGV road graphs (paper Appendix A.1): a directed ~2 m fine graph and a sparse decision graph.

Fine graph: nodes sampled along each driving lane about every 2 m, edges in the direction of
travel; lanes are joined inside junctions by connector curves for every legal manoeuvre
(no U-turns except at dead ends).

Decision graph: structural anchors (junction entries and exits, dead ends, forks and merges)
plus cruise anchors spaced about 10 m apart along each lane. Each decision edge keeps the
sequence of fine nodes between its two anchors.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import networkx as nx
import numpy as np

from agos.world.town import JUNCTION_SETBACK_M, LANE_WIDTH_M, TownLayout

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
        succ = list(self.fine.successors(node))
        if succ:
            a, b = node, succ[0]
        else:
            a, b = next(iter(self.fine.predecessors(node))), node
        d = self.positions_world_m[b] - self.positions_world_m[a]
        return math.atan2(d[1], d[0])

    def path_length_m(self, nodes: list[int]) -> float:
        p = self.positions_world_m[nodes]
        return float(np.linalg.norm(np.diff(p, axis=0), axis=1).sum()) if len(nodes) > 1 else 0.0


def build_road_graphs(layout: TownLayout) -> RoadGraphs:
    positions: list[tuple[float, float]] = []
    fine = nx.DiGraph()
    anchors: dict[int, str] = {}
    junction_degree = _junction_degrees(layout)

    def add_node(p: np.ndarray) -> int:
        positions.append((float(p[0]), float(p[1])))
        fine.add_node(len(positions) - 1)
        return len(positions) - 1

    # lane ends per junction: (lane start node, direction) leaving, (lane end node, direction) arriving
    leaving: dict[int, list[tuple[int, np.ndarray, int]]] = {j: [] for j in range(len(layout.junctions))}
    arriving: dict[int, list[tuple[int, np.ndarray, int]]] = {j: [] for j in range(len(layout.junctions))}
    for seg, (a, b) in enumerate(layout.segments):
        for j_from, j_to in ((a, b), (b, a)):
            p0, p1 = np.asarray(layout.junctions[j_from]), np.asarray(layout.junctions[j_to])
            direction = (p1 - p0) / np.linalg.norm(p1 - p0)
            right = np.array([direction[1], -direction[0]])
            start = p0 + direction * JUNCTION_SETBACK_M + right * (LANE_WIDTH_M / 2)
            end = p1 - direction * JUNCTION_SETBACK_M + right * (LANE_WIDTH_M / 2)
            nodes = [add_node(p) for p in _sample_line(start, end)]
            for u, v in zip(nodes, nodes[1:], strict=False):
                fine.add_edge(u, v)
            _place_cruise_anchors(nodes, positions, anchors)
            anchors[nodes[0]] = "junction_exit"
            anchors[nodes[-1]] = "dead_end" if junction_degree[j_to] == 1 else "junction_entry"
            leaving[j_from].append((nodes[0], direction, seg))
            arriving[j_to].append((nodes[-1], direction, seg))

    for j in range(len(layout.junctions)):
        for end_node, d_in, seg_in in arriving[j]:
            for start_node, d_out, seg_out in leaving[j]:
                if seg_in == seg_out and junction_degree[j] > 1:
                    continue  # no U-turns except to leave a dead end
                p0, p2 = np.asarray(positions[end_node]), np.asarray(positions[start_node])
                ctrl = _connector_control(p0, d_in, p2, d_out)
                inner = [add_node(p) for p in _sample_bezier(p0, ctrl, p2)[1:-1]]
                chain = [end_node, *inner, start_node]
                for u, v in zip(chain, chain[1:], strict=False):
                    fine.add_edge(u, v)

    pos = np.asarray(positions)
    for u, v in fine.edges():
        fine.edges[u, v]["length_m"] = float(np.linalg.norm(pos[v] - pos[u]))
    # forks and merges not already anchored (none in grid towns, common in imported maps)
    for n in fine.nodes():
        if n not in anchors and (fine.out_degree(n) > 1 or fine.in_degree(n) > 1):
            anchors[n] = "fork" if fine.out_degree(n) > 1 else "merge"
    graphs = RoadGraphs(pos, fine, anchors)
    _build_decision_graph(graphs)
    return graphs


def _junction_degrees(layout: TownLayout) -> list[int]:
    degree = [0] * len(layout.junctions)
    for a, b in layout.segments:
        degree[a] += 1
        degree[b] += 1
    return degree


def _sample_line(start: np.ndarray, end: np.ndarray) -> list[np.ndarray]:
    length = float(np.linalg.norm(end - start))
    n = max(1, math.ceil(length / FINE_SPACING_M))
    return [start + (end - start) * (k / n) for k in range(n + 1)]


def _connector_control(p0: np.ndarray, d_in: np.ndarray, p2: np.ndarray, d_out: np.ndarray) -> np.ndarray:
    cross = d_in[0] * d_out[1] - d_in[1] * d_out[0]
    if abs(cross) < 1e-6:
        if float(np.dot(d_in, d_out)) > 0:
            return (p0 + p2) / 2  # straight through
        # U-turn at a dead end: bulge forward of the lane ends
        return (p0 + p2) / 2 + d_in * (np.linalg.norm(p2 - p0) * 0.8)
    # intersection of the two lane lines
    t = ((p2[0] - p0[0]) * d_out[1] - (p2[1] - p0[1]) * d_out[0]) / cross
    return p0 + d_in * t


def _sample_bezier(p0: np.ndarray, c: np.ndarray, p2: np.ndarray) -> list[np.ndarray]:
    ts = np.linspace(0, 1, 64)
    pts = ((1 - ts) ** 2)[:, None] * p0 + (2 * (1 - ts) * ts)[:, None] * c + (ts ** 2)[:, None] * p2
    arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(pts, axis=0), axis=1))])
    n = max(1, math.ceil(arc[-1] / FINE_SPACING_M))
    targets = np.linspace(0, arc[-1], n + 1)
    return [pts[int(np.searchsorted(arc, s, side="left").clip(0, len(pts) - 1))] for s in targets[:-1]] + [p2]


def _place_cruise_anchors(nodes: list[int], positions: list[tuple[float, float]],
                          anchors: dict[int, str]) -> None:
    p = np.asarray([positions[n] for n in nodes])
    arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(p, axis=0), axis=1))])
    pieces = max(1, round(arc[-1] / CRUISE_SPACING_M))
    for k in range(1, pieces):
        idx = int(np.argmin(np.abs(arc - arc[-1] * k / pieces)))
        if 0 < idx < len(nodes) - 1:
            anchors[nodes[idx]] = "cruise"


def _build_decision_graph(graphs: RoadGraphs) -> None:
    fine, decision = graphs.fine, graphs.decision
    for anchor, kind in graphs.anchors.items():
        decision.add_node(anchor, kind=kind)
    for anchor in graphs.anchors:
        for first in fine.successors(anchor):
            chain = [anchor, first]
            while chain[-1] not in graphs.anchors:
                succ = list(fine.successors(chain[-1]))
                if len(succ) != 1:
                    break
                chain.append(succ[0])
            if chain[-1] in graphs.anchors:
                edge = DecisionEdge(anchor, chain[-1], chain, graphs.path_length_m(chain))
                graphs.decision_edges[(anchor, chain[-1])] = edge
                decision.add_edge(anchor, chain[-1], length_m=edge.length_m)
