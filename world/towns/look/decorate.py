"""Drawing a town's dressing (:class:`~agos.world.towns.dressing.Dressing`): façade styles, rooftop
units, lamp posts and street trees along the sidewalks, the sun. Deterministic: the random stream
is the town's dressing seed and the dressing version, apart from the layout's own.
"""

from __future__ import annotations

import math

import numpy as np

from agos.world.towns.dressing import DRESSING_VERSION, Dressing, Facade, Lamp, RoofUnit, dressing_seed
from agos.world.towns.layout import TownLayout
from agos.world.towns.look.streetdressing import sidewalks
from agos.world.towns.look.texmesh import arc_length, cut, footprint
from agos.world.towns.look.textures import FACADES, GROUND_FLOORS
from agos.world.towns.placement import Building, Tree

LAMP_SPACING_M = 40.0
TREE_SPACING_M = 16.0
LAMP_SETBACK_M = 0.45
"""Lamp posts stand this far behind the kerb."""
TREE_SETBACK_M = 1.35


def dress(layout: TownLayout) -> Dressing:
    """Draw the dressing of a layout (deterministic: same layout, same dressing)."""
    seed = dressing_seed(layout.seed, layout.town_id)
    rng = np.random.default_rng([seed, DRESSING_VERSION])
    facades = tuple(_facade(b, rng) for b in layout.buildings)
    units = tuple(u for k, b in enumerate(layout.buildings) for u in _roof_units(k, b, rng))
    lamps: list[Lamp] = []
    trees: list[Tree] = []
    taken = _Occupancy(layout.buildings)
    for walk in sidewalks(layout):
        kerb = walk.kerb_m
        length = arc_length(kerb)
        if length < 8.0:
            continue
        inward = 1.0 if _left_is_outer(kerb, walk.outer_m) else -1.0
        for s in np.arange(float(rng.uniform(3.0, LAMP_SPACING_M / 2)), length - 2.0, LAMP_SPACING_M):
            p, d = _point_at(kerb, float(s))
            q = p + inward * np.array([-d[1], d[0]]) * LAMP_SETBACK_M
            if taken.free(q, 1.0):
                taken.add(q, 1.0)
                arm = math.atan2(-inward * d[0], inward * d[1])
                lamps.append(Lamp((round(float(q[0]), 3), round(float(q[1]), 3)), round(arm, 6)))
        for s in np.arange(float(rng.uniform(2.0, TREE_SPACING_M)), length - 2.0, TREE_SPACING_M):
            p, d = _point_at(kerb, float(s))
            q = p + inward * np.array([-d[1], d[0]]) * TREE_SETBACK_M
            if rng.random() < 0.25 or not taken.free(q, 2.5):
                continue
            taken.add(q, 2.0)
            trees.append(Tree((round(float(q[0]), 3), round(float(q[1]), 3)), round(float(rng.uniform(5.0, 7.5)), 3),
                              round(float(rng.uniform(1.3, 1.8)), 3)))
    azimuth = float(rng.uniform(-math.pi, math.pi))
    elevation = float(rng.uniform(math.radians(48), math.radians(62)))
    return Dressing(DRESSING_VERSION, seed, round(azimuth, 6), round(elevation, 6), facades, units, tuple(lamps),
                    tuple(trees))


def _facade(b: Building, rng: np.random.Generator) -> Facade:
    tall = b.size_m[2] > 24.0
    weights = np.array([1.0, 1.0, 1.2, 1.0, 1.4 if tall else 0.3, 1.2 if tall else 0.3, 1.0])
    style = FACADES[int(rng.choice(len(FACADES), p=weights / weights.sum()))]
    if b.size_m[2] < 7.0:
        return Facade(style, "")
    glassy = style.startswith("glass") or style == "concrete_ribbon"
    ground = "lobby" if glassy and rng.random() < 0.6 else GROUND_FLOORS[int(rng.integers(2))]
    return Facade(style, ground)


