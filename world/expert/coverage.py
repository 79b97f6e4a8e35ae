"""What each role can search, and the waypoints of the expert's mTSP (paper, Appendix "Path
Generation of the AGOS Dataset": visible ranges, IoU pairing, role-exclusive waypoints).

The ground of an episode's region is a raster of ``CELL_M`` cells. The *searchable ground* is
where a target may stand or a searcher must look: the lanes (roads and junctions, under decks
too) and the open areas off the road (parks, plazas). Buildings block a ground camera's view.

Visible ranges (sets of searchable cells), from each role's sensors:

* a UAV node sees the nadir footprint of its camera at its altitude (a square of side
  ``2 h tan(fov / 2)``, about 92 m at 80 m and 60 deg), less the road under decks (it sees the
  deck's top);
* a UGV anchor sees the lanes, decks included, within the CONFIRM checker's distance (50 m)
  along a line of sight that no building blocks: its six views cover all directions, and the
  checker accepts no target farther away. Parks and plazas are not in its range: the UGV
  searches the roads (a target is parked on one) and cannot reach those areas.

Waypoints ("sampled to cover the map"): the UAV's are a greedy set cover of the UAV-visible
ground by the active nodes it can reach (its start first); a UGV anchor becomes a waypoint when
its range pairs with a UAV waypoint's (IoU >= 0.8, the anchor of highest IoU within
``PAIR_SEARCH_M``), and a greedy cover of the road under decks adds the anchors only the UGV can
search from; the UGV's start is one too. Unpaired waypoints are exclusive to their role
(``V_ex = V \\ V_C``): a UAV node over a park or plaza, or over ground no single anchor sees
alike, is the UAV's; an anchor under a deck is the UGV's.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import cv2
import networkx as nx
import numpy as np

from agos.world.towns.asset import Town

CELL_M = 2.0
"""Side of a ground raster cell."""
PAIR_IOU = 0.8
"""The paper's pairing threshold on |S_uav ∩ S_ugv| / |S_uav ∪ S_ugv|."""
PAIR_SEARCH_M = 20.0
"""Anchors farther than this from a UAV node are not tried as its pair (their IoU is far below
PAIR_IOU: the ranges are ~90 m wide)."""
MIN_NEW_CELLS = 25
"""A greedy cover stops adding waypoints that would add fewer new cells than this (100 m²):
slivers at the region's edge are not worth a detour (a target there is found by the mop-up)."""


@dataclass(frozen=True)
class GroundRaster:
    """The searchable ground of a region: boolean masks over cells ``(row = y, col = x)``."""

    x0_m: float
    y0_m: float
    road: np.ndarray
    """Lanes (junctions included), under decks too."""
    covered: np.ndarray
    """Lanes under a deck: hidden from the air."""
    offroad: np.ndarray
    """Parks and plazas: open to the air, off the UGV's roads."""
    blocked: np.ndarray
    """Building footprints: ground lines of sight through them are blocked."""

    @property
    def shape(self) -> tuple[int, int]:
        return self.road.shape

    def centres(self) -> tuple[np.ndarray, np.ndarray]:
        """World x and y of every cell centre, each of ``shape``."""
        h, w = self.shape
        xs = self.x0_m + (np.arange(w) + 0.5) * CELL_M
        ys = self.y0_m + (np.arange(h) + 0.5) * CELL_M
        return np.meshgrid(xs, ys)

    @property
    def uav_visible(self) -> np.ndarray:
        return (self.road & ~self.covered) | self.offroad


