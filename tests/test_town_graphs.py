"""Town layout, road graphs, UAV grid, asset hash and episode sampling / files."""

from __future__ import annotations

import json
import math
import statistics
from pathlib import Path

import networkx as nx
import numpy as np
import pytest

from agos.runtime.schemas import EpisodeSpec
from agos.world.asset import AssetMismatch, Town, build_town, town_for
from agos.world.catalog import BODY_TYPES, NEAR_COLOURS, VIVID_COLOURS
from agos.world.episodes import (
    MIN_START_DISTANCE_M,
    EpisodeFileError,
    generate_episodes,
    read_episodes,
    write_episodes,
)
from agos.world.roadgraph import RoadGraphs
from agos.world.town import build_layout
from agos.world.uavgrid import ALTITUDE_M, EXPAND_M, SPACING_M

GENERATOR = "procedural-grid"
SEED = 7


@pytest.fixture(scope="module")
def town() -> Town:
    return build_town(GENERATOR, SEED)


@pytest.fixture(scope="module")
def episodes(town: Town) -> list[EpisodeSpec]:
    return generate_episodes(town, per_difficulty=6, seed=11)


# --- layout and asset hash -----------------------------------------------------------------------


def test_same_seed_same_sha_different_seed_different_sha(town: Town) -> None:
    fresh = build_town.__wrapped__  # bypass the lru_cache: really build twice
    a = fresh(GENERATOR, SEED)
    b = fresh(GENERATOR, SEED)
    assert a is not b
    assert a.sha256 == b.sha256 == town.sha256
    assert len(a.sha256) == 64
    int(a.sha256, 16)  # hex
    c = fresh(GENERATOR, SEED + 1)
    assert c.sha256 != a.sha256
    assert c.town_id == f"grid-s{SEED + 1}"


def test_layout_is_deterministic_and_connected(town: Town) -> None:
    layout = town.layout
    assert layout.town_id == "grid-s7"
    assert layout.generator == GENERATOR
    assert layout.seed == SEED
    assert len(layout.junctions) == 36
    again = build_layout(GENERATOR, SEED)
    assert again.junctions == layout.junctions
    assert again.segments == layout.segments
    assert again.parked == layout.parked
    graph = nx.Graph(layout.segments)
    graph.add_nodes_from(range(len(layout.junctions)))
    assert nx.is_connected(graph)
    assert min(d for _, d in graph.degree()) >= 2
    assert {p.slot_id for p in layout.parked} <= {s.slot_id for s in layout.slots}


def test_unknown_generator() -> None:
    with pytest.raises(ValueError, match="unknown town generator"):
        build_layout("opendrive-nowhere", 1)


def test_town_for_checks_sha(town: Town) -> None:
    assert town_for(GENERATOR, SEED) is town
    assert town_for(GENERATOR, SEED, town.sha256) is town
    wrong = "0" * 64
    with pytest.raises(AssetMismatch, match="grid-s7") as info:
        town_for(GENERATOR, SEED, wrong)
    assert "000000000000" in str(info.value)
    assert issubclass(AssetMismatch, ValueError)


# --- road graphs ---------------------------------------------------------------------------------


def test_fine_graph_strongly_connected(town: Town) -> None:
    fine = town.roads.fine
    assert fine.number_of_nodes() == len(town.roads.positions_world_m)
    assert nx.is_strongly_connected(fine)


def test_fine_edge_lengths(town: Town) -> None:
    roads = town.roads
    lengths = []
    for u, v, data in roads.fine.edges(data=True):
        expected = float(np.linalg.norm(roads.positions_world_m[v] - roads.positions_world_m[u]))
        assert data["length_m"] == pytest.approx(expected)
        lengths.append(data["length_m"])
    assert 1.5 <= statistics.median(lengths) <= 2.5


def test_decision_edge_lengths(town: Town) -> None:
    lengths = [e.length_m for e in town.roads.decision_edges.values()]
    assert len(lengths) > 100
    assert 7.0 <= statistics.median(lengths) <= 13.0


