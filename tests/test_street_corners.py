"""Procedural street corners and the dressing's spacing: sidewalks meet round every junction, on
the inside of a corner and on the outside of a bend, without covering a road; lamps and trees keep
their distance from each other and from buildings across grid cells."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from agos.world.towns.look.decorate import _Occupancy
from agos.world.towns.placement import Building
from agos.world.towns.streets import ROAD_HALF_WIDTH_M, SIDEWALK_WIDTH_M, Street, StreetPlan, plan_to_lanes

CELL_M = 0.1


def _raster(polygons: list[np.ndarray], origin: np.ndarray, size_m: float) -> np.ndarray:
    """A 0.1 m raster of the square ``origin`` + [0, size_m]², 1 inside any of ``polygons``."""
    n = int(size_m / CELL_M)
    grid = np.zeros((n, n), np.uint8)
    for poly in polygons:
        cv2.fillPoly(grid, [np.round((poly - origin) / CELL_M * 8).astype(np.int32)], 1, cv2.LINE_8, shift=3)
    return grid


@pytest.mark.parametrize("name, nodes, streets", [
    ("cross", [(0, 0), (80, 0), (0, 80), (-80, 0), (0, -80)], [(0, 1), (0, 2), (0, 3), (0, 4)]),
    ("tee", [(0, 0), (80, 0), (-80, 0), (0, -80)], [(0, 1), (0, 2), (0, 3)]),
    ("bend", [(0, 0), (80, 0), (0, 80)], [(0, 1), (0, 2)]),
    ("acute", [(0, 0), (80, 0), (80 * np.cos(0.9), 80 * np.sin(0.9)), (-80, 0)], [(0, 1), (0, 2), (0, 3)]),
])
def test_sidewalks_ring_the_junction_and_never_cover_its_roads(name, nodes, streets):
    plan = StreetPlan([tuple(map(float, n)) for n in nodes], [Street(a, b) for a, b in streets])
    geometry = plan_to_lanes(plan)
    size = 2 * 30.0
    origin = np.array([-30.0, -30.0])
    walk = _raster([s.polygon_m for s in geometry.surfaces if s.kind == "sidewalk"], origin, size)
    road = _raster([s.polygon_m for s in geometry.surfaces if s.kind in ("road", "junction")], origin, size)
    lanes = _raster([np.concatenate([left, right[::-1]]) for left, right in
                     (lane.boundary() for lane in geometry.network.lanes.values())], origin, size)
    # every point within a sidewalk's reach of a street (the ray from the node along it) is
    # sidewalk or road: the corners between them included
    reach_m = ROAD_HALF_WIDTH_M + SIDEWALK_WIDTH_M - 0.2
    heads = [np.asarray(nodes[b if a == 0 else a], float) / 80.0 for a, b in streets]
    for x in np.arange(-20.0, 20.0, 0.25):
        for y in np.arange(-20.0, 20.0, 0.25):
            q = np.array([x, y])
            near = min(float(np.linalg.norm(q - max(0.0, float(q @ h)) * h)) for h in heads) <= reach_m
            u, v = ((q - origin) / CELL_M).astype(int)
            assert not near or walk[v, u] or road[v, u], f"{name}: neither sidewalk nor road at ({x:.2f}, {y:.2f})"
    # no sidewalk on a street's asphalt or on a lane beyond the edges they share (the junction
    # patch is a convex hull that overreaches at obtuse corners: the sidewalk is drawn above it)
    inside = cv2.erode(walk, np.ones((3, 3), np.uint8))
    streets = _raster([s.polygon_m for s in geometry.surfaces if s.kind == "road"], origin, size)
    overlap_m2 = np.count_nonzero(inside & (streets | lanes)) * CELL_M ** 2
    assert overlap_m2 < 1.0, f"{name}: {overlap_m2:.2f} m² of sidewalk on the road"


def test_a_bend_has_a_sidewalk_round_its_outside():
    plan = StreetPlan([(0.0, 0.0), (80.0, 0.0), (0.0, 80.0)], [Street(0, 1), Street(0, 2)])
    outer = [s for s in plan_to_lanes(plan).surfaces if s.kind == "sidewalk" and np.all(s.polygon_m.max(axis=0) <= 1e-6)]
    assert len(outer) == 1  # the piece behind the node, on the outside of the bend
    far = ROAD_HALF_WIDTH_M + SIDEWALK_WIDTH_M
    assert np.allclose(outer[0].polygon_m.min(axis=0), (-far, -far), atol=0.05)  # out to where the outer edges meet


def test_occupancy_sees_discs_and_buildings_in_neighbouring_cells():
    taken = _Occupancy([Building((20.0, 8.0), (6.0, 6.0, 10.0), (0.5, 0.5, 0.5))])
    taken.add(np.array([3.9, 1.0]), 2.0)  # a tree, in the 4 m cell (0, 0)
    assert not taken.free(np.array([8.1, 1.0]), 2.5)  # 4.2 m away, two cells over: too close
    assert taken.free(np.array([8.6, 1.0]), 2.5)
    # the building (x 17..23) is filed under 16 m cell (1, 0); something in cell (0, 0) 1.1 m from its wall
    assert not taken.free(np.array([15.9, 8.0]), 1.5)
    assert taken.free(np.array([15.9, 8.0]), 0.5)
