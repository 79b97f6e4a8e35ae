"""Street plans: how procedural towns describe their roads before lanes exist.

A :class:`StreetPlan` is a planar graph: junction nodes and two-way streets between them, each
street straight or bent through control points, possibly covered by a deck. :func:`plan_to_lanes`
turns it into a :class:`~agos.world.towns.lanes.LaneNetwork` (one 3.5 m lane per direction, traffic on
the right, connector lanes across junctions for every manoeuvre except U-turns, a turnaround at
dead ends) and into the :class:`Surface` strips the scene renders (asphalt with parking strips,
junction patches, sidewalks, lane markings).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from agos.world.towns.lanes import TURNAROUND, Lane, LaneNetwork

LANE_WIDTH_M = 3.5
PARKING_WIDTH_M = 2.5
SIDEWALK_WIDTH_M = 2.5
ROAD_HALF_WIDTH_M = LANE_WIDTH_M + PARKING_WIDTH_M
JUNCTION_SETBACK_M = ROAD_HALF_WIDTH_M + 2.0
"""Lanes end this far (along the street) from a junction centre; connectors cross the junction."""
SAMPLE_M = 1.0


@dataclass(frozen=True)
class Street:
    a: int
    b: int
    via: tuple[tuple[float, float], ...] = ()
    """Control points of a curved street (a quadratic or cubic Bezier between the nodes)."""
    covered: bool = False
    """Under a deck: the UGV drives it, the UAV cannot see it."""


@dataclass
class StreetPlan:
    nodes: list[tuple[float, float]]
    streets: list[Street]

    def degree(self) -> list[int]:
        deg = [0] * len(self.nodes)
        for s in self.streets:
            deg[s.a] += 1
            deg[s.b] += 1
        return deg


@dataclass(frozen=True)
class Surface:
    """A flat area to render: ``kind`` is road, junction, sidewalk, marking_yellow,
    marking_white, park or plaza."""

    kind: str
    polygon_m: np.ndarray
    """(K, 2) outline, counter-clockwise seen from above."""
    shape: str = "strip"
    """How to triangulate: ``strip`` (first half one edge, second half the other edge reversed),
    ``convex`` (a fan) or ``region`` (any simple polygon; rasterized at 1 m)."""


@dataclass
class PlanGeometry:
    network: LaneNetwork
    surfaces: list[Surface] = field(default_factory=list)
    street_lines: list[np.ndarray] = field(default_factory=list)
    """Centre polyline of each street (node a to node b), for placement and decks."""


def street_polyline(plan: StreetPlan, street: Street) -> np.ndarray:
    """The street's centre line from node a to node b, about SAMPLE_M apart."""
    p0, p1 = np.asarray(plan.nodes[street.a]), np.asarray(plan.nodes[street.b])
    ctrl = [np.asarray(v) for v in street.via]
    rough_len = float(np.linalg.norm(p1 - p0)) + sum(float(np.linalg.norm(c - p0)) for c in ctrl) * 0.2
    n = max(2, math.ceil(rough_len / (SAMPLE_M / 2)))
    t = np.linspace(0.0, 1.0, n)[:, None]
    if not ctrl:
        pts = p0 + (p1 - p0) * t
    elif len(ctrl) == 1:
        pts = (1 - t) ** 2 * p0 + 2 * (1 - t) * t * ctrl[0] + t ** 2 * p1
    else:
        c1, c2 = ctrl[0], ctrl[1]
        pts = (1 - t) ** 3 * p0 + 3 * (1 - t) ** 2 * t * c1 + 3 * (1 - t) * t ** 2 * c2 + t ** 3 * p1
    return resample(pts, SAMPLE_M)


def resample(points: np.ndarray, spacing_m: float) -> np.ndarray:
    """Points along a polyline at equal arc length, at most ``spacing_m`` apart, ends kept."""
    seg = np.linalg.norm(np.diff(points, axis=0), axis=1)
    arc = np.concatenate([[0.0], np.cumsum(seg)])
    n = max(1, math.ceil(arc[-1] / spacing_m))
    s = np.linspace(0.0, arc[-1], n + 1)
    return np.stack([np.interp(s, arc, points[:, 0]), np.interp(s, arc, points[:, 1])], axis=1)


def trim(points: np.ndarray, start_m: float, end_m: float) -> np.ndarray:
    """The part of a polyline between arc lengths ``start_m`` and ``length - end_m``."""
    seg = np.linalg.norm(np.diff(points, axis=0), axis=1)
    arc = np.concatenate([[0.0], np.cumsum(seg)])
    lo, hi = start_m, arc[-1] - end_m
    if hi - lo < 1.0:
        raise ValueError(f"street too short ({arc[-1]:.1f} m) for junction setbacks")
    s = np.concatenate([[lo], arc[(arc > lo) & (arc < hi)], [hi]])
    return np.stack([np.interp(s, arc, points[:, 0]), np.interp(s, arc, points[:, 1])], axis=1)


