"""Vehicle meshes by body type for the ``rich`` look; pure numpy (the scene turns them into shapes).

A vehicle is built from side profiles (x forward, z up, metres, origin on the road under the
vehicle's centre) extruded across the width: a lower body (bumpers, hood, trunk or bed), a
greenhouse narrowed towards the roof (sloped windscreen, roof, rear window), for trucks a cargo
box. Dark glass, wheels, wheel arches, head and tail lights, plates and a grille are drawn on top
as thin faces a centimetre proud of the body. Every face has its own vertices and its flat
normal (PyBullet has no per-face colour), and triangles are grouped by *material*: the scene
gives each material its colour, so one geometry serves every paint.

Attributes a careful viewer can check (:class:`VehicleAttributes`), each drawn so that it shows
from the ground as well as from above (docs/WORLD.md, "Cues a viewer can check"): a two-tone roof
(the greenhouse, pillars and roof in a contrasting colour), a roof rack carrying a cargo box, a
stripe over the whole length (bumper, hood, roof, trunk, rear) and along both sides. The same
inputs give the same vertices, byte for byte; :func:`vehicle_mesh` is cached.

Collisions are not meshes: :attr:`VehicleMesh.collision_boxes` are a few boxes around the parts.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from functools import lru_cache

import numpy as np

from agos.world.towns.catalog import colour_rgb
from agos.world.towns.look.texmesh import ccw

MATERIALS: tuple[str, ...] = ("paint", "roof", "stripe", "glass", "dark", "rim", "rack", "cargo", "head", "tail",
                              "plate")
"""Material groups of a vehicle mesh; ``paint``, ``roof`` and ``stripe`` take colours from the
vehicle's paint and attributes, the others are fixed (:data:`FIXED_RGB`)."""
FIXED_RGB: dict[str, tuple[float, float, float]] = {
    "glass": (0.09, 0.11, 0.14),
    "dark": (0.05, 0.05, 0.05),
    "rim": (0.55, 0.56, 0.58),
    "rack": (0.16, 0.16, 0.17),
    "cargo": (0.50, 0.51, 0.53),
    "head": (0.97, 0.95, 0.82),
    "tail": (0.78, 0.04, 0.04),
    "plate": (0.95, 0.95, 0.93),
}
RICH_BODY_TYPES: tuple[str, ...] = ("sedan", "hatchback", "suv", "pickup", "van", "box_truck", "bus")
ATTRIBUTE_BODY_TYPES: tuple[str, ...] = ("sedan", "hatchback", "suv", "pickup")
"""The cars, the body types that carry attributes: on a van, a box truck or a bus a roof box or a
stripe is out of sight from a ground camera below their roof (bench/bench_cues.py)."""
ROOF_COLOUR = "white"
"""The two-tone roof's colour (a black one would pass for dark glass from above)."""
DECAL_M = 0.012
"""How far glass, stripes and the side windows stand proud of the face they are drawn on; lights,
plates, the grille and the bus's end glass stand twice as far (over a stripe)."""


@dataclass(frozen=True)
class VehicleAttributes:
    """Checkable details; the default is a plain vehicle in one paint."""

    roof: str | None = None
    """Colour name of a two-tone roof: the greenhouse (pillars, window frames, roof) in that colour
    (a bus: its roof and a band above the windows); None: all in the body's paint."""
    rack: bool = False
    """A roof rack carrying a closed cargo box: two dark rails, two cross bars and a grey box on them."""
    stripe: str | None = None
    """Colour name of a stripe over the whole length (front, hood, roof, trunk, rear) and along
    both sides, or None."""


@dataclass(frozen=True)
class _Prism:
    profile_xz: tuple[tuple[float, float], ...]
    """Convex side profile."""
    half_width_bottom_m: float
    half_width_top_m: float
    role: str
    """``lower`` (bumpers to beltline), ``cabin`` (greenhouse) or ``box`` (cargo box, bus body)."""
    glass_edges: tuple[int, ...] = ()
    """Profile edges (i to i+1) carrying an inset glass pane: windscreen, rear window."""
    windows_x: tuple[tuple[float, float], ...] = ()
    """Side windows: x ranges of the inset side outline drawn as glass."""
    windows_z: tuple[float, float] | None = None
    """Height range of the side windows (default: the inset outline's own)."""