def ground_raster(town: Town, region: tuple[float, float, float, float]) -> GroundRaster:
    """Rasterise the searchable ground and the buildings of ``region`` (world metres)."""
    x0, y0, x1, y1 = region
    w, h = math.ceil((x1 - x0) / CELL_M), math.ceil((y1 - y0) / CELL_M)
    layout = town.layout

    def px(poly: np.ndarray) -> np.ndarray:
        return np.round((np.asarray(poly, float) - [x0, y0]) / CELL_M - 0.5).astype(np.int32)

    road, covered, offroad, blocked = (np.zeros((h, w), np.uint8) for _ in range(4))
    for lane in layout.network.lanes.values():
        left, right = lane.boundary()
        poly = np.concatenate([left, right[::-1]])
        lx0, ly0 = poly.min(axis=0)
        lx1, ly1 = poly.max(axis=0)
        if lx1 < x0 or lx0 > x1 or ly1 < y0 or ly0 > y1:
            continue
        # a lane's outline folds on itself on sharp bends: fill it as a band of quads
        quads = [np.array([left[k], left[k + 1], right[k + 1], right[k]]) for k in range(len(left) - 1)]
        cv2.fillPoly(road, [px(q) for q in quads], 1)
        if lane.covered:
            cv2.fillPoly(covered, [px(q) for q in quads], 1)
    for surface in layout.surfaces:
        if surface.kind in ("junction",):
            cv2.fillPoly(road, [px(surface.polygon_m)], 1)
        elif surface.kind in ("park", "plaza"):
            cv2.fillPoly(offroad, [px(surface.polygon_m)], 1)
    for deck in layout.decks:
        half = len(deck.polygon_m) // 2
        quads = [np.array([deck.polygon_m[k], deck.polygon_m[k + 1], deck.polygon_m[-k - 2], deck.polygon_m[-k - 1]])
                 for k in range(half - 1)]
        deck_mask = np.zeros((h, w), np.uint8)
        cv2.fillPoly(deck_mask, [px(q) for q in quads], 1)
        covered |= deck_mask & road
    for b in layout.buildings:
        c, s = math.cos(b.yaw_rad), math.sin(b.yaw_rad)
        hx, hy = b.size_m[0] / 2, b.size_m[1] / 2
        corners = [(b.center_world_m[0] + c * dx - s * dy, b.center_world_m[1] + s * dx + c * dy)
                   for dx, dy in ((-hx, -hy), (hx, -hy), (hx, hy), (-hx, hy))]
        cv2.fillPoly(blocked, [px(np.array(corners))], 1)
    road_b = road.astype(bool)
    return GroundRaster(x0, y0, road_b, covered.astype(bool) & road_b, offroad.astype(bool) & ~road_b,
                        blocked.astype(bool) & ~road_b)


def footprint_half_m(altitude_m: float, fov_deg: float) -> float:
    """Half the side of a nadir camera's square ground footprint."""
    return altitude_m * math.tan(math.radians(fov_deg) / 2)


def uav_range(ground: GroundRaster, xy: tuple[float, float], half_m: float) -> np.ndarray:
    """Flat indices of the searchable cells a UAV node at ``xy`` sees (its footprint, no decks)."""
    xs, ys = ground.centres()
    inside = (np.abs(xs - xy[0]) <= half_m) & (np.abs(ys - xy[1]) <= half_m) & ground.uav_visible
    return np.flatnonzero(inside)


def ugv_range(ground: GroundRaster, xy: tuple[float, float], reach_m: float) -> np.ndarray:
    """Flat indices of the lane cells a UGV at ``xy`` sees: within ``reach_m``, line of sight clear
    of buildings (checked every metre along the ray)."""
    xs, ys = ground.centres()
    near = ground.road & (np.hypot(xs - xy[0], ys - xy[1]) <= reach_m)
    cells = np.flatnonzero(near)
    if len(cells) == 0:
        return cells
    h, w = ground.shape
    tx, ty = xs.ravel()[cells], ys.ravel()[cells]
    steps = max(2, math.ceil(reach_m))
    t = np.linspace(0.0, 1.0, steps)[None, :]
    sx = xy[0] + (tx[:, None] - xy[0]) * t
    sy = xy[1] + (ty[:, None] - xy[1]) * t
    col = np.clip(((sx - ground.x0_m) / CELL_M).astype(int), 0, w - 1)
    row = np.clip(((sy - ground.y0_m) / CELL_M).astype(int), 0, h - 1)
    clear = ~ground.blocked[row, col].any(axis=1)
    return cells[clear]


def iou(a: np.ndarray, b: np.ndarray) -> float:
    """|a ∩ b| / |a ∪ b| of two sets of cell indices (0 for two empty sets)."""
    inter = len(np.intersect1d(a, b, assume_unique=True))
    union = len(a) + len(b) - inter
    return inter / union if union else 0.0


@dataclass
class CoverageProblem:
    """The waypoints of the expert's mTSP and how the two roles' ones relate."""

    uav_nodes: list[str]
    """V^A: UAV waypoints (grid node ids), the start first."""
    ugv_nodes: list[int]
    """V^G: UGV waypoints (decision anchors, fine node ids), the start first."""
    pairs: list[tuple[str, int]]
    """V^C as pairs (UAV node, UGV anchor) whose visible ranges have IoU >= PAIR_IOU: searching
    either searches both."""
    pair_iou: dict[tuple[str, int], float] = field(default_factory=dict)
    uav_reason: dict[str, str] = field(default_factory=dict)
    """Why each UAV waypoint is there: ``start``, ``paired``, ``offroad`` (mostly park or plaza),
    ``unmatched`` (no anchor sees its ground alike)."""
    ugv_reason: dict[int, str] = field(default_factory=dict)
    """``start``, ``paired`` or ``deck`` (road only the UGV can search)."""

    @property
    def uav_exclusive(self) -> list[str]:
        paired = {a for a, _ in self.pairs}
        return [n for n in self.uav_nodes if n not in paired]

    @property
    def ugv_exclusive(self) -> list[int]:
        paired = {g for _, g in self.pairs}
        return [n for n in self.ugv_nodes if n not in paired]


