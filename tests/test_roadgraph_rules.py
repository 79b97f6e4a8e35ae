"""Road-graph rules (paper Appendix A.1) pinned on small hand-made lane networks.

Every network here is built directly from :class:`Lane` objects with numpy centre lines, so the
expected node counts, anchor kinds and edge lengths can be worked out by hand.
"""

from __future__ import annotations

import math

import networkx as nx
import numpy as np
import pytest

from agos.world.towns.lanes import Lane, LaneNetwork
from agos.world.towns.roadgraph import RoadGraphs, build_road_graphs


def polyline(*corners: tuple[float, float], step: float = 0.5) -> np.ndarray:
    """A centre line through the corners, points at most ``step`` apart (corners kept)."""
    out: list[np.ndarray] = []
    for p0, p1 in zip(corners, corners[1:], strict=False):
        a, b = np.asarray(p0, float), np.asarray(p1, float)
        n = math.ceil(np.linalg.norm(b - a) / step) + 1
        seg = a + (b - a) * np.linspace(0.0, 1.0, n)[:, None]
        out.append(seg if not out else seg[1:])
    return np.concatenate(out)


def bezier(p0: tuple[float, float], c: tuple[float, float], p2: tuple[float, float], n: int = 40) -> np.ndarray:
    t = np.linspace(0.0, 1.0, n)[:, None]
    a, b, d = (np.asarray(p, float) for p in (p0, c, p2))
    return (1 - t) ** 2 * a + 2 * (1 - t) * t * b + t ** 2 * d


def lane(lane_id: str, centre: np.ndarray, **kw) -> Lane:
    return Lane(lane_id, centre, np.full(len(centre), 3.5), **kw)


def graphs(*lanes: Lane) -> RoadGraphs:
    network = LaneNetwork({ln.lane_id: ln for ln in lanes})
    network.check()
    return build_road_graphs(network)


def lane_nodes(g: RoadGraphs, lane_id: str) -> list[int]:
    return [n for n, lid in enumerate(g.node_lane) if lid == lane_id]


def kinds(g: RoadGraphs, kind: str) -> set[int]:
    return {n for n, k in g.anchors.items() if k == kind}


def assert_decision_edges_follow_fine_graph(g: RoadGraphs) -> None:
    for (source, target), edge in g.decision_edges.items():
        assert edge.source == source and edge.target == target
        assert edge.fine_nodes[0] == source and edge.fine_nodes[-1] == target
        assert len(edge.fine_nodes) >= 2
        for u, v in zip(edge.fine_nodes, edge.fine_nodes[1:], strict=False):
            assert g.fine.has_edge(u, v), f"decision edge {source}->{target}: {u}->{v} is not a fine edge"
        assert not set(edge.fine_nodes[1:-1]) & set(g.anchors), "an anchor inside a decision edge"
        assert edge.length_m == pytest.approx(g.path_length_m(edge.fine_nodes))
        assert g.decision.has_edge(source, target)
        assert g.decision.edges[source, target]["length_m"] == pytest.approx(edge.length_m)


# -- a single straight lane ---------------------------------------------------------------------


@pytest.fixture(scope="module")
def straight40() -> RoadGraphs:
    return graphs(lane("a", polyline((0, 0), (40, 0))))


def test_straight_lane_nodes_every_2_m_including_the_end(straight40):
    g = straight40
    assert g.fine.number_of_nodes() == 21
    np.testing.assert_allclose(g.positions_world_m[:, 0], np.arange(0.0, 41.0, 2.0), atol=1e-9)
    np.testing.assert_allclose(g.positions_world_m[:, 1], 0.0, atol=1e-9)
    assert sorted(g.fine.edges()) == [(k, k + 1) for k in range(20)]
    for _, _, data in g.fine.edges(data=True):
        assert data["length_m"] == pytest.approx(2.0)
    assert g.node_lane == ["a"] * 21
    assert not g.covered.any() and g.covered.shape == (21,)