def offset(points: np.ndarray, right_m: float) -> np.ndarray:
    """The polyline shifted ``right_m`` to the right of its direction (negative: to the left)."""
    d = np.gradient(points, axis=0)
    d /= np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-9)
    right = np.stack([d[:, 1], -d[:, 0]], axis=1)
    return points + right * right_m


def strip(points: np.ndarray, right_from_m: float, right_to_m: float) -> np.ndarray:
    """Polygon of the band between two right-offsets of a polyline (CCW seen from above)."""
    near, far = offset(points, right_from_m), offset(points, right_to_m)
    poly = np.concatenate([far, near[::-1]]) if right_to_m > right_from_m else np.concatenate([near, far[::-1]])
    return poly if _signed_area(poly) > 0 else poly[::-1]


def _signed_area(poly: np.ndarray) -> float:
    x, y = poly[:, 0], poly[:, 1]
    return 0.5 * float(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1)))


def _bezier(p0: np.ndarray, c: np.ndarray, p2: np.ndarray) -> np.ndarray:
    t = np.linspace(0, 1, 48)[:, None]
    return resample((1 - t) ** 2 * p0 + 2 * (1 - t) * t * c + t ** 2 * p2, SAMPLE_M)


def _connector_control(p0: np.ndarray, d_in: np.ndarray, p2: np.ndarray, d_out: np.ndarray) -> np.ndarray:
    cross = d_in[0] * d_out[1] - d_in[1] * d_out[0]
    if abs(cross) < 0.05:
        if float(np.dot(d_in, d_out)) > 0:
            return (p0 + p2) / 2
        return (p0 + p2) / 2 + d_in * (np.linalg.norm(p2 - p0) * 0.9)  # turnaround bulb
    t = ((p2[0] - p0[0]) * d_out[1] - (p2[1] - p0[1]) * d_out[0]) / cross
    return p0 + d_in * t


def _lane(lane_id: str, centre: np.ndarray, *, road_id: str, in_junction: bool = False,
          parking: bool = False, covered: bool = False) -> Lane:
    centre = resample(centre, SAMPLE_M)
    return Lane(lane_id, centre, np.full(len(centre), LANE_WIDTH_M), [], in_junction, road_id,
                LANE_WIDTH_M / 2 + PARKING_WIDTH_M / 2 if parking else None, covered)


def plan_to_lanes(plan: StreetPlan) -> PlanGeometry:
    degree = plan.degree()
    lanes: dict[str, Lane] = {}
    surfaces: list[Surface] = []
    leaving: dict[int, list[tuple[str, np.ndarray, int]]] = {j: [] for j in range(len(plan.nodes))}
    arriving: dict[int, list[tuple[str, np.ndarray, int]]] = {j: [] for j in range(len(plan.nodes))}
    lines = [street_polyline(plan, street) for street in plan.streets]
    around = [_leaving(plan, j, lines) for j in range(len(plan.nodes))]  # each node's streets, by heading
    gaps = [_gaps_around(streets) for streets in around]
    for k, street in enumerate(plan.streets):
        line = lines[k]
        core = trim(line, JUNCTION_SETBACK_M, JUNCTION_SETBACK_M)
        for direction, (j_from, j_to, pts) in enumerate(((street.a, street.b, core), (street.b, street.a, core[::-1]))):
            lane = _lane(f"s{k}.{direction}", offset(pts, LANE_WIDTH_M / 2), road_id=f"s{k}", parking=True,
                         covered=street.covered)
            lanes[lane.lane_id] = lane
            d_start = lane.centre_m[1] - lane.centre_m[0]
            d_end = lane.centre_m[-1] - lane.centre_m[-2]
            leaving[j_from].append((lane.lane_id, d_start / np.linalg.norm(d_start), k))
            arriving[j_to].append((lane.lane_id, d_end / np.linalg.norm(d_end), k))
        road = trim(line, ROAD_HALF_WIDTH_M, ROAD_HALF_WIDTH_M)
        surfaces.append(Surface("road", strip(road, -ROAD_HALF_WIDTH_M, ROAD_HALF_WIDTH_M)))
        inner = trim(line, JUNCTION_SETBACK_M + 1.0, JUNCTION_SETBACK_M + 1.0)
        surfaces.append(Surface("marking_yellow", strip(inner, -0.08, 0.08)))
        for side in (-1, 1):
            surfaces.append(Surface("marking_white", strip(inner, side * LANE_WIDTH_M - 0.06, side * LANE_WIDTH_M + 0.06)))
            # the line's right side (+1) faces the street clockwise of it at node a, counter-clockwise at b
            start = _sidewalk_start_m(gaps[street.a].get((k, "cw" if side > 0 else "ccw")))
            end = _sidewalk_start_m(gaps[street.b].get((k, "ccw" if side > 0 else "cw")))
            if _length(line) - start - end >= 2.0:
                lo, hi = sorted((side * ROAD_HALF_WIDTH_M, side * (ROAD_HALF_WIDTH_M + SIDEWALK_WIDTH_M)))
                surfaces.append(Surface("sidewalk", strip(trim(line, start, end), lo, hi)))

    for j in range(len(plan.nodes)):
        for in_id, d_in, k_in in arriving[j]:
            for out_id, d_out, k_out in leaving[j]:
                if k_in == k_out and degree[j] > 1:
                    continue  # no U-turns except the turnaround at a dead end
                p0, p2 = lanes[in_id].centre_m[-1], lanes[out_id].centre_m[0]
                curve = _bezier(p0, _connector_control(p0, d_in, p2, d_out), p2)
                conn = _lane(f"j{j}.{in_id}>{out_id}", curve, road_id=TURNAROUND if k_in == k_out else f"j{j}",
                             in_junction=True)
                conn.successors.append(out_id)
                lanes[conn.lane_id] = conn
                lanes[in_id].successors.append(conn.lane_id)
        surfaces.append(Surface("junction", _junction_patch(np.asarray(plan.nodes[j]), plan, j, lines), "convex"))
        surfaces.extend(_corner_pieces(np.asarray(plan.nodes[j]), around[j]))
    network = LaneNetwork(lanes)
    network.check()
    return PlanGeometry(network, surfaces, lines)