def _scc_of(graph: nx.DiGraph, start: int) -> set[int]:
    """Nodes reachable from ``start`` and back: any waypoint among them can follow any other."""
    forward = nx.descendants(graph, start) | {start}
    backward = nx.ancestors(graph, start) | {start}
    return forward & backward


def coverage_problem(town: Town, region: tuple[float, float, float, float], active: list[str], uav_start: str,
                     ugv_start: int, *, nadir_fov_deg: float, ugv_reach_m: float) -> CoverageProblem:
    """Sample both roles' waypoints over ``region`` and pair them (module docstring)."""
    grid, roads = town.uav_grid, town.roads
    ground = ground_raster(town, region)
    half = footprint_half_m(grid.altitude_m, nadir_fov_deg)
    flyable = sorted(grid.reachable(uav_start, set(active)))
    uav_ranges = {n: uav_range(ground, grid.nodes[n].position_world_m[:2], half) for n in flyable}
    uav_nodes = _greedy_cover(uav_ranges, [uav_start])

    component = _scc_of(roads.fine, ugv_start)
    ids, xy = roads.anchor_array()
    x0, y0, x1, y1 = region
    in_region = [int(n) for n, p in zip(ids, xy, strict=True)
                 if int(n) in component and x0 <= p[0] <= x1 and y0 <= p[1] <= y1]
    ugv_cache: dict[int, np.ndarray] = {}

    def seen(anchor: int) -> np.ndarray:
        if anchor not in ugv_cache:
            p = roads.positions_world_m[anchor]
            ugv_cache[anchor] = ugv_range(ground, (float(p[0]), float(p[1])), ugv_reach_m)
        return ugv_cache[anchor]

    pairs: list[tuple[str, int]] = []
    pair_iou: dict[tuple[str, int], float] = {}
    taken: set[int] = set()
    uav_reason: dict[str, str] = {uav_start: "start"}
    offroad = ground.offroad.ravel()
    for node in uav_nodes:
        nx_, ny_ = grid.nodes[node].position_world_m[:2]
        near = [a for a in in_region if a not in taken
                and math.hypot(roads.positions_world_m[a][0] - nx_, roads.positions_world_m[a][1] - ny_) <= PAIR_SEARCH_M]
        scored = sorted(((iou(uav_ranges[node], seen(a)), a) for a in near), key=lambda s: (-s[0], s[1]))
        if scored and scored[0][0] >= PAIR_IOU:
            score, anchor = scored[0]
            pairs.append((node, anchor))
            pair_iou[(node, anchor)] = round(score, 4)
            taken.add(anchor)
            uav_reason.setdefault(node, "paired")
        elif node not in uav_reason:
            cells = uav_ranges[node]
            uav_reason[node] = "offroad" if len(cells) and offroad[cells].mean() >= 0.5 else "unmatched"
    ugv_nodes = [ugv_start] + sorted(g for _, g in pairs if g != ugv_start)
    ugv_reason: dict[int, str] = {ugv_start: "start"}
    ugv_reason.update({g: "paired" for _, g in pairs if g != ugv_start})
    deck = np.flatnonzero(ground.covered.ravel())
    if len(deck):
        under = {a: np.intersect1d(seen(a), deck, assume_unique=True) for a in in_region if bool(roads.covered[a])}
        under[ugv_start] = np.intersect1d(seen(ugv_start), deck, assume_unique=True)
        for a in _greedy_cover(under, [ugv_start, *ugv_nodes[1:]])[len(ugv_nodes):]:
            ugv_nodes.append(a)
            ugv_reason[a] = "deck"
    return CoverageProblem(uav_nodes, ugv_nodes, pairs, pair_iou, uav_reason, ugv_reason)


def _greedy_cover(ranges: dict, chosen: list) -> list:
    """Greedy set cover: ``chosen`` first, then the key adding the most new cells (ties by key)
    while it adds at least MIN_NEW_CELLS."""
    out = list(chosen)
    done = np.unique(np.concatenate([ranges[k] for k in out if k in ranges] or [np.zeros(0, int)]))
    left = {k: np.setdiff1d(v, done, assume_unique=True) for k, v in ranges.items() if k not in out}
    while left:
        key = min(left, key=lambda k: (-len(left[k]), k))
        gain = left.pop(key)
        if len(gain) < MIN_NEW_CELLS:
            break
        out.append(key)
        left = {k: np.setdiff1d(v, gain, assume_unique=True) for k, v in left.items()}
    return out