def test_straight_lane_dead_end_and_cruise_anchors_every_10_m(straight40):
    g = straight40
    assert g.anchors[20] == "dead_end"
    assert kinds(g, "dead_end") == {20}
    assert set(g.anchors) == {0, 5, 10, 15, 20}
    assert kinds(g, "cruise") == {0, 5, 10, 15}


def test_straight_lane_decision_edges_are_chains_of_fine_edges(straight40):
    g = straight40
    assert sorted(g.decision_edges) == [(0, 5), (5, 10), (10, 15), (15, 20)]
    assert g.decision_edges[(5, 10)].fine_nodes == [5, 6, 7, 8, 9, 10]
    for edge in g.decision_edges.values():
        assert edge.length_m == pytest.approx(10.0)
    assert_decision_edges_follow_fine_graph(g)
    assert g.decision.out_degree(20) == 0  # nowhere to go from the dead end


def test_lane_length_not_a_multiple_of_2_m_is_sampled_equally_and_at_most_2_m():
    g = graphs(lane("a", polyline((0, 0), (41, 0))))
    assert g.fine.number_of_nodes() == 22  # ceil(41 / 2) = 21 pieces
    steps = np.diff(g.positions_world_m[:, 0])
    np.testing.assert_allclose(steps, 41 / 21)
    assert g.positions_world_m[-1, 0] == pytest.approx(41.0)


def test_anchor_ids_round_trip(straight40):
    assert RoadGraphs.anchor_id(15) == "R15"
    assert RoadGraphs.parse_anchor_id("R15") == 15
    for bad in ("U1_2", "R", "R1a", "15"):
        with pytest.raises(ValueError, match="not a road waypoint id"):
            RoadGraphs.parse_anchor_id(bad)
    assert straight40.nearest_fine_node((9.2, 0.7)) == 5
    ids, xy = straight40.anchor_array()
    assert ids.tolist() == [0, 5, 10, 15, 20]
    np.testing.assert_allclose(xy[:, 0], [0, 10, 20, 30, 40])


# -- successors ---------------------------------------------------------------------------------


def test_successor_shares_the_joint_node():
    g = graphs(lane("a", polyline((0, 0), (20, 0)), successors=["b"]), lane("b", polyline((20, 0), (40, 0))))
    a, b = lane_nodes(g, "a"), lane_nodes(g, "b")
    assert len(a) == 10  # the end of a is b's first node, not a second node at x = 20
    assert len(b) == 11
    assert g.fine.number_of_nodes() == 21
    assert len({tuple(np.round(p, 6)) for p in g.positions_world_m}) == 21  # no duplicated position
    assert g.positions_world_m[a[-1]].tolist() == pytest.approx([18.0, 0.0])
    assert g.positions_world_m[b[0]].tolist() == pytest.approx([20.0, 0.0])
    assert g.fine.has_edge(a[-1], b[0])
    assert g.fine.edges[a[-1], b[0]]["length_m"] == pytest.approx(2.0)
    # a plain continuation is no structural anchor: only cruise anchors and the final dead end
    assert set(g.anchors.values()) == {"cruise", "dead_end"}
    assert kinds(g, "dead_end") == {b[-1]}


# -- a junction ---------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def junction() -> RoadGraphs:
    """West and south arms drive in; east and north arms drive out; four connector lanes."""
    w_end, s_end = (-10.0, -1.75), (1.75, -10.0)
    e_start, n_start = (10.0, -1.75), (1.75, 10.0)
    return graphs(
        lane("in_w", polyline((-60.0, -1.75), w_end), successors=["j.w>e", "j.w>n"]),
        lane("in_s", polyline((1.75, -60.0), s_end), successors=["j.s>n", "j.s>e"]),
        lane("out_e", polyline(e_start, (60.0, -1.75))),
        lane("out_n", polyline(n_start, (1.75, 60.0))),
        lane("j.w>e", polyline(w_end, e_start), successors=["out_e"], in_junction=True, road_id="j"),
        lane("j.w>n", bezier(w_end, (1.75, -1.75), n_start), successors=["out_n"], in_junction=True, road_id="j"),
        lane("j.s>n", polyline(s_end, n_start), successors=["out_n"], in_junction=True, road_id="j"),
        lane("j.s>e", bezier(s_end, (1.75, -1.75), e_start), successors=["out_e"], in_junction=True, road_id="j"),
    )