def test_decision_edges_follow_fine_graph(town: Town) -> None:
    roads = town.roads
    assert roads.decision_edges
    assert set(roads.decision.edges()) == set(roads.decision_edges)
    for (source, target), edge in roads.decision_edges.items():
        assert edge.source == source
        assert edge.target == target
        assert source in roads.anchors
        assert target in roads.anchors
        assert edge.fine_nodes[0] == source
        assert edge.fine_nodes[-1] == target
        assert len(edge.fine_nodes) >= 2
        for u, v in zip(edge.fine_nodes, edge.fine_nodes[1:], strict=False):
            assert roads.fine.has_edge(u, v)
        assert not any(n in roads.anchors for n in edge.fine_nodes[1:-1])
        total = sum(roads.fine.edges[u, v]["length_m"] for u, v in zip(edge.fine_nodes, edge.fine_nodes[1:],
                                                                        strict=False))
        assert edge.length_m == pytest.approx(total)
        assert roads.decision.edges[source, target]["length_m"] == pytest.approx(edge.length_m)


def test_anchor_kinds_and_ids(town: Town) -> None:
    roads = town.roads
    assert set(roads.anchors.values()) <= {"cruise", "junction_entry", "junction_exit", "dead_end", "fork", "merge"}
    assert "cruise" in roads.anchors.values()
    assert RoadGraphs.anchor_id(42) == "R42"
    assert RoadGraphs.parse_anchor_id("R42") == 42
    for bad in ("U1_2", "R", "Rx", "42", "r42"):
        with pytest.raises(ValueError):
            RoadGraphs.parse_anchor_id(bad)
    ids, xy = roads.anchor_array()
    assert list(ids) == sorted(roads.anchors)
    np.testing.assert_array_equal(xy, roads.positions_world_m[ids])


# --- UAV grid ------------------------------------------------------------------------------------


def test_uav_grid_spacing_and_altitude(town: Town) -> None:
    grid = town.uav_grid
    assert grid.spacing_m == SPACING_M == 40.0
    assert grid.altitude_m == ALTITUDE_M == 80.0
    x_min, y_min = town.roads.positions_world_m.min(axis=0) - EXPAND_M
    assert len(grid.nodes) > 50
    for key, node in grid.nodes.items():
        assert key == node.node_id == f"U{node.i}_{node.j}"
        x, y, z = node.position_world_m
        assert z == 80.0
        assert x == pytest.approx(x_min + 40.0 * node.i, abs=1e-3)
        assert y == pytest.approx(y_min + 40.0 * node.j, abs=1e-3)
    by_index = {(n.i, n.j): n.position_world_m for n in grid.nodes.values()}
    pairs = 0
    for (i, j), (x, y, _) in by_index.items():
        if (i + 1, j) in by_index:
            assert by_index[i + 1, j][0] - x == pytest.approx(40.0, abs=1e-6)
            assert by_index[i + 1, j][1] == y
            pairs += 1
        if (i, j + 1) in by_index:
            assert by_index[i, j + 1][1] - y == pytest.approx(40.0, abs=1e-6)
            assert by_index[i, j + 1][0] == x
            pairs += 1
    assert pairs > 50


def test_uav_nodes_near_decision_anchors(town: Town) -> None:
    _, anchor_xy = town.roads.anchor_array()
    for node in town.uav_grid.nodes.values():
        d = np.hypot(anchor_xy[:, 0] - node.position_world_m[0], anchor_xy[:, 1] - node.position_world_m[1])
        assert d.min() <= 40.0 + 1e-3  # positions are stored rounded to the millimetre


