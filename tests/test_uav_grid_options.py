"""UAV grid (Appendix A.1) and runtime waypoint options (Appendix A.2) on hand-made inputs."""

from __future__ import annotations

import math

import networkx as nx
import numpy as np
import pytest

from agos.world.sim.options import RoadOption, shortest_path, uav_options, ugv_options
from agos.world.towns.lanes import Lane, LaneNetwork
from agos.world.towns.roadgraph import RoadGraphs, build_road_graphs
from agos.world.towns.uavgrid import ALTITUDE_M, SPACING_M, UavGrid, build_uav_grid

# Road bounding box (0, 0)-(100, 60), expanded by 50 m: x in [-50, 150], y in [-50, 110].
ROAD = np.array([[0.0, 0.0], [100.0, 60.0], [40.0, 20.0]])
XS = [-50.0, -10.0, 30.0, 70.0, 110.0, 150.0]
YS = [-50.0, -10.0, 30.0, 70.0, 110.0]


def full_grid() -> UavGrid:
    """Every grid node kept: an anchor on each one."""
    anchors = np.array([(x, y) for x in XS for y in YS])
    return build_uav_grid(ROAD, anchors)


# -- the grid -----------------------------------------------------------------------------------


def test_grid_spacing_altitude_and_expanded_bbox():
    grid = full_grid()
    assert grid.spacing_m == SPACING_M == 40.0
    assert grid.altitude_m == ALTITUDE_M == 80.0
    assert len(grid.nodes) == len(XS) * len(YS) == 30
    for node in grid.nodes.values():
        assert node.node_id == f"U{node.i}_{node.j}"
        assert node.position_world_m == pytest.approx((XS[node.i], YS[node.j], 80.0))
    assert grid.nodes["U0_0"].position_world_m == pytest.approx((-50.0, -50.0, 80.0))  # bbox min - 50 m
    assert grid.nodes["U5_4"].position_world_m == pytest.approx((150.0, 110.0, 80.0))  # bbox max + 50 m
    assert {n.i for n in grid.nodes.values()} == set(range(6))
    assert {n.j for n in grid.nodes.values()} == set(range(5))


def test_grid_neighbours_are_exactly_40_m_apart():
    grid = full_grid()
    for node in grid.nodes.values():
        right = grid.nodes.get(f"U{node.i + 1}_{node.j}")
        up = grid.nodes.get(f"U{node.i}_{node.j + 1}")
        if right is not None:
            assert right.position_world_m[0] - node.position_world_m[0] == pytest.approx(40.0)
            assert right.position_world_m[1] == pytest.approx(node.position_world_m[1])
        if up is not None:
            assert up.position_world_m[1] - node.position_world_m[1] == pytest.approx(40.0)


def test_grid_does_not_extend_beyond_the_expanded_bbox():
    far_anchor = np.array([[195.0, 155.0]])  # 63.6 m from the corner node (150, 110)
    assert build_uav_grid(ROAD, far_anchor).nodes == {}


def test_node_39_m_from_an_anchor_kept_and_41_m_dropped():
    # anchor at (30, -9): U2_2 (30, 30) is 39 m away, U2_1 (30, -10) 1 m, U2_0 (30, -50) 41 m,
    # U1_1 (-10, -10) and U3_1 (70, -10) 40.01 m.
    grid = build_uav_grid(ROAD, np.array([[30.0, -9.0]]))
    assert math.dist(grid.nodes["U2_2"].position_world_m[:2], (30.0, -9.0)) == pytest.approx(39.0)
    assert sorted(grid.nodes) == ["U2_1", "U2_2"]
    assert "U2_0" not in grid.nodes  # 41 m away
    assert "U1_1" not in grid.nodes and "U3_1" not in grid.nodes  # just over 40 m


def test_node_exactly_40_m_from_an_anchor_is_kept():
    grid = build_uav_grid(ROAD, np.array([[30.0, -10.0]]))  # on U2_1: its four axis neighbours are 40 m away
    assert {"U2_1", "U1_1", "U3_1", "U2_0", "U2_2"} == set(grid.nodes)


def test_inside_region_gives_the_active_nodes():
    grid = full_grid()
    assert grid.inside((-10.0, -10.0, 70.0, 30.0)) == ["U1_1", "U1_2", "U2_1", "U2_2", "U3_1", "U3_2"]  # bounds inclusive
    assert grid.inside((0.0, 0.0, 25.0, 25.0)) == []
    assert grid.inside((-1000.0, -1000.0, 1000.0, 1000.0)) == sorted(grid.nodes)
    partial = build_uav_grid(ROAD, np.array([[30.0, -9.0]]))
    assert partial.inside((-100.0, -100.0, 100.0, 100.0)) == ["U2_1", "U2_2"]