def test_junction_entries_and_exits(junction):
    g = junction
    entries = {lane_nodes(g, "in_w")[-1], lane_nodes(g, "in_s")[-1]}
    exits = {lane_nodes(g, "out_e")[0], lane_nodes(g, "out_n")[0]}
    assert kinds(g, "junction_entry") == entries
    assert kinds(g, "junction_exit") == exits
    # two manoeuvres leave each entry and arrive at each exit, yet no fork or merge anchor there
    assert all(g.fine.out_degree(n) == 2 for n in entries)
    assert all(g.fine.in_degree(n) == 2 for n in exits)
    assert not kinds(g, "fork") and not kinds(g, "merge")


def test_no_anchors_inside_junction_connectors(junction):
    g = junction
    for connector in ("j.w>e", "j.w>n", "j.s>n", "j.s>e"):
        nodes = lane_nodes(g, connector)
        assert nodes, connector
        assert not set(nodes) & set(g.anchors), f"anchor inside connector {connector}"


def test_one_decision_edge_per_manoeuvre_through_its_connector(junction):
    g = junction
    entry = {arm: lane_nodes(g, f"in_{arm}")[-1] for arm in "ws"}
    exit_ = {arm: lane_nodes(g, f"out_{arm}")[0] for arm in "en"}
    for a in "ws":
        assert sorted(g.decision.successors(entry[a])) == sorted(exit_.values())
        for b in "en":
            edge = g.decision_edges[(entry[a], exit_[b])]
            connector = lane_nodes(g, f"j.{a}>{b}")
            assert edge.fine_nodes == [entry[a], *connector, exit_[b]]
    assert_decision_edges_follow_fine_graph(g)
    # the straight manoeuvre west -> east: 2 m to the junction, 20 m across it
    assert g.decision_edges[(entry["w"], exit_["e"])].length_m == pytest.approx(22.0, abs=1e-6)


def test_junction_arms_still_get_cruise_anchors(junction):
    g = junction
    for arm in ("in_w", "in_s", "out_e", "out_n"):
        nodes = lane_nodes(g, arm)
        assert kinds(g, "cruise") & set(nodes), arm
    out_e = lane_nodes(g, "out_e")
    assert g.anchors[out_e[-1]] == "dead_end"


# -- forks, merges, dead ends -------------------------------------------------------------------


def test_fork_anchor_where_a_lane_splits_outside_a_junction():
    g = graphs(lane("a", polyline((0, 0), (30, 0)), successors=["b", "c"]),
               lane("b", polyline((30, 0), (70, 0))),
               lane("c", polyline((30, 0), (58.28, 28.28))))
    fork = lane_nodes(g, "a")[-1]
    assert g.anchors[fork] == "fork"
    assert kinds(g, "fork") == {fork}
    assert sorted(g.fine.successors(fork)) == sorted([lane_nodes(g, "b")[0], lane_nodes(g, "c")[0]])
    assert g.decision.out_degree(fork) == 2
    assert not kinds(g, "junction_entry") and not kinds(g, "merge")
    assert_decision_edges_follow_fine_graph(g)


def test_merge_anchor_where_two_lanes_join_outside_a_junction():
    g = graphs(lane("p", polyline((0, 0), (30, 0)), successors=["r"]),
               lane("q", polyline((1.72, 28.28), (30, 0)), successors=["r"]),
               lane("r", polyline((30, 0), (70, 0))))
    merge = lane_nodes(g, "r")[0]
    assert g.anchors[merge] == "merge"
    assert kinds(g, "merge") == {merge}
    assert sorted(g.fine.predecessors(merge)) == sorted([lane_nodes(g, "p")[-1], lane_nodes(g, "q")[-1]])
    assert g.decision.in_degree(merge) == 2
    assert not kinds(g, "fork")
    assert_decision_edges_follow_fine_graph(g)


