"""Every town, procedural and imported CARLA, yields sampled episodes that are solvable when
checked independently by rendering (a verifying anchor within 50 m with line of sight, a UAV
node that sees the target, and a road path from the UGV start)."""

from __future__ import annotations

import math
from pathlib import Path

import pytest

from agos.world.episodes.sampling import sample_episode
from agos.world.episodes.solvability import check, reachable
from agos.world.sim.scene import Scene
from agos.world.towns.asset import Town, freeze, open_town
from agos.world.towns.procedural import TOWNS

pytestmark = pytest.mark.slow  # samples and renders episodes of every town: make test, not make check

CARLA = Path(__file__).resolve().parents[2] / "shared" / "maps" / "carla"
CARLA_TOWNS = ["Town01", "Town02", "Town04", "Town06", "Town07", "Town10HD"]


def _town(name: str) -> Town:
    if name in TOWNS:
        return open_town(name)
    path = CARLA / f"{name}.xodr"
    if not path.exists():
        pytest.skip(f"{path} not present")
    from agos.world.towns.imported import imported_layout

    return freeze(imported_layout(path))


@pytest.mark.parametrize("name", [*TOWNS, *CARLA_TOWNS])
def test_sampled_episode_is_solvable(name: str) -> None:
    town = _town(name)
    with Scene(town.layout, look="flat") as scene:
        spec = sample_episode(town, scene, "mid", 0, seed=3)
        t = spec.target
        uid = scene.add_vehicle(t.model, t.colour, t.position_world_m, t.yaw_rad)
        result = check(scene, town, uid, t.position_world_m, t.yaw_rad, spec.active_uav_waypoints)
    assert result.verifying_anchors, "no decision anchor can verify the target"
    anchor_xy = town.roads.positions_world_m[result.verifying_anchors[0]]
    assert math.dist(anchor_xy, t.position_world_m[:2]) <= 50.0
    assert result.uav_nodes and set(result.uav_nodes) <= set(spec.active_uav_waypoints)
    assert reachable(town, town.roads.parse_anchor_id(spec.ugv_start_waypoint), result.verifying_anchors)
    x0, y0, x1, y1 = spec.region_world_m
    assert x1 - x0 == pytest.approx(300.0) and y1 - y0 == pytest.approx(300.0)
    assert x0 <= t.position_world_m[0] <= x1 and y0 <= t.position_world_m[1] <= y1