def _roof_units(k: int, b: Building, rng: np.random.Generator) -> list[RoofUnit]:
    sx, sy, _ = b.size_m
    if min(sx, sy) < 12.0:
        return []
    out = []
    for _ in range(int(rng.integers(1, 3))):
        kind = rng.random()
        if kind < 0.55:  # air handling box
            size = (float(rng.uniform(1.5, 3.5)), float(rng.uniform(1.2, 2.5)), float(rng.uniform(1.0, 1.8)))
        elif kind < 0.85:  # stair or lift housing
            size = (float(rng.uniform(3.0, 5.0)), float(rng.uniform(2.5, 4.0)), float(rng.uniform(2.4, 3.2)))
        else:  # a flat plant platform
            size = (float(rng.uniform(4.0, 7.0)), float(rng.uniform(3.0, 5.0)), float(rng.uniform(0.4, 0.7)))
        mx, my = sx / 2 - size[0] / 2 - 1.2, sy / 2 - size[1] / 2 - 1.2
        if mx <= 0 or my <= 0:
            continue
        off = (float(rng.uniform(-mx, mx)), float(rng.uniform(-my, my)))
        out.append(RoofUnit(k, (round(off[0], 3), round(off[1], 3)), tuple(round(v, 3) for v in size)))  # type: ignore[arg-type]
    return out


def _left_is_outer(kerb: np.ndarray, outer: np.ndarray) -> bool:
    mid = len(kerb) // 2
    d = kerb[min(mid + 1, len(kerb) - 1)] - kerb[max(mid - 1, 0)]
    left = np.array([-d[1], d[0]])
    return float(np.dot(left, outer[mid] - kerb[mid])) > 0


def _point_at(line: np.ndarray, s: float) -> tuple[np.ndarray, np.ndarray]:
    part = cut(line, max(0.0, s - 0.5), s + 0.5)
    d = part[-1] - part[0]
    d = d / max(float(np.hypot(*d)), 1e-9)
    return (part[0] + part[-1]) / 2, d


class _Occupancy:
    """Discs already taken (lamps, trees) on a 4 m hash grid, and building footprints on a 16 m one.

    :meth:`free` looks in every cell a clash could come from: discs up to ``radius`` plus the
    largest radius added so far away, footprints up to ``radius`` away (a footprint is filed under
    every cell its bounding box touches)."""

    POINT_CELL_M = 4.0
    RECT_CELL_M = 16.0

    def __init__(self, buildings: list[Building]) -> None:
        self.points: dict[tuple[int, int], list[tuple[np.ndarray, float]]] = {}
        self.max_radius_m = 0.0
        self.rects = [(footprint(b.center_world_m, b.size_m[:2], b.yaw_rad), b) for b in buildings]
        self.rect_grid: dict[tuple[int, int], list[int]] = {}
        for k, (corners, _) in enumerate(self.rects):
            for cell in _cells(corners.min(axis=0), corners.max(axis=0), self.RECT_CELL_M):
                self.rect_grid.setdefault(cell, []).append(k)

    def free(self, q: np.ndarray, radius: float) -> bool:
        reach = radius + self.max_radius_m
        for cell in _cells(q - reach, q + reach, self.POINT_CELL_M):
            for p, r in self.points.get(cell, []):
                if float(np.hypot(*(p - q))) < radius + r:
                    return False
        near = {k for cell in _cells(q - radius, q + radius, self.RECT_CELL_M) for k in self.rect_grid.get(cell, [])}
        for k in sorted(near):
            b = self.rects[k][1]
            c, s = math.cos(b.yaw_rad), math.sin(b.yaw_rad)
            rel = q - np.asarray(b.center_world_m)
            lx, ly = rel[0] * c + rel[1] * s, -rel[0] * s + rel[1] * c
            if abs(lx) < b.size_m[0] / 2 + radius and abs(ly) < b.size_m[1] / 2 + radius:
                return False
        return True

    def add(self, q: np.ndarray, radius: float) -> None:
        (cell,) = _cells(q, q, self.POINT_CELL_M)
        self.points.setdefault(cell, []).append((q.copy(), radius))
        self.max_radius_m = max(self.max_radius_m, radius)


def _cells(lo: np.ndarray, hi: np.ndarray, cell_m: float) -> list[tuple[int, int]]:
    """The grid cells (``cell_m`` square) that the box from ``lo`` to ``hi`` touches."""
    i0, j0 = (int(v) for v in np.floor(np.asarray(lo) / cell_m))
    i1, j1 = (int(v) for v in np.floor(np.asarray(hi) / cell_m))
    return [(i, j) for i in range(i0, i1 + 1) for j in range(j0, j1 + 1)]
