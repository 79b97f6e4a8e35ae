"""The street level of the rich look, derived from a town layout alone: road and lot surfaces,
sidewalks with kerbs, lane markings, stop lines, zebra crossings and parking bays.

Every flat surface is a list of convex pieces on a :class:`Layer` (a material at one height): the
scene draws the pieces as textured meshes, and :mod:`agos.world.towns.look.shadows` clips cast shadows
against the same pieces, so a shadow lies a few millimetres above exactly the surface it darkens.

Markings follow from the lane network, for procedural and imported towns alike (pure numpy):

- a lane's left edge: a solid yellow line inside it when the lane on the other side runs the other
  way (the two lanes draw a double yellow centre line), a dashed white line on it when that lane
  runs the same way, a solid white edge line when there is none; its right edge: a solid white
  edge line when no lane lies beyond it;
- at a lane's end into a junction a stop line across it and a zebra crossing beyond, across the
  parking strip too; at a lane's start out of a junction the crossing of that side;
- ticks between the parking places of a parking strip, and bays on plazas.

Sidewalks are the layout's own where it has them (procedural towns); imported maps get 2.5 m
sidewalks along every lane edge with no lane beyond it, cut where they would cover a road.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import cv2
import numpy as np

from agos.world.towns.lanes import Lane, LaneNetwork
from agos.world.towns.layout import TownLayout
from agos.world.towns.look.texmesh import (
    TexMesh,
    arc_length,
    ccw,
    convex_decomposition,
    convex_pieces_mesh,
    cut,
    flat_strip,
    footprint,
    merge,
    offset_line,
    simplify_strip,
)
from agos.world.towns.look.textures import TILE_M

CELL_M = 0.5
SIDEWALK_WIDTH_M = 2.5
KERB_HEIGHT_M = 0.12
KERB_TOP_M = 0.18
"""Width of the kerb stone's top along the sidewalk's road edge."""
Z = {"ground": 0.0, "grass": 0.015, "asphalt": 0.02, "junction": 0.025, "marking": 0.035, "paving": KERB_HEIGHT_M,
     "kerb": KERB_HEIGHT_M + 0.002}
"""Heights of the surfaces (the flat look's heights where both have the surface)."""
STOP_LINE_M = (4.5, 4.05)
"""Distance of a stop line's two edges before a lane's end into a junction."""
CROSSING_M = (3.6, 0.6)
"""A zebra crossing spans this range of distances from the lane's junction end."""
DASH_M, GAP_M = 3.0, 6.0


Strip = tuple[np.ndarray, np.ndarray]
"""A band between two polylines (point i of one across from point i of the other)."""


@dataclass
class Layer:
    """One material at one height: loose convex pieces and bands."""

    material: str
    z_m: float
    semantic: str
    """``ground``, ``road``, ``sidewalk``, ``marking`` or ``vegetation``."""
    loose: list[np.ndarray] = field(default_factory=list)
    """Convex polygons (K, 2), drawn as fans."""
    strips: list[Strip] = field(default_factory=list)
    """Bands (straight runs already merged), drawn as strips sharing their vertices."""

    @property
    def pieces(self) -> list[np.ndarray]:
        """Every convex piece of the layer (the bands cut in quads), for clipping shadows."""
        out = list(self.loose)
        for a, b in self.strips:
            out += _quads(a, b)
        return out

    def add_strip(self, edge_a: np.ndarray, edge_b: np.ndarray, *, max_len_m: float = 12.0) -> None:
        if len(edge_a) >= 2:
            self.strips.append(simplify_strip(edge_a, edge_b, max_len_m=max_len_m))

    def mesh(self) -> TexMesh:
        tile = TILE_M.get(self.material, 1.0)
        return merge([convex_pieces_mesh(self.loose, self.z_m, tile)]
                     + [flat_strip(a, b, self.z_m, tile) for a, b in self.strips])

    def __bool__(self) -> bool:
        return bool(self.loose or self.strips)


@dataclass
class Sidewalk:
    kerb_m: np.ndarray
    """(N, 2) the edge along the road."""
    outer_m: np.ndarray
    """(N, 2) the edge away from the road (point i across from kerb point i)."""


@dataclass
class StreetLevel:
    layers: list[Layer]
    sidewalks: list[Sidewalk]
    kerbs: TexMesh
    """Vertical kerb faces and the kerb stones' tops (material ``kerb``)."""


def _quads(a: np.ndarray, b: np.ndarray) -> list[np.ndarray]:
    """Convex quads (counter-clockwise) covering a band."""
    quads = np.stack([a[:-1], a[1:], b[1:], b[:-1]], axis=1)
    x, y = quads[:, :, 0], quads[:, :, 1]
    nxt = [1, 2, 3, 0]
    area = (x * y[:, nxt] - y * x[:, nxt]).sum(axis=1)
    quads[area < 0] = quads[area < 0][:, ::-1]
    return list(quads[np.abs(area) > 2e-4])


# ----- a raster of the drivable surface -------------------------------------------------------------
class _Raster:
    def __init__(self, bounds: tuple[float, float, float, float], pad_m: float = 20.0) -> None:
        self.x0, self.y0 = bounds[0] - pad_m, bounds[1] - pad_m
        self.w = math.ceil((bounds[2] - bounds[0] + 2 * pad_m) / CELL_M)
        self.h = math.ceil((bounds[3] - bounds[1] + 2 * pad_m) / CELL_M)
        self.ids = np.zeros((self.h, self.w), np.int32)

    def px(self, pts: np.ndarray) -> np.ndarray:
        return np.round((np.asarray(pts) - [self.x0, self.y0]) / CELL_M).astype(np.int32)

    def fill(self, polygon: np.ndarray, value: int) -> None:
        cv2.fillPoly(self.ids, [self.px(polygon)], int(value))

    def at(self, pts: np.ndarray) -> np.ndarray:
        p = self.px(pts)
        inside = (p[:, 0] >= 0) & (p[:, 1] >= 0) & (p[:, 0] < self.w) & (p[:, 1] < self.h)
        out = np.zeros(len(p), np.int32)
        out[inside] = self.ids[p[inside, 1], p[inside, 0]]
        return out


def _lane_polygon(lane: Lane) -> np.ndarray:
    left, right = lane.boundary()
    return np.concatenate([left, right[::-1]])


def lane_sides(network: LaneNetwork) -> dict[str, tuple[str, str]]:
    """For every lane outside junctions: what lies beyond its left and right edges, each
    ``opposite`` (a lane running the other way), ``same`` (one running the same way) or ``none``."""
    lanes = [network.lanes[k] for k in sorted(network.lanes) if not network.lanes[k].in_junction]
    raster = _Raster(network.bounds_m())
    for k, lane in enumerate(lanes):
        raster.fill(_lane_polygon(lane), k + 1)
    out: dict[str, tuple[str, str]] = {}
    for k, lane in enumerate(lanes):
        left, right = lane.boundary()
        d = np.gradient(lane.centre_m, axis=0)
        d /= np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-9)
        normal_left = np.stack([-d[:, 1], d[:, 0]], axis=1)
        sample = np.linspace(0, len(lane.centre_m) - 1, min(len(lane.centre_m), 7)).round().astype(int)[1:-1]
        if len(sample) == 0:
            sample = np.array([len(lane.centre_m) // 2])
        sides = []
        for edge, sign in ((left, 1.0), (right, -1.0)):
            probe = edge[sample] + sign * normal_left[sample] * 0.6
            ids = raster.at(probe)
            others = ids[(ids != 0) & (ids != k + 1)]
            if len(others) * 2 < len(sample):
                sides.append("none")
                continue
            other = lanes[int(np.bincount(others).argmax()) - 1]
            j = np.argmin(np.linalg.norm(other.centre_m[None, :, :] - probe[:, None, :], axis=2), axis=1)
            od = np.gradient(other.centre_m, axis=0)[j]
            sides.append("opposite" if float(np.sum(od * d[sample])) < 0 else "same")
        out[lane.lane_id] = (sides[0], sides[1])
    return out


def _junction_ends(network: LaneNetwork) -> tuple[set[str], set[str]]:
    """Lanes that end into a junction, and lanes that start out of one."""
    ends, starts = set(), set()
    for lane in network.lanes.values():
        if lane.in_junction:
            continue
        if any(network.lanes[s].in_junction for s in lane.successors if s in network.lanes):
            ends.add(lane.lane_id)
    for lane in network.lanes.values():
        if lane.in_junction:
            for s in lane.successors:
                if s in network.lanes and not network.lanes[s].in_junction:
                    starts.add(s)
    return ends, starts


# ----- markings ---------------------------------------------------------------------------------
def _band(centre: np.ndarray, s0: float, s1: float, left_from: float, left_to: float) -> list[Strip]:
    part = cut(centre, s0, s1)
    if len(part) < 2:
        return []
    return [simplify_strip(offset_line(part, left_from), offset_line(part, left_to), max_len_m=8.0)]


def _dashes(centre: np.ndarray, s0: float, s1: float, left_m: float, width_m: float) -> list[np.ndarray]:
    """A dashed line as quads, one a dash between points interpolated on its two edges (a 3 m run is
    straight enough); a solid line is a :func:`_band`."""
    starts = np.arange(s0 + GAP_M / 2, s1, DASH_M + GAP_M)
    if len(starts) == 0:
        return []
    ends = np.minimum(starts + DASH_M, s1)
    seg = np.linalg.norm(np.diff(centre, axis=0), axis=1)
    arc = np.concatenate([[0.0], np.cumsum(seg)])
    edges = [offset_line(centre, left_m - width_m / 2), offset_line(centre, left_m + width_m / 2)]

    def at(edge: np.ndarray, t: np.ndarray) -> np.ndarray:
        return np.stack([np.interp(t, arc, edge[:, 0]), np.interp(t, arc, edge[:, 1])], axis=1)

    quads = np.stack([at(edges[0], starts), at(edges[0], ends), at(edges[1], ends), at(edges[1], starts)], axis=1)
    return list(quads[ends - starts > 0.3])


def lane_markings(network: LaneNetwork) -> tuple[Layer, Layer]:
    """The white and yellow marking layers of every lane outside junctions (module docstring)."""
    sides = lane_sides(network)
    ends, starts = _junction_ends(network)
    white = Layer("marking_white", Z["marking"], "marking")
    yellow = Layer("marking_yellow", Z["marking"], "marking")
    for lane_id in sorted(sides):
        lane = network.lanes[lane_id]
        length = lane.length_m
        half = float(np.median(lane.width_m)) / 2
        s0 = STOP_LINE_M[0] + 0.1 if lane_id in starts else 0.0
        s1 = length - (STOP_LINE_M[0] + 0.1 if lane_id in ends else 0.0)
        if s1 - s0 < 1.0 or length < 6.0:
            continue
        c = lane.centre_m
        left, right = sides[lane_id]
        if left == "opposite":
            yellow.strips += _band(c, s0, s1, half - 0.23, half - 0.11)
        elif left == "same":
            white.loose += _dashes(c, s0, s1, half, 0.12)
        else:
            white.strips += _band(c, s0, s1, half - 0.25, half - 0.11)
        if right == "none":
            white.strips += _band(c, s0, s1, -half + 0.11, -half + 0.25)
        park = _parking_strip_m(lane)
        if lane_id in ends and length > 12.0:
            white.strips += _band(c, length - STOP_LINE_M[0], length - STOP_LINE_M[1], -half, half)
            white.loose += _zebra(c, length - CROSSING_M[0], length - CROSSING_M[1], -half - park, half)
        if lane_id in starts and length > 12.0:
            white.loose += _zebra(c, CROSSING_M[1], CROSSING_M[0], -half - park, half)
    return white, yellow


def _parking_strip_m(lane: Lane) -> float:
    """Width of a parking strip beyond the lane's right edge (0 where cars park in the lane)."""
    if lane.parking_offset_m is None:
        return 0.0
    return max(0.0, 2.0 * (lane.parking_offset_m - float(np.median(lane.width_m)) / 2))


def _zebra(centre: np.ndarray, s0: float, s1: float, left_from: float, left_to: float) -> list[np.ndarray]:
    """Stripes 0.5 m wide, 0.5 m apart, along the lane across the band [left_from, left_to], each
    one quad from its start to its end (3 m of a lane are straight enough)."""
    part = cut(centre, s0, s1)
    if len(part) < 2:
        return []
    ends = part[[0, -1]]
    d = ends[1] - ends[0]
    d = d / max(float(np.hypot(*d)), 1e-9)
    left = np.array([-d[1], d[0]])
    xs = np.arange(left_from + 0.25, left_to - 0.6 + 1e-9, 1.0)
    return [np.array([ends[0] + left * x, ends[1] + left * x, ends[1] + left * (x + 0.5), ends[0] + left * (x + 0.5)])
            for x in xs]


def parking_ticks(layout: TownLayout) -> list[np.ndarray]:
    """White ticks between the places of parking strips, and the bays of plazas."""
    out: list[np.ndarray] = []
    for slot in layout.slots:
        x, y = slot.position_world_m
        c, s = math.cos(slot.yaw_rad), math.sin(slot.yaw_rad)
        if slot.plaza:  # cars side by side facing +y: lines at x +- 1.5 m, 5 m long
            for dx in (-1.5, 1.5):
                out.append(footprint((x + dx, y), (5.0, 0.12), slot.yaw_rad - math.pi / 2))
            continue
        lane = layout.network.lanes.get(slot.lane_id)
        if lane is None or _parking_strip_m(lane) <= 0.0:
            continue
        width = _parking_strip_m(lane)  # one tick behind each place (slots are 7.5 m apart)
        out.append(footprint((x - c * 3.75, y - s * 3.75), (0.12, width * 0.8), slot.yaw_rad))
    return out


# ----- sidewalks and kerbs ----------------------------------------------------------------------
def _drivable(layout: TownLayout) -> _Raster:
    raster = _Raster(layout.network.bounds_m())
    for lane in layout.network.lanes.values():
        raster.fill(_lane_polygon(lane), 1)
    for s in layout.surfaces:
        if s.kind in ("road", "junction", "plaza"):
            raster.fill(s.polygon_m, 1)
    return raster


def sidewalks(layout: TownLayout) -> list[Sidewalk]:
    """The layout's sidewalks (kerb edge first) or, for imported maps, derived ones."""
    drivable = _drivable(layout)
    own = [s for s in layout.surfaces if s.kind == "sidewalk"]
    out: list[Sidewalk] = []
    for s in own:
        half = len(s.polygon_m) // 2
        a, b = s.polygon_m[:half], s.polygon_m[half:][::-1]
        if len(a) < 2:
            continue
        mid = len(a) // 2
        away_a = a[mid] + (a[mid] - b[mid]) / max(float(np.linalg.norm(a[mid] - b[mid])), 1e-9) * 0.8
        out.append(Sidewalk(a, b) if drivable.at(away_a[None])[0] else Sidewalk(b, a))
    if own:
        return out
    sides = lane_sides(layout.network)
    for lane_id in sorted(sides):
        lane = layout.network.lanes[lane_id]
        left, right = lane.boundary()
        for edge, side, sign in ((left, sides[lane_id][0], 1.0), (right, sides[lane_id][1], -1.0)):
            if side != "none" or arc_length(edge) < 4.0:
                continue
            outer = offset_line(edge, sign * SIDEWALK_WIDTH_M)
            probe_mid = offset_line(edge, sign * (SIDEWALK_WIDTH_M / 2 + 0.2))
            ok = (drivable.at(probe_mid) == 0) & (drivable.at(offset_line(edge, sign * (SIDEWALK_WIDTH_M - 0.1))) == 0)
            ok &= drivable.at(offset_line(edge, sign * 0.6)) == 0
            for run in _runs(ok):
                if len(run) >= 3:
                    kerb, far = edge[run], outer[run]
                    out.append(Sidewalk(kerb, far))
    return out


def _runs(mask: np.ndarray) -> list[np.ndarray]:
    idx = np.flatnonzero(mask)
    if len(idx) == 0:
        return []
    breaks = np.flatnonzero(np.diff(idx) > 1)
    return np.split(idx, breaks + 1)


def kerb_mesh(walks: list[Sidewalk]) -> TexMesh:
    """Kerb faces facing the road and the kerb stones' tops, as strips sharing their vertices."""
    tile = TILE_M["kerb"]
    parts = []
    for w in walks:
        kerb, outer = simplify_strip(w.kerb_m, w.outer_m, max_len_m=14.0, tol_m=0.06)
        across = outer - kerb
        unit = across / np.maximum(np.linalg.norm(across, axis=1, keepdims=True), 1e-9)
        inner = kerb + unit * KERB_TOP_M
        n = len(kerb)
        arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(kerb, axis=0), axis=1))]) / tile
        # the face: bottom and top rows of vertices along the kerb, normals towards the road
        face_v = np.concatenate([np.column_stack([kerb, np.zeros(n)]), np.column_stack([kerb, np.full(n, Z["kerb"])])])
        face_n = np.concatenate([np.column_stack([-unit, np.zeros(n)])] * 2)
        face_uv = np.concatenate([np.column_stack([arc, np.zeros(n)]), np.column_stack([arc, np.full(n, Z["kerb"] / tile)])])
        parts.append(_strip_faces(face_v, face_n, face_uv, towards=-unit))
        top = flat_strip(kerb, inner, Z["kerb"], tile)
        parts.append(top)
    return merge(parts)


