"""E2A projection, road-graph path planning, ablation mechanics and the oracle/random policies."""

from __future__ import annotations

import math

import networkx as nx
import numpy as np
import pytest

from agos import Env
from agos.agents.names import split_name, tools_for
from agos.agents.registry import make_policy
from agos.evaluator.metrics import acg
from agos.evaluator.summary import EpisodeSummary
from agos.runtime.episode_config import EpisodeConfig, ToolConfig
from agos.runtime.geometry import distance_to_polygon
from agos.world.episodes.sampling import generate_episodes
from agos.world.sim import sensors
from agos.world.sim.options import shortest_path
from agos.world.sim.projection import candidate_region
from agos.world.sim.scene import Scene
from agos.world.towns.asset import open_town
from agos.world.towns.lanes import Lane, LaneNetwork
from agos.world.towns.roadgraph import build_road_graphs


@pytest.mark.parametrize("altitude", [40.0, 80.0, 120.0])
@pytest.mark.parametrize("yaw_deg", [0.0, 30.0, 90.0, 217.0])
def test_e2a_cell_centres_land_within_a_metre_of_the_true_ground_point(altitude: float, yaw_deg: float) -> None:
    eye = np.array([12.0, -7.0, altitude])
    yaw = math.radians(yaw_deg)
    pose = sensors._pose(eye, np.array([0.0, 0.0, -1.0]), np.array([math.cos(yaw), math.sin(yaw), 0.0]))
    intr = sensors.intrinsics_for(512, 512, 60.0)
    for r, row in enumerate(sensors.GRID_ROWS):
        for c in range(sensors.GRID_COLS):
            polygon = sensors.cell_polygon_world(f"{row}{c + 1}", pose, intr)
            centre = np.mean(polygon, axis=0)
            # the true ground point under the cell's centre pixel, by intersecting its ray with z = 0
            u, v = (c + 0.5) * 512 / 5, (r + 0.5) * 512 / 5
            ray = pose[:3, :3] @ np.array([(u - intr.cx_px) / intr.fx_px, (v - intr.cy_px) / intr.fy_px, 1.0])
            truth = eye + ray * (-eye[2] / ray[2])
            assert np.linalg.norm(centre - truth[:2]) < 1.0


@pytest.mark.parametrize("yaw_deg", [0.0, 30.0, 217.0])
def test_no_e2a_candidate_is_the_footprint_centre_and_acg_measures_from_it(yaw_deg: float) -> None:
    eye = np.array([12.0, -7.0, 80.0])
    yaw = math.radians(yaw_deg)
    pose = sensors._pose(eye, np.array([0.0, 0.0, -1.0]), np.array([math.cos(yaw), math.sin(yaw), 0.0]))
    intr = sensors.intrinsics_for(512, 512, 60.0)
    # the nadir footprint at 80 m with a 60 degree view: a square of side 2 * 80 * tan(30 deg) = 92.4 m,
    # centred below the camera at (12, -7), whichever cell was annotated (the cell is only metadata)
    for cell in ("A1", "C3", "E5"):
        polygon, centre = candidate_region(cell, pose, intr, e2a=False)
        assert centre == pytest.approx((12.0, -7.0), abs=1e-6)
        assert polygon == [centre]  # the region is the centre alone
    # a target 30 m east of the centre lies inside the footprint (half side 46.2 m): measured from the
    # whole footprint, d = 0 and ACG_e = 1; measured from the centre, d = 30 and ACG_e = 50 / (50 + 30)
    target = (42.0, -7.0)
    footprint = sensors.footprint_world(pose, intr)
    assert distance_to_polygon(target, footprint) == 0.0
    d = distance_to_polygon(target, polygon)
    assert d == pytest.approx(30.0)
    episode = EpisodeSummary.model_validate(dict(
        episode_id="e", difficulty="easy", success=False, ground_observed=False, n_confirm=0, ugv_path_length_m=0.0,
        final_distance_m=None, uav_budget=80, uav_first_visible_step=None, decisions_uav=1, decisions_ugv=0,
        candidates=[{"distance_to_polygon_m": d, "center_error_m": math.dist(target, centre)}]))
    assert acg(episode) == pytest.approx(50 / 80)
    # with E2A the candidate is the annotated cell: its ground quadrilateral and that one's centroid
    polygon, centre = candidate_region("C3", pose, intr, e2a=True)
    assert polygon == sensors.cell_polygon_world("C3", pose, intr) and len(polygon) == 4
    assert centre == pytest.approx(tuple(np.mean(polygon, axis=0)))


def _lane(lane_id: str, points, successors=(), in_junction=False) -> Lane:
    pts = np.asarray(points, dtype=float)
    dense = np.concatenate([np.linspace(pts[i], pts[i + 1], 20, endpoint=False) for i in range(len(pts) - 1)] + [pts[-1:]])
    return Lane(lane_id, dense, np.full(len(dense), 3.5), list(successors), in_junction)


