"""Buildings of the rich look as textured meshes, and the skyline that fills the view beyond a town.

A building is its footprint box cut in bands: a ground floor of shop fronts or a glass lobby
(4.5 m), the upper storeys in its façade style (UVs count bays and storeys, each wall fitted with
a whole number of both, so windows meet the corners), a roof and rooftop units. Meshes come
grouped by material (the texture names of :mod:`agos.world.towns.look.textures`), so the scene makes
one shape per material, not per building.

The skyline (:func:`skyline`) is a ring of city blocks around the town's placement area, derived
from the layout's bounds and the dressing seed: buildings without parapets or rooftop units and
the streets between them, never collidable; drawn so that views out of the town and UAV views at
its edge show city, not a plain.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from agos.world.towns.dressing import DRESSING_VERSION, Dressing, Facade, RoofUnit
from agos.world.towns.layout import TownLayout
from agos.world.towns.look.texmesh import TexMesh, boxes, flat_fans, footprints, walls_batch
from agos.world.towns.look.textures import (
    BAYS_PER_TILE,
    FACADE_MODULE_M,
    FACADES,
    ROOF_OF,
    SHOP_BAYS_PER_TILE,
    STOREYS_PER_TILE,
    TILE_M,
)
from agos.world.towns.placement import Building

SKYLINE_DEPTH_M = 220.0
"""How far beyond the placement area the skyline reaches (its first rows hide the rest)."""
PLACEMENT_PAD_M = 60.0
"""Buildings of the town itself stand at most this far beyond its roads (placement.Raster)."""

Meshes = dict[str, list[TexMesh]]


def _add(out: Meshes, material: str, mesh: TexMesh) -> None:
    if mesh.triangle_count:
        out.setdefault(material, []).append(mesh)


def buildings_meshes(buildings: list[Building], facades: list[Facade], *, detailed: bool = True,
                     units: tuple[RoofUnit, ...] = ()) -> Meshes:
    """The meshes of many buildings, by material; ``detailed`` adds the rooftop units
    (``RoofUnit.building`` indexes ``buildings``). Vectorised over buildings."""
    out: Meshes = {}
    n = len(buildings)
    if n == 0:
        return out
    centres = np.array([b.center_world_m for b in buildings], float)
    sizes = np.array([b.size_m for b in buildings], float)
    yaws = np.array([b.yaw_rad for b in buildings], float)
    corners = footprints(centres, sizes[:, :2], yaws)  # (N, 4, 2)
    nxt = np.roll(corners, -1, axis=1)
    length = np.hypot(*(nxt - corners).transpose(2, 0, 1))  # (N, 4)
    height = sizes[:, 2]
    styles = np.array([f.style for f in facades])
    grounds = np.array([f.ground for f in facades])
    ground_h = np.array([FACADE_MODULE_M[g][1] if g else 0.0 for g in grounds])
    module = np.array([FACADE_MODULE_M[st] for st in styles])  # (N, 2) bay, storey
    storeys = np.maximum(1, np.round((height - ground_h) / module[:, 1]))
    bays = np.maximum(1, np.round(length / module[:, :1]))
    for style in sorted(set(styles.tolist())):
        m = styles == style
        k = m.sum()
        _add(out, style, walls_batch(corners[m].reshape(-1, 2), nxt[m].reshape(-1, 2), np.repeat(ground_h[m], 4),
                                     np.repeat(height[m], 4), bays[m].ravel() / BAYS_PER_TILE, np.zeros(4 * k),
                                     np.repeat(storeys[m] / STOREYS_PER_TILE, 4)))
        roof = ROOF_OF[style]
        _add(out, roof, flat_fans(corners[m], height[m], TILE_M[roof], unit_uv=True))  # coping at the edge
    for ground in sorted(set(grounds.tolist()) - {""}):
        m = grounds == ground
        shop_bays = np.maximum(1, np.round(length[m] / FACADE_MODULE_M[ground][0]))
        _add(out, ground, walls_batch(corners[m].reshape(-1, 2), nxt[m].reshape(-1, 2), 0.0,
                                      np.repeat(ground_h[m], 4), shop_bays.ravel() / SHOP_BAYS_PER_TILE, 0.0, 1.0))
    if units and detailed:
        b_idx = np.array([u.building for u in units])
        off = np.array([u.offset_m for u in units], float)
        size = np.array([u.size_m for u in units], float)
        c, s = np.cos(yaws[b_idx]), np.sin(yaws[b_idx])
        ux = centres[b_idx, 0] + c * off[:, 0] - s * off[:, 1]
        uy = centres[b_idx, 1] + s * off[:, 0] + c * off[:, 1]
        uz = height[b_idx] + size[:, 2] / 2
        _add(out, "metal", boxes(np.column_stack([ux, uy, uz]), size / 2, yaws[b_idx], TILE_M["metal"]))
    return out


def town_buildings(layout: TownLayout, dressing: Dressing) -> Meshes:
    """Every building of the town, with its façade and rooftop units, merged by material."""
    return buildings_meshes(list(layout.buildings), list(dressing.facades), units=dressing.roof_units)


@dataclass(frozen=True)
class Skyline:
    buildings: tuple[Building, ...]
    facades: tuple[Facade, ...]
    streets: tuple[np.ndarray, ...]
    """Convex quads of the streets between the skyline's blocks."""