def test_uav_neighbours(town: Town) -> None:
    grid = town.uav_grid
    active = set(grid.nodes)
    full = 0
    for key, node in grid.nodes.items():
        neighbours = grid.neighbours(key, active)
        assert len(neighbours) <= 8
        assert len(set(neighbours)) == len(neighbours)
        assert key not in neighbours
        for other in neighbours:
            p = grid.nodes[other].position_world_m
            assert abs(p[0] - node.position_world_m[0]) <= 1.5 * 40.0
            assert abs(p[1] - node.position_world_m[1]) <= 1.5 * 40.0
            assert max(abs(grid.nodes[other].i - node.i), abs(grid.nodes[other].j - node.j)) == 1
        expected = sum(f"U{node.i + di}_{node.j + dj}" in active
                       for di in (-1, 0, 1) for dj in (-1, 0, 1) if di or dj)
        assert len(neighbours) == expected
        full += len(neighbours) == 8
    assert full > 0
    # only active nodes are offered
    some = next(k for k in grid.nodes if len(grid.neighbours(k, active)) == 8)
    keep = set(grid.neighbours(some, active)[:3])
    assert set(grid.neighbours(some, keep)) == keep
    assert grid.neighbours(some, set()) == []


def test_uav_inside_and_nearest(town: Town) -> None:
    grid = town.uav_grid
    region = (-100.0, -100.0, 100.0, 100.0)
    inside = grid.inside(region)
    assert inside == sorted(inside)
    expected = {k for k, n in grid.nodes.items()
                if -100 <= n.position_world_m[0] <= 100 and -100 <= n.position_world_m[1] <= 100}
    assert set(inside) == expected
    target = grid.nodes[inside[0]].position_world_m
    assert grid.nearest((target[0] + 3.0, target[1] - 2.0), inside) == inside[0]


# --- episodes ------------------------------------------------------------------------------------


def _inside(p, region) -> bool:
    return region[0] <= p[0] <= region[2] and region[1] <= p[1] <= region[3]


def test_episode_mix_and_ids(episodes: list[EpisodeSpec], town: Town) -> None:
    assert [e.difficulty for e in episodes] == ["easy"] * 6 + ["mid"] * 6 + ["hard"] * 6
    for k, ep in enumerate(episodes):
        assert ep.episode_id == f"grid-s7-{ep.difficulty}-{k % 6:03d}-v1"
        assert ep.asset_sha256 == town.sha256
        assert ep.town.town_id == "grid-s7"
        assert ep.town.seed == SEED
        assert ep.town.generator == GENERATOR
        assert ep.decision_budget == 80
    assert generate_episodes(town, per_difficulty=6, seed=11) == episodes
    assert generate_episodes(town, per_difficulty=6, seed=12) != episodes


def test_episode_regions(episodes: list[EpisodeSpec], town: Town) -> None:
    bx0, by0, bx1, by1 = town.layout.bounds_world_m()
    for ep in episodes:
        x0, y0, x1, y1 = ep.region_world_m
        side = 150.0 if ep.difficulty == "easy" else 300.0
        assert x1 - x0 == pytest.approx(side)
        assert y1 - y0 == pytest.approx(side)
        assert bx0 <= x0 and x1 <= bx1
        assert by0 <= y0 and y1 <= by1


def test_episode_targets_and_starts(episodes: list[EpisodeSpec], town: Town) -> None:
    slots = {s.position_world_m: s for s in town.layout.slots}
    occupied = town.layout.occupied_slots
    for ep in episodes:
        t = ep.target
        assert t.model in BODY_TYPES
        assert t.colour in VIVID_COLOURS
        slot = slots[(t.position_world_m[0], t.position_world_m[1])]
        assert slot.slot_id not in occupied
        assert t.yaw_rad == slot.yaw_rad
        assert _inside(t.position_world_m, ep.region_world_m)
        assert ep.active_uav_waypoints == town.uav_grid.inside(ep.region_world_m)
        assert ep.uav_start_waypoint in ep.active_uav_waypoints
        ugv = RoadGraphs.parse_anchor_id(ep.ugv_start_waypoint)
        assert town.roads.anchors[ugv] == "cruise"
        p = town.roads.positions_world_m[ugv]
        assert _inside(p, ep.region_world_m)
        assert math.dist(p, t.position_world_m[:2]) >= MIN_START_DISTANCE_M