def _junction_patch(centre: np.ndarray, plan: StreetPlan, j: int, lines: list[np.ndarray]) -> np.ndarray:
    """Convex hull of the road-edge corners where the junction's streets start."""
    import cv2

    corners = [centre]
    for k, street in enumerate(plan.streets):
        if j not in (street.a, street.b):
            continue
        line = lines[k] if street.a == j else lines[k][::-1]
        head = trim(line, 0.0, max(0.0, _length(line) - ROAD_HALF_WIDTH_M - 0.5))
        for side in (-1, 1):
            corners.extend(offset(head, side * ROAD_HALF_WIDTH_M)[[0, -1]])
    hull = cv2.convexHull(np.asarray(corners, dtype=np.float32)).reshape(-1, 2).astype(float)
    return hull if _signed_area(hull) > 0 else hull[::-1]


def _leaving(plan: StreetPlan, j: int, lines: list[np.ndarray]) -> list[tuple[float, int, np.ndarray]]:
    """(heading in rad, street index, centre line from node ``j`` outwards) of every street at ``j``,
    by heading. The heading is the chord to the point ``ROAD_HALF_WIDTH_M`` out, where kerbs meet."""
    out = []
    for k, street in enumerate(plan.streets):
        for end in ("a", "b"):  # a loop street leaves its node twice
            if getattr(street, end) != j:
                continue
            line = lines[k] if end == "a" else lines[k][::-1]
            d = _point_at_arc(line, ROAD_HALF_WIDTH_M) - line[0]
            out.append((math.atan2(d[1], d[0]), k, line))
    return sorted(out, key=lambda t: t[0])


def _gaps_around(around: list[tuple[float, int, np.ndarray]]) -> dict[tuple[int, str], float]:
    """{(street, "ccw" | "cw"): angle in rad to the next street on that side} at a node whose
    streets (:func:`_leaving`) are ``around``; no entry at a dead end."""
    gaps: dict[tuple[int, str], float] = {}
    if len(around) < 2:
        return gaps
    for i, (heading, k, _) in enumerate(around):
        gaps[(k, "ccw")] = (around[(i + 1) % len(around)][0] - heading) % (2 * math.pi)
        gaps[(k, "cw")] = (heading - around[i - 1][0]) % (2 * math.pi)
    return gaps


def _sidewalk_start_m(gap_rad: float | None) -> float:
    """How far from the junction centre a sidewalk starts, given the angle to the neighbouring
    street on its side: where its kerb meets that street's kerb (6 m at a right angle), so the two
    sidewalks meet at the corner, or at an acute corner where its outer edge does (further out: its
    end must not reach the other road; :func:`_corner_pieces` fills the tip); at the centre where
    the neighbour is straight ahead or the corner is reflex; as before at a dead end."""
    if gap_rad is None:
        return JUNCTION_SETBACK_M - 1.0
    if gap_rad >= math.pi - 1e-3:
        return 0.0
    kerbs_meet = ROAD_HALF_WIDTH_M / math.tan(gap_rad / 2)
    outer_meets_kerb = (ROAD_HALF_WIDTH_M + (ROAD_HALF_WIDTH_M + SIDEWALK_WIDTH_M) * math.cos(gap_rad)) / math.sin(gap_rad)
    return max(kerbs_meet, outer_meets_kerb)