def skyline(layout: TownLayout, dressing: Dressing, *, block_m: float = 72.0, street_m: float = 16.0) -> Skyline:
    """City blocks on a lattice around the town's placement area, out to ``SKYLINE_DEPTH_M``."""
    rng = np.random.default_rng([dressing.texture_seed, DRESSING_VERSION, 7])
    x0, y0, x1, y1 = layout.network.bounds_m()
    ix0, iy0, ix1, iy1 = x0 - PLACEMENT_PAD_M, y0 - PLACEMENT_PAD_M, x1 + PLACEMENT_PAD_M, y1 + PLACEMENT_PAD_M
    pitch = block_m + street_m
    ox, oy = ix0 - street_m / 2, iy0 - street_m / 2
    n_out = math.ceil(SKYLINE_DEPTH_M / pitch)
    nx, ny = math.ceil((ix1 - ix0) / pitch), math.ceil((iy1 - iy0) / pitch)
    buildings: list[Building] = []
    facades: list[Facade] = []
    streets: list[np.ndarray] = []
    lo_x, hi_x = ox - n_out * pitch, ox + (nx + n_out) * pitch
    lo_y, hi_y = oy - n_out * pitch, oy + (ny + n_out) * pitch
    for i in range(-n_out, nx + n_out + 1):  # streets along y and along x, cut out of the inner area
        gx = ox + i * pitch - street_m / 2
        streets += _street_outside((gx, lo_y, gx + street_m, hi_y), (ix0, iy0, ix1, iy1))
    for j in range(-n_out, ny + n_out + 1):
        gy = oy + j * pitch - street_m / 2
        streets += _street_outside((lo_x, gy, hi_x, gy + street_m), (ix0, iy0, ix1, iy1))
    for i in range(-n_out, nx + n_out):
        for j in range(-n_out, ny + n_out):
            bx0, by0 = ox + i * pitch + street_m / 2, oy + j * pitch + street_m / 2
            if bx0 + block_m > ix0 and bx0 < ix1 and by0 + block_m > iy0 and by0 < iy1:
                continue  # inside the town's own placement area
            for qi in range(2):
                for qj in range(2):
                    sx, sy = block_m / 2 - rng.uniform(1.0, 6.0), block_m / 2 - rng.uniform(1.0, 6.0)
                    cx = bx0 + block_m / 4 * (1 + 2 * qi) + rng.uniform(-1.0, 1.0)
                    cy = by0 + block_m / 4 * (1 + 2 * qj) + rng.uniform(-1.0, 1.0)
                    h = float(rng.choice([rng.uniform(10, 22), rng.uniform(22, 60)], p=[0.55, 0.45]))
                    buildings.append(Building((float(cx), float(cy)), (float(sx), float(sy), h), (0.6, 0.6, 0.6)))
                    facades.append(Facade(FACADES[int(rng.integers(len(FACADES)))], ""))  # no shops: too far to read
    return Skyline(tuple(buildings), tuple(facades), tuple(streets))


def _street_outside(rect: tuple[float, float, float, float], hole: tuple[float, float, float, float]) -> list[np.ndarray]:
    """The parts of an axis-aligned street rectangle outside the inner area, as quads."""
    x0, y0, x1, y1 = rect
    hx0, hy0, hx1, hy1 = hole
    if x1 <= hx0 or x0 >= hx1 or y1 <= hy0 or y0 >= hy1:
        return [_quad(x0, y0, x1, y1)]
    out = []
    if x1 - x0 > y1 - y0:  # runs along x: keep the parts left and right of the hole
        if x0 < hx0:
            out.append(_quad(x0, y0, hx0, y1))
        if x1 > hx1:
            out.append(_quad(hx1, y0, x1, y1))
    else:
        if y0 < hy0:
            out.append(_quad(x0, y0, x1, hy0))
        if y1 > hy1:
            out.append(_quad(x0, hy1, x1, y1))
    return out


def _quad(x0: float, y0: float, x1: float, y1: float) -> np.ndarray:
    return np.array([[x0, y0], [x1, y0], [x1, y1], [x0, y1]], float)


def skyline_meshes(sky: Skyline) -> Meshes:
    return buildings_meshes(list(sky.buildings), list(sky.facades), detailed=False)


def ground_extent(layout: TownLayout) -> tuple[float, float, float, float]:
    """The rectangle the ground covers: the town, its placement pad and the skyline."""
    x0, y0, x1, y1 = layout.network.bounds_m()
    pad = PLACEMENT_PAD_M + SKYLINE_DEPTH_M + 120.0
    return x0 - pad, y0 - pad, x1 + pad, y1 + pad
