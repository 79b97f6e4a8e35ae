"""Six procedural towns of distinct character (paper: five for train/val, a disjoint test town).

| town        | character                                                      | split      |
|-------------|----------------------------------------------------------------|------------|
| grid-s7     | regular grid, a few streets removed                            | train/val  |
| irregular-s11 | jittered junctions, diagonal streets, irregular blocks       | train/val  |
| curved-s13  | grid topology with bent streets and a curved ring              | train/val  |
| tee-s17     | staggered cross streets (T-junctions) and dead-end spurs       | train/val  |
| deck-s19    | grid with streets under decks / in tunnels (UGV only)          | train/val  |
| parks-s23   | mixed: curves, T-junctions, a deck, parks and plazas (UAV only) | test       |

Every generator is a function ``seed -> StreetPlan`` plus options for the furnishing step
(parks, plazas); :func:`build_layout` turns it into a :class:`TownLayout`.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import cv2
import networkx as nx
import numpy as np

from agos.world.towns.layout import Deck, TownLayout, park_background
from agos.world.towns.look.decorate import dress
from agos.world.towns.placement import (
    ParkingSlot,
    Raster,
    free_areas,
    lane_parking_slots,
    pack_buildings,
    road_raster,
    scatter_trees,
)
from agos.world.towns.streets import (
    JUNCTION_SETBACK_M,
    ROAD_HALF_WIDTH_M,
    SIDEWALK_WIDTH_M,
    Street,
    StreetPlan,
    Surface,
    plan_to_lanes,
    strip,
    trim,
)


@dataclass(frozen=True)
class TownRecipe:
    plan: Callable[[np.random.Generator], StreetPlan]
    parks: int = 0
    plazas: int = 0
    split: str = "trainval"


def _grid_nodes(rng: np.random.Generator, n: int, spacing: tuple[float, float]) -> tuple[np.ndarray, np.ndarray]:
    xs = np.concatenate([[0.0], np.cumsum(rng.uniform(*spacing, size=n - 1))])
    ys = np.concatenate([[0.0], np.cumsum(rng.uniform(*spacing, size=n - 1))])
    return xs - xs[-1] / 2, ys - ys[-1] / 2


def _grid_plan(rng: np.random.Generator, n: int = 6, spacing=(75.0, 100.0), jitter: float = 0.0) -> StreetPlan:
    xs, ys = _grid_nodes(rng, n, spacing)
    nodes = [(float(xs[i] + rng.uniform(-jitter, jitter)), float(ys[j] + rng.uniform(-jitter, jitter)))
             for i in range(n) for j in range(n)]
    streets = [Street(i * n + j, (i + 1) * n + j) for i in range(n - 1) for j in range(n)]
    streets += [Street(i * n + j, i * n + j + 1) for i in range(n) for j in range(n - 1)]
    return StreetPlan(nodes, streets)


def _remove(plan: StreetPlan, fraction: float, rng: np.random.Generator, *, min_degree: int = 2) -> StreetPlan:
    """Drop streets at random while the network stays connected and no node falls below
    ``min_degree`` (1 allows dead ends)."""
    graph = nx.MultiGraph()
    graph.add_nodes_from(range(len(plan.nodes)))
    for k, s in enumerate(plan.streets):
        graph.add_edge(s.a, s.b, key=k)
    keep = set(range(len(plan.streets)))
    target = round(fraction * len(plan.streets))
    for k in rng.permutation(len(plan.streets)):
        if len(plan.streets) - len(keep) >= target:
            break
        s = plan.streets[int(k)]
        graph.remove_edge(s.a, s.b, key=int(k))
        if nx.is_connected(graph) and graph.degree(s.a) >= min_degree and graph.degree(s.b) >= min_degree:
            keep.discard(int(k))
        else:
            graph.add_edge(s.a, s.b, key=int(k))
    return StreetPlan(plan.nodes, [plan.streets[k] for k in sorted(keep)])


def grid_plan(rng: np.random.Generator) -> StreetPlan:
    return _remove(_grid_plan(rng), 0.12, rng)


def irregular_plan(rng: np.random.Generator) -> StreetPlan:
    plan = _grid_plan(rng, n=6, spacing=(70.0, 110.0), jitter=14.0)
    n = 6
    extra: list[Street] = []
    for _ in range(4):  # a few diagonal avenues across blocks
        i, j = int(rng.integers(0, n - 1)), int(rng.integers(0, n - 1))
        a, b = (i * n + j, (i + 1) * n + j + 1) if rng.random() < 0.5 else (i * n + j + 1, (i + 1) * n + j)
        if all({a, b} != {s.a, s.b} for s in plan.streets + extra) and not _crosses_diagonal(extra, i, j):
            extra.append(Street(a, b))
    return _remove(StreetPlan(plan.nodes, plan.streets + extra), 0.15, rng)


def _crosses_diagonal(extra: list[Street], i: int, j: int) -> bool:
    n = 6
    cell = {i * n + j, (i + 1) * n + j + 1, i * n + j + 1, (i + 1) * n + j}
    return any({s.a, s.b} <= cell for s in extra)


def curved_plan(rng: np.random.Generator) -> StreetPlan:
    plan = _grid_plan(rng, n=5, spacing=(85.0, 110.0))
    bent = []
    for s in plan.streets:
        p0, p1 = np.asarray(plan.nodes[s.a]), np.asarray(plan.nodes[s.b])
        d = p1 - p0
        normal = np.array([-d[1], d[0]]) / np.linalg.norm(d)
        if rng.random() < 0.7:
            bow = rng.choice([-1, 1]) * rng.uniform(8.0, 18.0)
            mid = (p0 + p1) / 2 + normal * bow
            bent.append(Street(s.a, s.b, via=((float(mid[0]), float(mid[1])),)))
        else:
            bent.append(s)
    return _remove(StreetPlan(plan.nodes, bent), 0.1, rng)


def tee_plan(rng: np.random.Generator) -> StreetPlan:
    """A brick pattern: full avenues east-west, cross streets alternating between columns, so
    every inner junction is a T; plus dead-end spurs into the blocks."""
    n = 6
    xs, ys = _grid_nodes(rng, n, (75.0, 95.0))
    nodes = [(float(xs[c]), float(ys[r])) for r in range(n) for c in range(n)]
    streets = [Street(r * n + c, r * n + c + 1) for r in range(n) for c in range(n - 1)]
    for r in range(n - 1):
        for c in range(n):
            if (c + r) % 2 == 0 or c in (0, n - 1):
                streets.append(Street(r * n + c, (r + 1) * n + c))
    spurs = 0
    for k in rng.permutation(len(streets)):
        street = streets[int(k)]
        p0, p1 = np.asarray(nodes[street.a]), np.asarray(nodes[street.b])
        if spurs >= 5 or abs(p0[1] - p1[1]) > 1e-6 or np.linalg.norm(p1 - p0) < 70:
            continue
        row = street.a // n
        side = 1.0 if row < n - 1 else -1.0  # into the block above, or below on the top row
        mid = (p0 + p1) / 2
        end = mid + np.array([0.0, side * 36.0])
        m, e = len(nodes), len(nodes) + 1
        nodes += [(float(mid[0]), float(mid[1])), (float(end[0]), float(end[1]))]
        streets[int(k)] = Street(street.a, m)
        streets += [Street(m, street.b), Street(m, e)]
        spurs += 1
    return StreetPlan(nodes, streets)


def deck_plan(rng: np.random.Generator) -> StreetPlan:
    plan = _remove(_grid_plan(rng), 0.1, rng)
    covered = set(int(k) for k in rng.choice(len(plan.streets), size=3, replace=False))
    return StreetPlan(plan.nodes, [Street(s.a, s.b, s.via, k in covered) for k, s in enumerate(plan.streets)])


def mixed_plan(rng: np.random.Generator) -> StreetPlan:
    plan = curved_plan(rng)
    streets = list(plan.streets)
    k = int(rng.integers(0, len(streets)))
    streets[k] = Street(streets[k].a, streets[k].b, streets[k].via, covered=True)
    return StreetPlan(plan.nodes, streets)


RECIPES: dict[str, TownRecipe] = {
    "grid": TownRecipe(grid_plan),
    "irregular": TownRecipe(irregular_plan),
    "curved": TownRecipe(curved_plan, parks=1),
    "tee": TownRecipe(tee_plan),
    "deck": TownRecipe(deck_plan),
    "parks": TownRecipe(mixed_plan, parks=3, plazas=2, split="test"),
}
TOWNS: dict[str, tuple[str, int]] = {
    "grid-s7": ("grid", 7), "irregular-s11": ("irregular", 11), "curved-s13": ("curved", 13),
    "tee-s17": ("tee", 17), "deck-s19": ("deck", 19), "parks-s23": ("parks", 23),
}
"""The benchmark's procedural towns: id -> (generator, seed)."""
TEST_TOWNS = ("parks-s23",)
DECK_BOTTOM_M, DECK_TOP_M = 6.5, 7.5