@dataclass(frozen=True)
class _Spec:
    length_m: float
    width_m: float
    prisms: tuple[_Prism, ...]
    wheels_x: tuple[float, ...]
    wheel_radius_m: float
    wheel_width_m: float = 0.22
    front_glass_z: tuple[float, float] | None = None
    """Windscreen drawn on a vertical front face (bus)."""
    rear_glass_z: tuple[float, float] | None = None
    doors_x: tuple[tuple[float, float], ...] = ()
    """Dark doors on the right (kerb) side, floor to window top (bus)."""
    roof_unit: tuple[float, float, float] | None = None
    """(x centre, length, height) of a box on the roof (bus air conditioning)."""
    tail_lights: str = "wide"
    """``wide``: low horizontal lamps at the rear corners; ``tall``: upright lamps up the rear corners
    (the hatchback's end-on cue)."""
    grille: str = "dark"
    """Material of the grille: ``dark``, or ``rim`` for a tall bright grille (the pickup's front cue)."""
    spare_wheel: tuple[float, float] | None = None
    """(z centre, radius) of a spare wheel on the rear door (the SUV's end-on cue)."""


@dataclass(frozen=True)
class VehicleMesh:
    """Triangles by material in the vehicle frame, and the boxes that collide."""

    name: str
    length_m: float
    width_m: float
    height_m: float
    triangles: dict[str, np.ndarray] = field(compare=False)
    """Material -> (T, 3, 3) float64 triangle corners, counter-clockwise seen from outside."""
    collision_boxes: tuple[tuple[tuple[float, float, float], tuple[float, float, float]], ...]
    """(centre, half extents) in the vehicle frame."""

    def arrays(self, material: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Vertices (V, 3), indices (V,) and flat normals (V, 3) of one material."""
        tris = self.triangles[material]
        vertices = tris.reshape(-1, 3)
        normal = np.cross(tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0])
        normal /= np.maximum(np.linalg.norm(normal, axis=1, keepdims=True), 1e-12)
        return vertices, np.arange(len(vertices)), np.repeat(normal, 3, axis=0)

    def triangle_count(self) -> int:
        return sum(len(t) for t in self.triangles.values())


def _specs() -> dict[str, _Spec]:
    return {
        "sedan": _Spec(4.6, 1.8, (
            _Prism(((2.30, 0.32), (2.30, 0.62), (2.18, 0.75), (0.85, 0.92), (-1.45, 0.96), (-2.22, 0.91),
                    (-2.30, 0.78), (-2.30, 0.32), (-2.05, 0.22), (2.05, 0.22)), 0.90, 0.90, "lower"),
            _Prism(((0.98, 0.90), (0.12, 1.37), (-0.98, 1.38), (-1.68, 0.94)), 0.84, 0.67, "cabin",
                   glass_edges=(0, 2), windows_x=((-0.32, 1.2), (-2.0, -0.44))),
        ), wheels_x=(1.38, -1.37), wheel_radius_m=0.32),
        "hatchback": _Spec(3.9, 1.72, (
            _Prism(((1.95, 0.32), (1.95, 0.62), (1.84, 0.75), (1.00, 0.90), (-1.85, 0.97), (-1.95, 0.90),
                    (-1.95, 0.32), (-1.75, 0.22), (1.75, 0.22)), 0.86, 0.86, "lower"),
            _Prism(((1.08, 0.88), (0.26, 1.53), (-1.72, 1.55), (-1.91, 0.93)), 0.81, 0.69, "cabin",
                   glass_edges=(0, 2), windows_x=((-0.52, 1.2), (-1.38, -0.64))),
        ), wheels_x=(1.25, -1.25), wheel_radius_m=0.30, tail_lights="tall"),
        "suv": _Spec(4.9, 2.0, (
            _Prism(((2.45, 0.44), (2.45, 0.86), (2.30, 0.99), (1.20, 1.08), (-2.40, 1.12), (-2.45, 1.05),
                    (-2.45, 0.44), (-2.25, 0.32), (2.25, 0.32)), 1.0, 1.0, "lower"),
            _Prism(((1.26, 1.06), (0.50, 1.80), (-2.22, 1.82), (-2.40, 1.10)), 0.95, 0.83, "cabin",
                   glass_edges=(0, 2), windows_x=((-0.32, 1.3), (-1.48, -0.44), (-2.6, -1.60))),
        ), wheels_x=(1.50, -1.45), wheel_radius_m=0.38, wheel_width_m=0.26, spare_wheel=(0.84, 0.30)),
        "pickup": _Spec(5.3, 2.0, (
            _Prism(((2.65, 0.46), (2.65, 0.90), (2.50, 1.02), (1.05, 1.11), (-2.65, 1.12), (-2.65, 0.46),
                    (-2.45, 0.38), (2.45, 0.38)), 1.0, 1.0, "lower"),
            _Prism(((1.10, 1.09), (0.42, 1.84), (-0.86, 1.86), (-0.98, 1.10)), 0.95, 0.84, "cabin",
                   glass_edges=(0, 2), windows_x=((-0.20, 1.2), (-1.2, -0.32))),
        ), wheels_x=(1.68, -1.75), wheel_radius_m=0.39, wheel_width_m=0.26, grille="rim"),
        "van": _Spec(5.2, 2.0, (
            _Prism(((2.60, 0.38), (2.60, 0.76), (2.45, 0.93), (1.85, 1.05), (-2.60, 1.05), (-2.60, 0.38),
                    (-2.45, 0.30), (2.45, 0.30)), 1.0, 1.0, "lower"),
            _Prism(((1.92, 1.02), (1.12, 2.06), (-2.56, 2.10), (-2.60, 1.03)), 0.99, 0.92, "cabin",
                   glass_edges=(0, 2), windows_x=((0.30, 1.6),), windows_z=(1.12, 1.78)),
        ), wheels_x=(1.78, -1.70), wheel_radius_m=0.35, wheel_width_m=0.24),
        "box_truck": _Spec(7.4, 2.4, (
            _Prism(((3.70, 0.52), (3.70, 1.30), (3.55, 1.44), (1.92, 1.44), (1.92, 0.52)), 1.13, 1.13, "lower"),
            _Prism(((3.56, 1.42), (3.28, 2.38), (1.98, 2.42), (1.94, 1.42)), 1.10, 1.02, "cabin",
                   glass_edges=(0,), windows_x=((2.0, 3.6),)),
            _Prism(((1.78, 0.98), (1.78, 3.34), (-3.70, 3.34), (-3.70, 0.98)), 1.20, 1.20, "box"),
        ), wheels_x=(2.75, -2.35), wheel_radius_m=0.50, wheel_width_m=0.34),
        "bus": _Spec(11.0, 2.5, (
            _Prism(((5.50, 0.40), (5.50, 2.92), (5.36, 3.12), (-5.36, 3.12), (-5.50, 2.92), (-5.50, 0.40),
                    (-5.30, 0.30), (5.30, 0.30)), 1.25, 1.25, "box",
                   windows_x=((3.9, 5.2), (2.6, 3.78), (1.3, 2.48), (0.0, 1.18), (-1.3, -0.12), (-2.6, -1.42),
                              (-3.9, -2.72), (-5.3, -4.02)), windows_z=(1.30, 2.72)),
        ), wheels_x=(3.85, -2.75), wheel_radius_m=0.50, wheel_width_m=0.32,
            front_glass_z=(1.05, 2.80), rear_glass_z=(2.0, 2.75),
            doors_x=((4.25, 5.15), (-0.45, 0.55)), roof_unit=(0.6, 2.6, 0.28)),
    }


_SPECS = _specs()


class _Builder:
    def __init__(self) -> None:
        self.tris: dict[str, list[np.ndarray]] = {m: [] for m in MATERIALS}

    def add(self, material: str, polygon: np.ndarray, outward: np.ndarray) -> None:
        """A convex planar polygon (N, 3), fanned, wound so its normal points along ``outward``."""
        p = np.asarray(polygon, float)
        if len(p) < 3:
            return
        n = np.cross(p[1] - p[0], p[2] - p[0])
        for k in range(2, len(p) - 1):  # the first triangle may be degenerate; use the largest
            c = np.cross(p[k] - p[0], p[k + 1] - p[0])
            if np.linalg.norm(c) > np.linalg.norm(n):
                n = c
        if np.dot(n, outward) < 0:
            p = p[::-1]
        for k in range(1, len(p) - 1):
            self.tris[material].append(np.stack([p[0], p[k], p[k + 1]]))

    def box(self, material: str, lo: tuple[float, float, float], hi: tuple[float, float, float]) -> None:
        x0, y0, z0 = lo
        x1, y1, z1 = hi
        c = np.array([(x0 + x1) / 2, (y0 + y1) / 2, (z0 + z1) / 2])
        corners = np.array([[x, y, z] for x in (x0, x1) for y in (y0, y1) for z in (z0, z1)])
        for axis in range(3):
            for side in (0, 1):
                face = corners[corners[:, axis] == (lo, hi)[side][axis]]
                face = face[_ring_order(face, axis)]
                out = np.zeros(3)
                out[axis] = 1 if side else -1
                self.add(material, face, out if np.dot(face.mean(0) - c, out) >= 0 else -out)

    def result(self) -> dict[str, np.ndarray]:
        return {m: np.stack(t) for m, t in self.tris.items() if t}


def _ring_order(face: np.ndarray, axis: int) -> np.ndarray:
    a, b = [k for k in range(3) if k != axis]
    centre = face.mean(0)
    return np.argsort(np.arctan2(face[:, b] - centre[b], face[:, a] - centre[a]), kind="stable")


def _clip(poly: np.ndarray, axis: int, value: float, keep_above: bool) -> np.ndarray:
    """Sutherland-Hodgman clip of a 2-D polygon by ``poly[:, axis] >= value`` (or <=)."""
    out = []
    sign = 1.0 if keep_above else -1.0
    for k in range(len(poly)):
        p, q = poly[k], poly[(k + 1) % len(poly)]
        dp, dq = sign * (p[axis] - value), sign * (q[axis] - value)
        if dp >= 0:
            out.append(p)
        if (dp >= 0) != (dq >= 0):
            out.append(p + (q - p) * (dp / (dp - dq)))
    return np.asarray(out).reshape(-1, 2)


def _inset(poly: np.ndarray, d: float) -> np.ndarray:
    """A convex counter-clockwise polygon with every edge moved ``d`` inwards."""
    n = len(poly)
    out = []
    for k in range(n):
        p0, p1, p2 = poly[k - 1], poly[k], poly[(k + 1) % n]
        e0, e1 = p1 - p0, p2 - p1
        n0 = np.array([-e0[1], e0[0]]) / np.linalg.norm(e0)
        n1 = np.array([-e1[1], e1[0]]) / np.linalg.norm(e1)
        a0, a1 = p0 + d * n0, p1 + d * n1
        m = np.array([e0, -e1]).T
        if abs(np.linalg.det(m)) < 1e-9:
            out.append(p1 + d * n1)
        else:
            t = np.linalg.solve(m, a1 - a0)[0]
            out.append(a0 + t * e0)
    return np.asarray(out)


class _Side:
    """The tapered side plane of a prism: y = sign * (w0 + slope * (z - z0))."""

    def __init__(self, prism: _Prism, sign: float) -> None:
        zs = [z for _, z in prism.profile_xz]
        self.z0, z1 = min(zs), max(zs)
        self.w0 = prism.half_width_bottom_m
        self.slope = (prism.half_width_top_m - prism.half_width_bottom_m) / (z1 - self.z0)
        self.sign = sign

    def y(self, z: np.ndarray, proud: float = 0.0) -> np.ndarray:
        return self.sign * (self.w0 + self.slope * (np.asarray(z) - self.z0) + proud)

    def lift(self, poly_xz: np.ndarray, proud: float = 0.0) -> np.ndarray:
        return np.column_stack([poly_xz[:, 0], self.y(poly_xz[:, 1], proud), poly_xz[:, 1]])

    def outward(self) -> np.ndarray:
        return np.array([0.0, self.sign, -self.slope])


def _prism(b: _Builder, prism: _Prism, *, top_material: str, attrs: VehicleAttributes, stripe_sides: bool) -> None:
    prof = ccw(np.asarray(prism.profile_xz, float))
    sides = (_Side(prism, 1.0), _Side(prism, -1.0))
    body = "roof" if attrs.roof is not None and prism.role == "cabin" else "paint"
    for side in sides:
        b.add(body, side.lift(prof), side.outward())
    n = len(prof)
    for k in range(n):
        p, q = prof[k], prof[(k + 1) % n]
        edge = q - p
        normal_xz = np.array([edge[1], -edge[0]]) / np.linalg.norm(edge)
        out = np.array([normal_xz[0], 0.0, normal_xz[1]])
        corners = np.array([[p[0], sides[0].y(p[1]), p[1]], [q[0], sides[0].y(q[1]), q[1]],
                            [q[0], sides[1].y(q[1]), q[1]], [p[0], sides[1].y(p[1]), p[1]]])
        b.add(top_material if normal_xz[1] > 0.9 else body, corners, out)
        original = tuple(map(tuple, prof[[k, (k + 1) % n]]))
        if _edge_index(prism, original) in prism.glass_edges:
            _pane(b, corners, out, margin_m=0.07)
        elif attrs.stripe is not None and normal_xz[1] > -0.6:  # every face but the underside
            _band(b, "stripe", corners, out, half_m=0.20)
    for side in sides:
        if prism.windows_x:
            outline = _inset(prof, 0.07)
            if prism.windows_z is not None:
                outline = _clip(_clip(outline, 1, prism.windows_z[0], True), 1, prism.windows_z[1], False)
            for x0, x1 in prism.windows_x:
                pane = _clip(_clip(outline, 0, x0, True), 0, x1, False)
                if len(pane) >= 3:
                    b.add("glass", side.lift(pane, DECAL_M), side.outward())
        if stripe_sides and attrs.stripe is not None:
            z_hi = max(z for _, z in prism.profile_xz)
            band = _clip(_clip(_inset(prof, 0.04), 1, z_hi - 0.28, True), 1, z_hi - 0.06, False)
            if len(band) >= 3:
                b.add("stripe", side.lift(band, DECAL_M), side.outward())


def _edge_index(prism: _Prism, edge: tuple[tuple[float, float], ...]) -> int:
    pts = [tuple(map(float, p)) for p in prism.profile_xz]
    a, c = (tuple(map(float, e)) for e in edge)
    for k in range(len(pts)):
        if {pts[k], pts[(k + 1) % len(pts)]} == {a, c}:
            return k
    return -1


def _pane(b: _Builder, quad: np.ndarray, out: np.ndarray, *, margin_m: float) -> None:
    """A glass pane inset in a quad face (corners: left-p, left-q, right-q, right-p)."""
    lp, lq, rq, rp = quad
    along = (lq - lp) / np.linalg.norm(lq - lp)
    across_l, across_r = (rp - lp) / np.linalg.norm(rp - lp), (lp - rp) / np.linalg.norm(lp - rp)
    pane = np.array([lp + margin_m * along + margin_m * across_l, lq - margin_m * along + margin_m * across_l,
                     rq - margin_m * along + margin_m * across_r, rp + margin_m * along + margin_m * across_r])
    b.add("glass", pane + DECAL_M * out, out)


def _band(b: _Builder, material: str, quad: np.ndarray, out: np.ndarray, *, half_m: float) -> None:
    """A stripe of ``half_m`` either side of the centre line of a face across the width."""
    lp, lq, rq, rp = quad
    mp, mq = (lp + rp) / 2, (lq + rq) / 2
    y = np.array([0.0, half_m, 0.0])
    b.add(material, np.array([mp + y, mq + y, mq - y, mp - y]) + DECAL_M * out, out)


def _rect_x(b: _Builder, material: str, x: float, y0: float, y1: float, z0: float, z1: float, facing: float) -> None:
    """A rectangle on a face looking along +x (facing 1) or -x (facing -1), over any stripe."""
    x = x + facing * 2 * DECAL_M
    b.add(material, np.array([[x, y0, z0], [x, y1, z0], [x, y1, z1], [x, y0, z1]]), np.array([facing, 0, 0]))


def _wheel(b: _Builder, x: float, y_centre: float, radius: float, width: float, segments: int = 8) -> None:
    a = 2 * math.pi * (np.arange(segments) + 0.5) / segments
    ring = np.column_stack([radius * np.cos(a), radius * np.sin(a)])  # (x, z) around the hub
    sign = 1.0 if y_centre > 0 else -1.0
    y_out, y_in = y_centre + sign * width / 2, y_centre - sign * width / 2
    centre = np.array([x, y_centre, radius])
    for y, s in ((y_out, sign), (y_in, -sign)):
        b.add("dark", np.column_stack([x + ring[:, 0], np.full(segments, y), radius + ring[:, 1]]), np.array([0, s, 0]))
    for k in range(segments):
        p, q = ring[k], ring[(k + 1) % segments]
        quad = np.array([[x + p[0], y_out, radius + p[1]], [x + q[0], y_out, radius + q[1]],
                         [x + q[0], y_in, radius + q[1]], [x + p[0], y_in, radius + p[1]]])
        b.add("dark", quad, quad.mean(0) - centre * [1, 0, 1] - [0, quad.mean(0)[1], 0])
    hub = 0.55 * ring
    y_hub = y_out + sign * 0.01
    b.add("rim", np.column_stack([x + hub[:, 0], np.full(segments, y_hub), radius + hub[:, 1]]), np.array([0, sign, 0]))


def _spare_wheel(b: _Builder, x_rear: float, z: float, radius: float, depth: float = 0.22, segments: int = 16) -> None:
    """A spare wheel on a rear face at ``x_rear`` (looking along -x): a dark tyre and a bright hub."""
    a = 2 * math.pi * (np.arange(segments) + 0.5) / segments
    ring = np.column_stack([radius * np.cos(a), radius * np.sin(a)])  # (y, z) around the hub
    x0, x1 = x_rear, x_rear - depth
    b.add("dark", np.column_stack([np.full(segments, x1), ring[:, 0], z + ring[:, 1]]), np.array([-1.0, 0, 0]))
    for k in range(segments):
        p, q = ring[k], ring[(k + 1) % segments]
        quad = np.array([[x0, p[0], z + p[1]], [x0, q[0], z + q[1]], [x1, q[0], z + q[1]], [x1, p[0], z + p[1]]])
        b.add("dark", quad, np.array([0.0, (p[0] + q[0]) / 2, (p[1] + q[1]) / 2]))
    hub = 0.5 * ring
    b.add("rim", np.column_stack([np.full(segments, x1 - 0.01), hub[:, 0], z + hub[:, 1]]), np.array([-1.0, 0, 0]))


def _arch(b: _Builder, x: float, radius: float, y_side: float, segments: int = 12) -> None:
    """A dark half ring around a wheel, drawn on the body side: the gap of the wheel arch."""
    a = math.pi * np.arange(segments + 1) / segments
    r = radius + 0.07
    pts = np.column_stack([x + r * np.cos(a), np.full(segments + 1, y_side), radius + r * np.sin(a)])
    sign = 1.0 if y_side > 0 else -1.0
    b.add("dark", pts, np.array([0.0, sign, 0.0]))


def _front_rear(spec: _Spec) -> tuple[tuple[float, float, float, float], tuple[float, float, float, float]]:
    """(x, z low, z high, half width) of the vertical front face and of the vertical rear face."""
    faces = []
    for prism in spec.prisms:
        for x in {max(x for x, _ in prism.profile_xz), min(x for x, _ in prism.profile_xz)}:
            zs = [z for px, z in prism.profile_xz if px == x]
            if len(zs) >= 2:
                faces.append((x, min(zs), max(zs), prism.half_width_bottom_m))
    return max(faces), min(faces)


def _build(name: str, attrs: VehicleAttributes) -> VehicleMesh:
    spec = _SPECS[name]
    b = _Builder()
    top = max(spec.prisms, key=lambda p: max(z for _, z in p.profile_xz))
    for prism in spec.prisms:
        material = "roof" if (prism is top or prism.role == "cabin") and attrs.roof is not None else "paint"
        _prism(b, prism, top_material=material, attrs=attrs,
               stripe_sides=prism is spec.prisms[-1 if name == "box_truck" else 0])
    hw = spec.width_m / 2
    r = spec.wheel_radius_m
    for x in spec.wheels_x:
        for sign in (1.0, -1.0):
            _wheel(b, x, sign * (hw - spec.wheel_width_m / 2 + 0.03), r, spec.wheel_width_m)
            arch_prism = next(p for p in spec.prisms if min(px for px, _ in p.profile_xz) <= x <= max(px for px, _ in p.profile_xz)
                        and min(z for _, z in p.profile_xz) < r * 2)
            _arch(b, x, r, sign * (arch_prism.half_width_bottom_m + DECAL_M / 2))
    (fx, fz0, fz1, fhw), (rx, rz0, rz1, rhw) = _front_rear(spec)
    h = min(fz1, fz0 + 0.55)
    for sign in (1.0, -1.0):  # headlights and tail lights near the corners
        _rect_x(b, "head", fx, sign * (fhw - 0.08), sign * (fhw - 0.40), h - 0.15, h - 0.03, 1.0)
        if spec.tail_lights == "tall":
            _rect_x(b, "tail", rx, sign * (rhw - 0.05), sign * (rhw - 0.22), rz0 + 0.16, rz1 - 0.03, -1.0)
        else:
            t = min(rz1, rz0 + 0.60)
            _rect_x(b, "tail", rx, sign * (rhw - 0.06), sign * (rhw - 0.30), t - 0.17, t - 0.04, -1.0)
    if spec.grille == "rim":  # tall and bright
        _rect_x(b, "rim", fx, -(fhw - 0.42), fhw - 0.42, h - 0.36, h - 0.02, 1.0)
    else:
        _rect_x(b, "dark", fx, -(fhw - 0.46), fhw - 0.46, h - 0.13, h - 0.05, 1.0)
    _rect_x(b, "plate", fx, -0.26, 0.26, fz0 + 0.05, fz0 + 0.16, 1.0)
    if spec.spare_wheel is not None:  # the plate goes under the wheel
        _rect_x(b, "plate", rx, -0.26, 0.26, rz0 + 0.02, rz0 + 0.12, -1.0)
        _spare_wheel(b, rx, *spec.spare_wheel)
    else:
        _rect_x(b, "plate", rx, -0.26, 0.26, rz0 + 0.12, rz0 + 0.23, -1.0)
    if spec.front_glass_z is not None:
        _rect_x(b, "glass", fx, -(fhw - 0.12), fhw - 0.12, *spec.front_glass_z, 1.0)
    if spec.rear_glass_z is not None:
        _rect_x(b, "glass", rx, -(rhw - 0.25), rhw - 0.25, *spec.rear_glass_z, -1.0)
    body = spec.prisms[0]
    for x0, x1 in spec.doors_x:
        y = -(body.half_width_bottom_m + DECAL_M)
        z1 = spec.prisms[0].windows_z[1] if spec.prisms[0].windows_z else 2.0
        b.add("glass", np.array([[x0, y, 0.45], [x1, y, 0.45], [x1, y, z1], [x0, y, z1]]), np.array([0.0, -1.0, 0.0]))
    roof_z = max(z for _, z in top.profile_xz)
    roof_xs = [x for x, z in top.profile_xz if z >= roof_z - 0.05]
    if spec.roof_unit is not None:
        cx, length, height = spec.roof_unit
        b.box("rim", (cx - length / 2, -0.8, roof_z - 0.01), (cx + length / 2, 0.8, roof_z + height))
    if attrs.roof is not None and top.role == "box" and top.windows_z is not None:  # a bus: a band above the windows
        z_hi = max(z for _, z in top.profile_xz)
        for sign in (1.0, -1.0):
            plane = _Side(top, sign)
            band = _clip(_inset(ccw(np.asarray(top.profile_xz, float)), 0.02), 1, top.windows_z[1] + 0.04, True)
            b.add("roof", plane.lift(_clip(band, 1, z_hi - 0.02, False), DECAL_M / 2), plane.outward())
    if attrs.rack:
        rx0, rx1 = min(roof_xs) + 0.12, max(roof_xs) - 0.12
        ry = top.half_width_top_m - 0.10
        for sign in (1.0, -1.0):
            b.box("rack", (rx0, sign * ry - 0.03, roof_z + 0.04), (rx1, sign * ry + 0.03, roof_z + 0.10))
            for x in (rx0, rx1):  # feet
                b.box("rack", (x - 0.03, sign * ry - 0.03, roof_z - 0.01), (x + 0.06, sign * ry + 0.03, roof_z + 0.04))
        for x in (rx0 + 0.25 * (rx1 - rx0), rx0 + 0.75 * (rx1 - rx0)):
            b.box("rack", (x - 0.03, -ry, roof_z + 0.10), (x + 0.03, ry, roof_z + 0.14))
        # the cargo box on the bars: what makes the rack show from the ground (a taller silhouette)
        cx, half_len = (rx0 + rx1) / 2, min(1.0, 0.36 * (rx1 - rx0))
        b.box("cargo", (cx - half_len, -(ry - 0.06), roof_z + 0.14), (cx + half_len, ry - 0.06, roof_z + 0.58))
    if name in ("suv", "pickup"):  # dark plastic cladding along the sills: the off-roader look
        lower = spec.prisms[0]
        for sign in (1.0, -1.0):
            plane = _Side(lower, sign)
            x_lo = min(x for x, _ in lower.profile_xz) + 0.2
            x_hi = max(x for x, _ in lower.profile_xz) - 0.2
            z_lo = min(z for _, z in lower.profile_xz) + 0.02
            band = np.array([[x_lo, z_lo], [x_hi, z_lo], [x_hi, z_lo + 0.16], [x_lo, z_lo + 0.16]])
            b.add("dark", plane.lift(band, DECAL_M / 2), plane.outward())
    if name == "pickup":  # the open bed seen from above: a dark floor inside the side walls
        b.add("dark", np.array([[-1.08, 0.88, 1.12 + DECAL_M], [-2.55, 0.88, 1.12 + DECAL_M],
                                [-2.55, -0.88, 1.12 + DECAL_M], [-1.08, -0.88, 1.12 + DECAL_M]]), np.array([0, 0, 1.0]))
    if name == "box_truck":  # chassis under the cargo box
        b.box("dark", (-3.5, -0.55, 0.55), (1.9, 0.55, 0.98))
    boxes = []
    for prism in spec.prisms:
        xs = [x for x, _ in prism.profile_xz]
        zs = [z for _, z in prism.profile_xz]
        w = max(prism.half_width_bottom_m, prism.half_width_top_m)
        boxes.append((((max(xs) + min(xs)) / 2, 0.0, (max(zs) + min(zs)) / 2),
                      ((max(xs) - min(xs)) / 2, w, (max(zs) - min(zs)) / 2)))
    triangles = b.result()
    height = max(float(t[:, :, 2].max()) for t in triangles.values())
    return VehicleMesh(name, spec.length_m, spec.width_m, height, triangles, tuple(boxes))


def contrast_colour(paint: str) -> str:
    """The stripe's colour on a paint: white on dark paints, black on light ones (relative
    luminance 0.5 and over: yellow, orange)."""
    rgb = colour_rgb(paint)
    return "black" if 0.2126 * rgb[0] + 0.7152 * rgb[1] + 0.0722 * rgb[2] >= 0.5 else "white"


@lru_cache(maxsize=256)
def vehicle_mesh(name: str, attributes: VehicleAttributes = VehicleAttributes()) -> VehicleMesh:
    """The mesh of a body type with the given attributes (cached; the same inputs, the same vertices)."""
    if name not in _SPECS:
        raise ValueError(f"unknown vehicle model {name!r}; known: {', '.join(RICH_BODY_TYPES)}")
    return _build(name, attributes)