def test_neighbours_interior_corner_and_inactive():
    grid = full_grid()
    active = set(grid.nodes)
    around = grid.neighbours("U2_2", active)
    assert len(around) == 8
    assert "U2_2" not in around
    assert set(around) == {f"U{i}_{j}" for i in (1, 2, 3) for j in (1, 2, 3)} - {"U2_2"}
    centre = grid.nodes["U2_2"].position_world_m
    for key in around:
        d = math.dist(grid.nodes[key].position_world_m, centre)
        diagonal = grid.nodes[key].i != 2 and grid.nodes[key].j != 2
        assert d == (pytest.approx(56.57, abs=0.01) if diagonal else pytest.approx(40.0))
    assert sorted(grid.neighbours("U0_0", active)) == ["U0_1", "U1_0", "U1_1"]
    fewer = active - {"U1_1", "U3_3", "U2_3"}
    assert set(grid.neighbours("U2_2", fewer)) == set(around) - {"U1_1", "U3_3", "U2_3"}
    # never more than 8, only active ones, never the centre itself
    for key in grid.nodes:
        out = grid.neighbours(key, fewer)
        assert len(out) <= 8 and key not in out and set(out) <= fewer


def test_nearest_and_uav_options_use_the_nearest_active_node():
    grid = full_grid()
    active = set(grid.nodes)
    assert grid.nearest((32.0, 27.0), sorted(active)) == "U2_2"
    assert sorted(uav_options(grid, (32.0, 27.0), active)) == sorted(grid.neighbours("U2_2", active))
    # U2_2 (14 m away) not active: the nearest active node is U2_1 (26.1 m), not U3_2 (40.5 m)
    without = active - {"U2_2"}
    assert grid.nearest((32.0, 16.0), sorted(without)) == "U2_1"
    assert sorted(uav_options(grid, (32.0, 16.0), without)) == sorted(grid.neighbours("U2_1", without))
    assert "U2_2" not in uav_options(grid, (32.0, 16.0), without)


# -- UGV options ----------------------------------------------------------------------------------


def polyline(*corners: tuple[float, float], step: float = 0.5) -> np.ndarray:
    out: list[np.ndarray] = []
    for p0, p1 in zip(corners, corners[1:], strict=False):
        a, b = np.asarray(p0, float), np.asarray(p1, float)
        n = math.ceil(np.linalg.norm(b - a) / step) + 1
        seg = a + (b - a) * np.linspace(0.0, 1.0, n)[:, None]
        out.append(seg if not out else seg[1:])
    return np.concatenate(out)


def lane(lane_id: str, centre: np.ndarray, **kw) -> Lane:
    return Lane(lane_id, centre, np.full(len(centre), 3.5), **kw)


def graphs(*lanes: Lane) -> RoadGraphs:
    return build_road_graphs(LaneNetwork({ln.lane_id: ln for ln in lanes}))


def lane_nodes(g: RoadGraphs, lane_id: str) -> list[int]:
    return [n for n, lid in enumerate(g.node_lane) if lid == lane_id]


def by_kind(options: list[RoadOption], kind: str) -> dict[int, float]:
    return {o.anchor: o.path_length_m for o in options if o.option == kind}


@pytest.fixture(scope="module")
def straight200() -> RoadGraphs:
    return graphs(lane("a", polyline((0, 0), (200, 0))))  # anchors every 5 nodes (10 m), one way


def test_forward_and_forward_far_on_a_long_straight_lane(straight200):
    g = straight200
    options = ugv_options(g, 0, [0])
    assert by_kind(options, "forward") == {5: pytest.approx(10.0)}
    assert by_kind(options, "forward_far") == {15: pytest.approx(30.0)}
    assert {o.option for o in options} == {"forward", "forward_far"}
    # between anchors: the next anchor ahead, and ~30 m from there on
    options = ugv_options(g, 7, [5, 6, 7])
    assert by_kind(options, "forward") == {10: pytest.approx(6.0)}
    assert by_kind(options, "forward_far") == {20: pytest.approx(26.0)}


def test_no_forward_options_at_a_dead_end(straight200):
    g = straight200
    last = g.fine.number_of_nodes() - 1
    assert g.anchors[last] == "dead_end"
    assert ugv_options(g, last, [last]) == []
    # near the end, forward_far is cut short by the dead end
    options = ugv_options(g, 90, [90])
    assert by_kind(options, "forward") == {95: pytest.approx(10.0)}
    assert by_kind(options, "forward_far") == {100: pytest.approx(20.0)}


def test_backward_not_offered_on_a_one_way_lane(straight200):
    g = straight200
    route = list(range(0, 11))  # drove 20 m from node 0 to the anchor at node 10
    options = ugv_options(g, 10, route)
    assert not by_kind(options, "backward")
    assert all(o.anchor != 10 for o in options)