def _corner_pieces(centre: np.ndarray, around: list[tuple[float, int, np.ndarray]]) -> list[Surface]:
    """Sidewalk where two neighbouring streets' sidewalks do not reach each other at a node
    (at ``centre``, its streets :func:`_leaving` it ``around``):
    round the outside of a reflex corner (the bend at a grid's edge, the back of a Y), from one
    sidewalk's start round the junction patch to the next one's and out to where their outer edges
    meet; and the tip of an acute corner, from the kerbs' meeting point to where the sidewalks'
    ends cross. Each is a strip whose first half runs along the road (the kerb)."""
    out: list[Surface] = []
    if len(around) < 2:
        return out
    far = ROAD_HALF_WIDTH_M + SIDEWALK_WIDTH_M
    for i, (heading, _, line_a) in enumerate(around):
        next_heading, _, line_b = around[(i + 1) % len(around)]
        gap = (next_heading - heading) % (2 * math.pi)
        # street a's left side (negative right offset) faces street b's right side
        if gap > math.pi + 1e-3:
            kerb_a, outer_a = (offset(line_a[:3], -d)[0] for d in (ROAD_HALF_WIDTH_M, far))
            kerb_b, outer_b = (offset(line_b[:3], d)[0] for d in (ROAD_HALF_WIDTH_M, far))
            corner = _meet(outer_a, line_a[0] - line_a[2], outer_b, line_b[0] - line_b[2])
            if corner is None or float(np.linalg.norm(corner - centre)) > 3 * far:
                corner = (outer_a + outer_b) / 2
            kerb = np.stack([kerb_a, (kerb_a + kerb_b) / 2, kerb_b])
            outer = np.stack([outer_a, corner, outer_b])
        elif gap < math.pi / 2 - 1e-3:
            start = _sidewalk_start_m(gap)
            tip = _kerb_point(line_a, ROAD_HALF_WIDTH_M / math.tan(gap / 2), -ROAD_HALF_WIDTH_M)
            start_a, start_b = _kerb_point(line_a, start, -ROAD_HALF_WIDTH_M), _kerb_point(line_b, start, ROAD_HALF_WIDTH_M)
            outward_a = _kerb_point(line_a, start, -far) - start_a
            outward_b = _kerb_point(line_b, start, far) - start_b
            ends_cross = _meet(start_a, outward_a, start_b, outward_b)  # where the sidewalks' ends meet
            kerb = np.stack([start_a, tip, start_b])
            outer = np.repeat(((start_a + start_b) / 2 if ends_cross is None else ends_cross)[None], 3, axis=0)
        else:
            continue
        poly = np.concatenate([kerb, outer[::-1]])
        out.append(Surface("sidewalk", poly if _signed_area(poly) > 0 else poly[::-1]))
    return out


def _kerb_point(line: np.ndarray, arc_m: float, right_m: float) -> np.ndarray:
    """The point ``right_m`` to the right of ``line`` at arc length ``arc_m`` along it."""
    d = _point_at_arc(line, arc_m + 0.5) - _point_at_arc(line, max(0.0, arc_m - 0.5))
    d /= max(float(np.linalg.norm(d)), 1e-9)
    return _point_at_arc(line, arc_m) + np.array([d[1], -d[0]]) * right_m


def _meet(p: np.ndarray, dp: np.ndarray, q: np.ndarray, dq: np.ndarray) -> np.ndarray | None:
    """Where the rays from ``p`` along ``dp`` and from ``q`` along ``dq`` cross, or None."""
    cross = dp[0] * dq[1] - dp[1] * dq[0]
    if abs(cross) < 1e-9:
        return None
    t = ((q[0] - p[0]) * dq[1] - (q[1] - p[1]) * dq[0]) / cross
    u = ((q[0] - p[0]) * dp[1] - (q[1] - p[1]) * dp[0]) / cross
    return p + dp * t if t >= 0 and u >= 0 else None


def _point_at_arc(points: np.ndarray, s_m: float) -> np.ndarray:
    seg = np.linalg.norm(np.diff(points, axis=0), axis=1)
    arc = np.concatenate([[0.0], np.cumsum(seg)])
    return np.array([np.interp(s_m, arc, points[:, 0]), np.interp(s_m, arc, points[:, 1])])


def _length(points: np.ndarray) -> float:
    return float(np.linalg.norm(np.diff(points, axis=0), axis=1).sum())