def _strip_faces(verts: np.ndarray, normals: np.ndarray, uvs: np.ndarray, *, towards: np.ndarray) -> TexMesh:
    """Quads between the two rows of a vertical strip (row 0 = first half), wound to face ``towards``."""
    n = len(verts) // 2
    i = np.arange(n - 1)
    tri = np.concatenate([np.stack([i, i + 1, n + i + 1], 1), np.stack([i, n + i + 1, n + i], 1)])
    a, b, c = verts[tri[:, 0]], verts[tri[:, 1]], verts[tri[:, 2]]
    face = np.cross(b - a, c - a)
    want = np.concatenate([towards[:-1], towards[:-1]])
    flip = np.sum(face[:, :2] * want, axis=1) < 0
    tri[flip] = tri[flip][:, [0, 2, 1]]
    return TexMesh(verts, tri.ravel().astype(np.int64), normals, uvs)


# ----- the whole street level ---------------------------------------------------------------------
def street_level(layout: TownLayout) -> StreetLevel:
    """Layers (asphalt with junctions and plazas, grass, paving, white and yellow markings) and kerbs."""
    asphalt = Layer("asphalt", Z["asphalt"], "road")
    junction = Layer("asphalt", Z["junction"], "road")
    grass = Layer("grass", Z["grass"], "vegetation")
    for s in layout.surfaces:
        if s.kind == "road":
            half = len(s.polygon_m) // 2
            asphalt.add_strip(s.polygon_m[:half], s.polygon_m[half:][::-1])
        elif s.kind == "junction":
            junction.loose.append(ccw(s.polygon_m))
        elif s.kind in ("park", "plaza"):
            outline = cv2.approxPolyDP(s.polygon_m.astype(np.float32).reshape(-1, 1, 2), 0.6, True).reshape(-1, 2)
            (grass if s.kind == "park" else asphalt).loose.extend(convex_decomposition(outline.astype(float)))
    if not any(s.kind == "road" for s in layout.surfaces):
        for lane in layout.network.lanes.values():
            asphalt.add_strip(*lane.boundary())
    walks = sidewalks(layout)
    paving = Layer("paving", Z["paving"], "sidewalk")
    for w in walks:
        paving.add_strip(w.kerb_m, w.outer_m)
    white, yellow = lane_markings(layout.network)
    white.loose += parking_ticks(layout)
    layers = [layer for layer in (asphalt, junction, grass, paving, white, yellow) if layer]
    return StreetLevel(layers, walks, kerb_mesh(walks))