@pytest.fixture(scope="module")
def loop() -> RoadGraphs:
    """A 160 m directed loop of two lanes: nodes 0..79, 2 m apart, cruise anchors every 10 m."""
    return graphs(lane("a", polyline((0, 0), (60, 0)), successors=["b"]),
                  lane("b", polyline((60, 0), (60, 20), (0, 20), (0, 0)), successors=["a"]))


def test_backward_offered_on_a_loop_with_the_loop_path_length(loop):
    g = loop
    assert sorted(g.anchors) == list(range(0, 80, 5))
    options = ugv_options(g, 10, list(range(0, 11)))
    # 10 m back along the driven route is anchor 5; the legal way there is the rest of the loop
    assert by_kind(options, "backward") == {5: pytest.approx(150.0)}
    assert by_kind(options, "forward") == {15: pytest.approx(10.0)}
    assert by_kind(options, "forward_far") == {25: pytest.approx(30.0)}
    assert all(o.anchor != 10 for o in options)


def test_backward_needs_about_10_m_of_driven_route(loop):
    g = loop
    assert not by_kind(ugv_options(g, 10, [6, 7, 8, 9, 10]), "backward")  # 8 m driven, no anchor behind
    assert not by_kind(ugv_options(g, 10, [10]), "backward")
    # the first anchor at least ~8 m back along the route, not the start of the route
    options = ugv_options(g, 20, list(range(0, 21)))
    assert by_kind(options, "backward") == {15: pytest.approx(150.0)}


def test_backward_never_offers_the_current_node(loop):
    g = loop
    # a whole lap ending where it started: the anchor 160 m back is the current node
    route = [*range(10, 80), *range(0, 11)]
    for o in ugv_options(g, 10, route):
        assert o.anchor != 10
    # a route whose first anchor ~10 m back is the current node itself: no backward option
    options = ugv_options(g, 10, [10, 11, 12, 13, 14, 13, 12, 11, 10])
    assert all(o.anchor != 10 for o in options)
    assert not by_kind(options, "backward")
    assert by_kind(options, "forward") == {15: pytest.approx(10.0)}


def test_backward_not_offered_beyond_the_return_path_limit():
    # a 400 m loop: the way back to the anchor 10 m behind is 390 m > 250 m
    g = graphs(lane("a", polyline((0, 0), (150, 0)), successors=["b"]),
               lane("b", polyline((150, 0), (150, 50), (0, 50), (0, 0)), successors=["a"]))
    assert g.fine.number_of_nodes() == 200
    options = ugv_options(g, 10, list(range(0, 11)))
    assert not by_kind(options, "backward")
    assert by_kind(options, "forward") == {15: pytest.approx(10.0)}


@pytest.fixture(scope="module")
def fork() -> RoadGraphs:
    """Lane a (0..20 m) splits at its last node (18 m) into b (east) and c (north-east)."""
    return graphs(lane("a", polyline((0, 0), (20, 0)), successors=["b", "c"]),
                  lane("b", polyline((20, 0), (80, 0))),
                  lane("c", polyline((20, 0), (62.43, 42.43))))


def test_forward_far_stops_at_a_split(fork):
    g = fork
    split = lane_nodes(g, "a")[-1]
    assert g.anchors[split] == "fork"
    assert sorted(g.anchors[n] for n in lane_nodes(g, "a") if n in g.anchors) == ["cruise", "cruise", "fork"]
    before = max(n for n in lane_nodes(g, "a") if n in g.anchors and n != split)
    start = min(lane_nodes(g, "a"))
    options = ugv_options(g, start, [start])
    assert by_kind(options, "forward") == {before: pytest.approx(g.positions_world_m[before][0])}
    assert by_kind(options, "forward_far") == {split: pytest.approx(18.0)}  # not beyond the fork
    # right before the split: the fork is next, and there is no single ~30 m target beyond it
    options = ugv_options(g, before, [start, before])
    assert by_kind(options, "forward") == {split: pytest.approx(18.0 - g.positions_world_m[before][0])}
    assert not by_kind(options, "forward_far")


def test_at_a_fork_forward_goes_down_every_branch(fork):
    g = fork
    split = lane_nodes(g, "a")[-1]
    forward = by_kind(ugv_options(g, split, [split]), "forward")
    assert len(forward) == 2
    lanes = {g.node_lane[n] for n in forward}
    assert lanes == {"b", "c"}
    for anchor, length in forward.items():
        assert 7.0 <= length <= 13.0
        assert length == pytest.approx(nx.shortest_path_length(g.fine, split, anchor, weight="length_m"), abs=1e-3)