def test_rgpp_paths_are_legal_on_the_fine_graph_and_shortest_on_the_decision_graph() -> None:
    # a square loop with a shortcut across: two ways from A to C, the shortcut is shorter
    net = LaneNetwork({
        "ab": _lane("ab", [(0, 0), (100, 0)], ["bc"]),
        "bc": _lane("bc", [(100, 0), (100, 100)], ["cd"]),
        "cd": _lane("cd", [(100, 100), (0, 100)], ["da"]),
        "da": _lane("da", [(0, 100), (0, 0)], ["ab"]),
        "short": _lane("short", [(0, 0), (100, 100)], ["cd"]),
    })
    net.lanes["da"].successors.append("short")
    roads = build_road_graphs(net)
    source = min(roads.anchors, key=lambda n: np.linalg.norm(roads.positions_world_m[n] - [0, 90]))
    target = min(roads.anchors, key=lambda n: np.linalg.norm(roads.positions_world_m[n] - [60, 100]))
    path = shortest_path(roads, source, target)
    assert all(roads.fine.has_edge(a, b) for a, b in zip(path, path[1:], strict=False))
    decision_len = nx.shortest_path_length(roads.decision, source, target, weight="length_m")
    assert roads.path_length_m(path) == pytest.approx(decision_len, abs=1e-6)
    assert any(roads.node_lane[n] == "short" for n in path)  # the shortcut, not the loop


def test_policy_names_and_tools() -> None:
    assert split_name("heuristic:no_rgpp") == ("heuristic", "no_rgpp")
    with pytest.raises(ValueError, match="variant"):
        split_name("heuristic:no_wings")
    with pytest.raises(ValueError, match="unknown policy"):
        make_policy("gpt-9", "uav")
    assert tools_for({"uav": "heuristic", "ugv": "heuristic"}) == {"candidates": True, "e2a": True, "rgpp": True,
                                                                   "oracle": False, "expert": False}
    assert tools_for({"uav": "heuristic:no_both", "ugv": "heuristic:no_both"}) == {
        "candidates": True, "e2a": False, "rgpp": False, "oracle": False, "expert": False}
    assert tools_for({"uav": "oracle", "ugv": "oracle"})["oracle"] is True
    assert tools_for({"uav": "baseline", "ugv": "baseline"})["candidates"] is False
    assert tools_for({"uav": "agos-agent:no_rgpp", "ugv": "agos-agent:no_rgpp"})["rgpp"] is False
    with pytest.raises(ValueError, match="no candidate tools"):
        split_name("baseline:no_e2a")
    with pytest.raises(ValueError, match="--vlm-base-url"):
        make_policy("agos-agent", "uav")


@pytest.fixture(scope="module")
def world():
    town = open_town("grid-s7")
    with Scene(town.layout, look="flat") as scene:
        episodes = generate_episodes(town, scene, per_difficulty=1, seed=1)
        yield town, scene, episodes


def _run(world, policy: str, spec, sink=None):
    town, scene, _ = world
    tools = tools_for({"uav": policy, "ugv": policy})
    config = EpisodeConfig(look="flat", tools=ToolConfig(e2a=tools["e2a"], rgpp=tools["rgpp"], oracle=tools["oracle"]))
    with Env(spec, config, run_id="t", scene=scene, town=town, sink=sink) as env:
        return env.play({r: make_policy(policy, r) for r in ("uav", "ugv")})


@pytest.mark.slow
def test_oracle_solves_every_episode_and_random_is_legal(world) -> None:
    for spec in world[2]:
        assert _run(world, "oracle", spec).success, spec.episode_id
        record = _run(world, "random", spec)
        assert record.fallbacks == 0  # random picks only legal actions with valid arguments


def test_no_rgpp_removes_go_to_candidate_and_gives_distance_hints(world) -> None:
    seen = []
    town, scene, episodes = world
    config = EpisodeConfig(look="flat", tools=ToolConfig(rgpp=False))
    policies = {r: make_policy("heuristic:no_rgpp", r) for r in ("uav", "ugv")}
    with Env(episodes[0], config, run_id="t", scene=scene, town=town) as env:
        record = env.play(policies, seen=seen)
    ugv = [o for o in seen if o.role == "ugv"]
    assert all("GO_TO_CANDIDATE" not in o.legal_actions for o in ugv)
    with_candidate = [o for o in ugv if any(c.status == "pending" for c in o.coordination.candidates)]
    assert with_candidate and all(w.distance_to_candidate_m is not None for o in with_candidate for w in o.waypoint_options)
    assert record.status == "finished"


def test_no_e2a_candidate_is_the_uav_footprint_centre(world) -> None:
    record = _run(world, "heuristic:no_e2a", world[2][0])
    assert record.candidates
    e2a = _run(world, "heuristic", world[2][0])
    # the footprint centre is below the UAV: farther from the target than the annotated cell
    assert record.candidates[0].center_error_m > e2a.candidates[0].center_error_m
    # and ACG's distance is measured from that centre, not from the whole footprint (then mostly 0)
    for c in record.candidates:
        assert c.distance_to_polygon_m == pytest.approx(c.center_error_m, abs=1e-2)
        assert c.distance_to_polygon_m > 0


def test_a_misspelt_policy_fails_before_any_process_starts(tmp_path, agos) -> None:
    from agos.agents.names import split_name

    with pytest.raises(ValueError, match="unknown policy 'heurstic'"):
        split_name("heurstic")
    with pytest.raises(ValueError, match="standin-<milliseconds>ms"):
        split_name("standin-fast")
    out = agos("eval", "--policy", "heurstic", "--run-dir", tmp_path / "r")  # in this process: the guard sees a start
    assert out.returncode == 2 and "unknown policy 'heurstic'" in out.stderr, out.stderr
    assert not (tmp_path / "r" / "logs").exists()  # nothing was started