def test_distractors(episodes: list[EpisodeSpec], town: Town) -> None:
    slots = {s.position_world_m for s in town.layout.slots}
    for ep in episodes:
        if ep.difficulty in ("easy", "mid"):
            assert ep.distractors == []
            continue
        assert 2 <= len(ep.distractors) <= 3
        target = ep.target
        for d in ep.distractors:
            same_model_near_colour = d.model == target.model and d.colour in NEAR_COLOURS[target.colour]
            same_colour_other_model = d.colour == target.colour and d.model != target.model
            assert same_model_near_colour or same_colour_other_model
            assert (d.position_world_m[0], d.position_world_m[1]) in slots
            assert _inside(d.position_world_m, ep.region_world_m)
            assert math.dist(d.position_world_m, target.position_world_m) >= 30.0
        positions = [d.position_world_m for d in ep.distractors]
        assert len(set(positions)) == len(positions)


def test_write_read_round_trip(episodes: list[EpisodeSpec], tmp_path: Path) -> None:
    path = tmp_path / "nested" / "split.jsonl"
    write_episodes(path, episodes)
    lines = path.read_text().splitlines()
    assert len(lines) == len(episodes)
    assert json.loads(lines[0])["type"] == "episode_spec"
    assert read_episodes(path) == episodes


def test_read_skips_blank_lines(episodes: list[EpisodeSpec], tmp_path: Path) -> None:
    path = tmp_path / "blank.jsonl"
    path.write_text("\n" + episodes[0].model_dump_json() + "\n   \n" + episodes[1].model_dump_json() + "\n")
    assert read_episodes(path) == episodes[:2]


def _file_with_line_2(tmp_path: Path, episodes: list[EpisodeSpec], second: str) -> Path:
    path = tmp_path / "bad.jsonl"
    path.write_text(episodes[0].model_dump_json() + "\n" + second + "\n" + episodes[1].model_dump_json() + "\n")
    return path


def test_read_bad_json(episodes: list[EpisodeSpec], tmp_path: Path) -> None:
    path = _file_with_line_2(tmp_path, episodes, '{"episode_id": "x",')
    with pytest.raises(EpisodeFileError) as info:
        read_episodes(path)
    message = str(info.value)
    assert str(path) in message
    assert f"{path}:2:" in message
    assert "JSON" in message


def test_read_missing_field(episodes: list[EpisodeSpec], tmp_path: Path) -> None:
    data = json.loads(episodes[3].model_dump_json())
    del data["uav_start_waypoint"]
    path = _file_with_line_2(tmp_path, episodes, json.dumps(data))
    with pytest.raises(EpisodeFileError) as info:
        read_episodes(path)
    message = str(info.value)
    assert f"{path}:2:" in message
    assert "uav_start_waypoint" in message


def test_read_wrong_type(episodes: list[EpisodeSpec], tmp_path: Path) -> None:
    data = json.loads(episodes[3].model_dump_json())
    data["decision_budget"] = "lots"
    path = _file_with_line_2(tmp_path, episodes, json.dumps(data))
    with pytest.raises(EpisodeFileError) as info:
        read_episodes(path)
    message = str(info.value)
    assert f"{path}:2:" in message
    assert "decision_budget" in message


def test_read_nested_wrong_type(episodes: list[EpisodeSpec], tmp_path: Path) -> None:
    data = json.loads(episodes[0].model_dump_json())
    data["target"]["yaw_rad"] = "north"
    path = tmp_path / "nested.jsonl"
    path.write_text(json.dumps(data) + "\n")
    with pytest.raises(EpisodeFileError) as info:
        read_episodes(path)
    assert f"{path}:1:" in str(info.value)
    assert "target.yaw_rad" in str(info.value)


@pytest.mark.parametrize("content", ["", "\n\n  \n"])
def test_read_empty_file(tmp_path: Path, content: str) -> None:
    path = tmp_path / "empty.jsonl"
    path.write_text(content)
    with pytest.raises(EpisodeFileError, match="no episodes") as info:
        read_episodes(path)
    assert str(path) in str(info.value)


def test_read_missing_file(tmp_path: Path) -> None:
    path = tmp_path / "absent.jsonl"
    with pytest.raises(EpisodeFileError) as info:
        read_episodes(path)
    assert str(path) in str(info.value)