@pytest.fixture(scope="module")
def tee() -> RoadGraphs:
    """A T-junction at the origin: arms west, east and south, one lane each way, right-hand
    traffic, connectors for every manoeuvre except U-turns; arms 50 m long from 10 m out."""
    arms = {"w": (-1.0, 0.0), "e": (1.0, 0.0), "s": (0.0, -1.0)}
    lanes: list[Lane] = []
    ends: dict[str, tuple[np.ndarray, np.ndarray]] = {}
    for name, (dx, dy) in arms.items():
        d = np.array([dx, dy])
        right_out = np.array([dy, -dx]) * 1.75
        near_in, far_in = 10 * d - right_out, 60 * d - right_out
        near_out, far_out = 10 * d + right_out, 60 * d + right_out
        lanes.append(lane(f"in_{name}", polyline(tuple(far_in), tuple(near_in)), successors=[]))
        lanes.append(lane(f"out_{name}", polyline(tuple(near_out), tuple(far_out))))
        ends[name] = (near_in, near_out)
    for a in arms:
        for b in arms:
            if a == b:
                continue  # no U-turns
            p0, p2 = ends[a][0], ends[b][1]
            t = np.linspace(0.0, 1.0, 40)[:, None]
            curve = (1 - t) ** 2 * p0 + 2 * (1 - t) * t * np.zeros(2) + t ** 2 * p2
            lanes.append(lane(f"j.{a}>{b}", curve, successors=[f"out_{b}"], in_junction=True, road_id="j0"))
            next(ln for ln in lanes if ln.lane_id == f"in_{a}").successors.append(f"j.{a}>{b}")
    return graphs(*lanes)


def test_tee_anchors(tee):
    g = tee
    for arm in "wes":
        assert g.anchors[lane_nodes(g, f"in_{arm}")[-1]] == "junction_entry"
        assert g.anchors[lane_nodes(g, f"out_{arm}")[0]] == "junction_exit"
        assert g.decision.out_degree(lane_nodes(g, f"in_{arm}")[-1]) == 2


def test_junction_exits_offered_when_the_entry_is_near(tee):
    g = tee
    entry = lane_nodes(g, "in_s")[-1]
    exits = {lane_nodes(g, "out_w")[0], lane_nodes(g, "out_e")[0]}
    u_turn = lane_nodes(g, "out_s")[0]
    (before,) = list(g.decision.predecessors(entry))
    gap = g.decision.edges[before, entry]["length_m"]
    assert gap <= 15.0
    options = ugv_options(g, before, [before])
    offered = by_kind(options, "junction_exit")
    assert set(offered) == exits  # two exits on a T, no U-turn
    assert u_turn not in {o.anchor for o in options}
    for exit_, length in offered.items():
        assert length == pytest.approx(gap + g.decision.edges[entry, exit_]["length_m"], abs=1e-3)
        assert length == pytest.approx(nx.shortest_path_length(g.fine, before, exit_, weight="length_m"), abs=1e-3)
    assert by_kind(options, "forward") == {entry: pytest.approx(gap, abs=1e-3)}


def test_junction_exits_not_offered_when_the_entry_is_far(tee):
    g = tee
    entry = lane_nodes(g, "in_s")[-1]
    (before,) = list(g.decision.predecessors(entry))
    (further,) = list(g.decision.predecessors(before))
    assert g.decision.edges[further, before]["length_m"] + g.decision.edges[before, entry]["length_m"] > 15.0
    options = ugv_options(g, further, [further])
    assert not by_kind(options, "junction_exit")


def test_at_the_entry_every_exit_is_a_forward_option(tee):
    g = tee
    entry = lane_nodes(g, "in_s")[-1]
    options = ugv_options(g, entry, [entry])
    anchors = {o.anchor for o in options if o.option in ("forward", "junction_exit")}
    assert anchors == {lane_nodes(g, "out_w")[0], lane_nodes(g, "out_e")[0]}
    assert all(o.anchor != entry for o in options)


def test_shortest_path_follows_the_fine_graph(loop, tee):
    path = shortest_path(loop, 10, 5)
    assert path[0] == 10 and path[-1] == 5
    assert path == [*range(10, 80), *range(0, 6)]
    for u, v in zip(path, path[1:], strict=False):
        assert loop.fine.has_edge(u, v)
    assert loop.path_length_m(path) == pytest.approx(150.0)
    g = tee
    src, dst = lane_nodes(g, "in_s")[0], lane_nodes(g, "out_w")[-1]
    path = shortest_path(g, src, dst)
    assert all(g.fine.has_edge(u, v) for u, v in zip(path, path[1:], strict=False))
    assert {g.node_lane[n] for n in path} == {"in_s", "j.s>w", "out_w"}
    with pytest.raises(nx.NetworkXNoPath):
        shortest_path(g, lane_nodes(g, "out_w")[-1], src)