@pytest.mark.parametrize("in_junction", [True, False])
def test_turnaround_successor_makes_a_dead_end(in_junction):
    g = graphs(lane("a", polyline((0, 0), (40, 0)), successors=["t"]),
               lane("t", polyline((40, 0), (46, 0), (46, 3.5), (40, 3.5)), successors=["b"], road_id="turnaround",
                    in_junction=in_junction),
               lane("b", polyline((40, 3.5), (0, 3.5))))
    end_of_a = lane_nodes(g, "a")[-1]
    assert g.anchors[end_of_a] == "dead_end"
    assert g.fine.out_degree(end_of_a) == 1  # the turnaround is still drivable
    assert g.anchors[lane_nodes(g, "b")[-1]] == "dead_end"
    assert "junction_entry" not in g.anchors.values()
    if in_junction:
        assert g.anchors[lane_nodes(g, "b")[0]] == "junction_exit"
    # the UGV can turn around: a decision path from the dead end at a to the far end of b
    assert nx.has_path(g.decision, end_of_a, lane_nodes(g, "b")[-1])
    assert_decision_edges_follow_fine_graph(g)


def test_lane_without_successor_ends_in_a_dead_end_anchor():
    g = graphs(lane("a", polyline((0, 0), (25, 0))), lane("b", polyline((0, 10), (25, 10))))
    assert kinds(g, "dead_end") == {lane_nodes(g, "a")[-1], lane_nodes(g, "b")[-1]}
    for n in kinds(g, "dead_end"):
        assert g.fine.out_degree(n) == 0


# -- lane changes -------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def two_lanes() -> RoadGraphs:
    return graphs(lane("a", polyline((0, 0), (60, 0)), lane_changes=["b"]),
                  lane("b", polyline((0, 3.5), (60, 3.5)), lane_changes=["a"]))


def test_one_lane_change_edge_each_way(two_lanes):
    g = two_lanes
    a, b = set(lane_nodes(g, "a")), set(lane_nodes(g, "b"))
    assert len(a) == len(b) == 31
    a_to_b = [(u, v) for u, v in g.fine.edges() if u in a and v in b]
    b_to_a = [(u, v) for u, v in g.fine.edges() if u in b and v in a]
    assert len(a_to_b) == 1 and len(b_to_a) == 1


@pytest.mark.parametrize(("src_lane", "dst_lane"), [("a", "b"), ("b", "a")])
def test_lane_change_from_40_percent_to_about_8_m_ahead(two_lanes, src_lane, dst_lane):
    g = two_lanes
    src_nodes, dst_nodes = lane_nodes(g, src_lane), set(lane_nodes(g, dst_lane))
    ((u, v),) = [(u, v) for u, v in g.fine.edges() if u in src_nodes and v in dst_nodes]
    assert u == src_nodes[int(len(src_nodes) * 0.4)]  # node 12 of 31: x = 24 m, 40 % of 60 m
    assert g.positions_world_m[u][0] == pytest.approx(24.0)
    assert g.positions_world_m[v][0] == pytest.approx(32.0)  # 8 m ahead, on the neighbour
    assert g.fine.edges[u, v]["length_m"] == pytest.approx(math.hypot(8.0, 3.5))
    # the lane change makes a fork where it leaves and a merge where it arrives
    assert g.anchors[u] == "fork" and g.anchors[v] == "merge"
    assert g.decision.has_edge(u, v)


def test_no_lane_change_on_short_lanes():
    g = graphs(lane("a", polyline((0, 0), (12, 0)), lane_changes=["b"]),
               lane("b", polyline((0, 3.5), (12, 3.5)), lane_changes=["a"]))
    a, b = set(lane_nodes(g, "a")), set(lane_nodes(g, "b"))
    assert not [(u, v) for u, v in g.fine.edges() if (u in a) != (v in a)]
    assert len(a) == len(b) == 7


# -- rings --------------------------------------------------------------------------------------