def build_layout(generator: str, seed: int) -> TownLayout:
    try:
        recipe = RECIPES[generator]
    except KeyError:
        raise ValueError(f"unknown town generator {generator!r}; known: {', '.join(RECIPES)}") from None
    rng = np.random.default_rng(seed)
    plan = recipe.plan(rng)
    geometry = plan_to_lanes(plan)
    layout = TownLayout(f"{generator}-s{seed}", generator, seed, geometry.network, list(geometry.surfaces))
    for street, line in zip(plan.streets, geometry.street_lines, strict=True):
        if street.covered:
            core = trim(line, JUNCTION_SETBACK_M, JUNCTION_SETBACK_M)
            half = ROAD_HALF_WIDTH_M + SIDEWALK_WIDTH_M + 1.0
            layout.decks.append(Deck(strip(core, -half, half), DECK_BOTTOM_M, DECK_TOP_M))
    furnish(layout, rng, parks=recipe.parks, plazas=recipe.plazas)
    return layout


KERB_OCCUPANCY = 0.6
"""Share of kerb parking slots holding a parked vehicle. City kerbs are mostly full (parking
studies count 60-90% at busy hours; the low end keeps the renders cheap): with the survey's paints
(catalog.PAINT_SHARES), a target's paint recurs in its region as it would on a real street."""