def test_ring_lane_without_structural_anchors_gets_cruise_anchors_and_a_cycle():
    theta = np.linspace(0.0, 2 * np.pi, 241)
    circle = np.stack([30 * np.cos(theta), 30 * np.sin(theta)], axis=1)
    g = graphs(lane("r", circle, successors=["r"]))
    n = g.fine.number_of_nodes()
    assert n == math.ceil(2 * np.pi * 30 / 2)  # 95: the end is the start, sampled once
    assert g.fine.has_edge(n - 1, 0)
    assert nx.is_strongly_connected(g.fine)
    assert set(g.anchors.values()) == {"cruise"}
    assert len(g.anchors) == round(2 * np.pi * 30 / 10)  # ~19 pieces of ~10 m
    assert nx.is_strongly_connected(g.decision)
    assert len(nx.find_cycle(g.decision)) == len(g.anchors)
    covered = {n for e in g.decision_edges.values() for n in e.fine_nodes}
    assert covered == set(range(n))
    for e in g.decision_edges.values():
        assert 8.0 <= e.length_m <= 12.0
    assert_decision_edges_follow_fine_graph(g)


def test_two_lane_loop_is_one_cycle_of_cruise_anchors():
    g = graphs(lane("a", polyline((0, 0), (60, 0)), successors=["b"]),
               lane("b", polyline((60, 0), (60, 20), (0, 20), (0, 0)), successors=["a"]))
    assert g.fine.number_of_nodes() == 80  # 160 m loop, 2 m apart, no duplicated joints
    assert set(g.anchors.values()) == {"cruise"}
    assert sorted(g.anchors) == list(range(0, 80, 5))
    assert nx.is_strongly_connected(g.decision)


# -- direction of travel --------------------------------------------------------------------------


@pytest.mark.parametrize(("start", "end", "heading"), [((0, 0), (40, 0), 0.0), ((40, 5), (0, 5), math.pi),
                                                       ((3, 0), (3, 30), math.pi / 2), ((0, 0), (30, 30), math.pi / 4)])
def test_edges_go_in_the_direction_of_travel(start, end, heading):
    g = graphs(lane("a", polyline(start, end)))
    d = np.asarray(end, float) - np.asarray(start, float)
    d /= np.linalg.norm(d)
    arc = (g.positions_world_m - np.asarray(start, float)) @ d
    for u, v in g.fine.edges():
        assert arc[v] > arc[u], f"edge {u}->{v} runs against the lane"
    for (u, v) in g.decision_edges:
        assert arc[v] > arc[u]
    assert arc[0] == pytest.approx(0.0)
    for node in g.fine.nodes():
        diff = (g.heading_at(node) - heading + math.pi) % (2 * math.pi) - math.pi
        assert abs(diff) < 1e-6, f"heading at {node}"


def test_heading_at_the_last_node_uses_its_in_edge():
    g = graphs(lane("a", polyline((10, 10), (10, -10))))
    last = g.fine.number_of_nodes() - 1
    assert g.fine.out_degree(last) == 0
    assert g.heading_at(last) == pytest.approx(-math.pi / 2)


def test_medians_on_a_200_m_lane():
    g = graphs(lane("a", polyline((0, 0), (200, 0))))
    fine = [d["length_m"] for _, _, d in g.fine.edges(data=True)]
    decision = [e.length_m for e in g.decision_edges.values()]
    assert 1.5 <= float(np.median(fine)) <= 2.5
    assert 7.0 <= float(np.median(decision)) <= 13.0
    assert len(g.anchors) == 21  # 20 pieces of 10 m and the dead end
    assert_decision_edges_follow_fine_graph(g)


def test_covered_lanes_mark_their_fine_nodes():
    g = graphs(lane("a", polyline((0, 0), (20, 0)), successors=["b"]),
               lane("b", polyline((20, 0), (40, 0)), covered=True))
    assert not g.covered[lane_nodes(g, "a")].any()
    assert g.covered[lane_nodes(g, "b")].all()