def furnish(layout: TownLayout, rng: np.random.Generator, *, parks: int = 0, plazas: int = 0,
            parked_fraction: float = KERB_OCCUPANCY) -> None:
    """Parks, plazas, buildings and parked traffic in the space the roads leave free."""
    raster = road_raster(layout.network, layout.surfaces)
    occupied = raster.dilate(3.0)
    areas = free_areas(occupied, raster, min_area_m2=1500.0)
    plaza_slots: list[ParkingSlot] = []
    for k, area in enumerate(areas[: parks + plazas]):
        kind = "park" if k < parks else "plaza"
        layout.surfaces.append(Surface(kind, area, "region"))
        _mark(occupied, raster, area)
        if kind == "park":
            layout.trees.extend(scatter_trees(area, rng))
        else:
            plaza_slots.extend(_plaza_slots(area))
    layout.buildings = pack_buildings(occupied, raster, rng)
    lane_slots = lane_parking_slots(layout.network)
    start = len(lane_slots)
    plaza = [ParkingSlot(start + i, s.position_world_m, s.yaw_rad, "", False, True) for i, s in enumerate(plaza_slots)]
    layout.slots = lane_slots + plaza
    # plazas are parking lots seen from the air; the UGV cannot reach them
    layout.parked = park_background(lane_slots, parked_fraction, rng) + park_background(plaza, 0.6, rng)
    layout.dressing = dress(layout)  # its own random stream: the layout above does not depend on it


def _mark(occupied: np.ndarray, raster: Raster, area: np.ndarray) -> None:
    cv2.fillPoly(occupied, [raster.to_px(area)], 1)


def _plaza_slots(area: np.ndarray) -> list[ParkingSlot]:
    """Rows of parking places on a plaza, 3 m apart, cars side by side facing +y."""
    contour = area.astype(np.float32).reshape(-1, 1, 2)
    x0, y0 = area.min(axis=0)
    x1, y1 = area.max(axis=0)
    out: list[ParkingSlot] = []
    for y in np.arange(y0 + 8, y1 - 8, 9.0):
        for x in np.arange(x0 + 6, x1 - 6, 3.0):
            if cv2.pointPolygonTest(contour, (float(x), float(y)), True) > 4.0:
                out.append(ParkingSlot(len(out), (round(float(x), 3), round(float(y), 3)), float(np.pi / 2), ""))
    return out


def resolve(town_id: str) -> tuple[str, int]:
    """``grid-s7`` -> ("grid", 7): a benchmark town, or any generator with any seed."""
    if town_id in TOWNS:
        return TOWNS[town_id]
    generator, _, seed = town_id.rpartition("-s")
    if generator in RECIPES and seed.isdigit():
        return generator, int(seed)
    raise ValueError(f"unknown town {town_id!r}: use one of {', '.join(TOWNS)}, <generator>-s<seed> with a "
                     f"generator in {', '.join(RECIPES)}, or an imported asset directory")
