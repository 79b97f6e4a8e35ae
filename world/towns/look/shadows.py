"""Shadows drawn as geometry: outlines projected along the sun onto the ground and clipped to the
surfaces they fall on.

TinyRenderer's own shadow option costs 78% of a render and shows nothing at city scale, so the
rich look draws them: every caster (a building's box, a tree's crown and trunk, a vehicle's mesh)
is projected along the sun direction onto z = 0, its convex hull is the shadow, and the hull is
clipped against each convex piece of each surface layer (asphalt, paving, grass, markings), to be
drawn a few millimetres above that piece with the piece's own texture darkened. The scene darkens
vehicles that stand in a building's shadow by the same factor. Pure numpy / Python.
"""

from __future__ import annotations

import math
from collections.abc import Iterable

import cv2
import numpy as np

from agos.world.towns.look.texmesh import ccw, footprint, signed_area
from agos.world.towns.placement import Building, Tree

SHADOW_LIFT_M = 0.006
"""How far above its surface a shadow is drawn."""
GRID_M = 24.0


def project(points_world_m: np.ndarray, sun: np.ndarray) -> np.ndarray:
    """(N, 3) points moved along the sun direction down to z = 0, as (N, 2)."""
    p = np.asarray(points_world_m, float)
    return p[:, :2] - p[:, 2:3] * (sun[None, :2] / sun[2])


def hull(points_xy: np.ndarray) -> np.ndarray:
    """Convex hull, counter-clockwise (float64)."""
    return ccw(cv2.convexHull(np.asarray(points_xy, np.float32)).reshape(-1, 2).astype(np.float64))


def building_shadow(b: Building, sun: np.ndarray) -> np.ndarray:
    corners = footprint(b.center_world_m, b.size_m[:2], b.yaw_rad)
    top = np.column_stack([corners, np.full(4, b.size_m[2])])
    return hull(np.concatenate([corners, project(top, sun)]))


def tree_shadows(trees: list[Tree], crown_centres: np.ndarray, sun: np.ndarray) -> list[np.ndarray]:
    """Shadows of many trees (``crown_centres`` (N, 3)): each crown's silhouette (the circle
    perpendicular to the sun, projected: an ellipse, eight points of it) and the trunk's foot."""
    if not trees:
        return []
    e1 = np.cross(sun, [0.0, 0.0, 1.0])
    e1 = e1 / max(float(np.linalg.norm(e1)), 1e-9)
    e2 = np.cross(sun, e1)
    a = np.arange(8) * math.pi / 4
    circle = np.cos(a)[:, None] * e1 + np.sin(a)[:, None] * e2  # (8, 3)
    r = np.array([t.crown_radius_m for t in trees])
    ring = crown_centres[:, None, :] + r[:, None, None] * circle[None]
    feet = np.array([[t.position_world_m[0], t.position_world_m[1], 0.0] for t in trees])[:, None, :]
    pts = np.concatenate([ring, feet], axis=1)
    flat = project(pts.reshape(-1, 3), sun).reshape(len(trees), 9, 2)
    return [hull(p) for p in flat]


def mesh_shadow(vertices_world_m: np.ndarray, sun: np.ndarray) -> np.ndarray:
    return hull(project(vertices_world_m, sun))


def clip_convex(subject: list[tuple[float, float]], clip: np.ndarray) -> list[tuple[float, float]]:
    """Sutherland-Hodgman: the part of a polygon inside a convex counter-clockwise polygon."""
    out = subject
    n = len(clip)
    for k in range(n):
        if not out:
            break
        ax, ay = float(clip[k][0]), float(clip[k][1])
        bx, by = float(clip[(k + 1) % n][0]), float(clip[(k + 1) % n][1])
        ex, ey = bx - ax, by - ay
        inp = out
        out = []
        px, py = inp[-1]
        p_in = ex * (py - ay) - ey * (px - ax) >= 0
        for qx, qy in inp:
            q_in = ex * (qy - ay) - ey * (qx - ax) >= 0
            if q_in != p_in:
                dp = ex * (py - ay) - ey * (px - ax)
                dq = ex * (qy - ay) - ey * (qx - ax)
                t = dp / (dp - dq)
                out.append((px + t * (qx - px), py + t * (qy - py)))
            if q_in:
                out.append((qx, qy))
            px, py, p_in = qx, qy, q_in
    return out


class ShadowSet:
    """Convex shadow polygons with a hash grid, for clipping against surfaces and point tests."""

    def __init__(self, polygons: Iterable[np.ndarray]) -> None:
        self.polygons = [p for p in polygons if len(p) >= 3]
        self.grid: dict[tuple[int, int], list[int]] = {}
        self.boxes = np.array([[*p.min(axis=0), *p.max(axis=0)] for p in self.polygons]).reshape(-1, 4)
        for k, (x0, y0, x1, y1) in enumerate(self.boxes):
            for i in range(math.floor(x0 / GRID_M), math.floor(x1 / GRID_M) + 1):
                for j in range(math.floor(y0 / GRID_M), math.floor(y1 / GRID_M) + 1):
                    self.grid.setdefault((i, j), []).append(k)

    def _candidates(self, x0: float, y0: float, x1: float, y1: float) -> list[int]:
        found: set[int] = set()
        for i in range(math.floor(x0 / GRID_M), math.floor(x1 / GRID_M) + 1):
            for j in range(math.floor(y0 / GRID_M), math.floor(y1 / GRID_M) + 1):
                found.update(self.grid.get((i, j), ()))
        return sorted(k for k in found if self.boxes[k, 0] <= x1 and self.boxes[k, 2] >= x0
                      and self.boxes[k, 1] <= y1 and self.boxes[k, 3] >= y0)

    def on(self, pieces: list[np.ndarray]) -> list[np.ndarray]:
        """The shadows' parts on each convex piece (one polygon per overlapping shadow and piece)."""
        out: list[np.ndarray] = []
        for piece in pieces:
            x0, y0 = piece.min(axis=0)
            x1, y1 = piece.max(axis=0)
            for k in self._candidates(float(x0), float(y0), float(x1), float(y1)):
                part = clip_convex([(float(x), float(y)) for x, y in self.polygons[k]], piece)
                if len(part) >= 3 and abs(signed_area(np.asarray(part))) > 1e-3:
                    out.append(np.asarray(part))
        return out

    def contains(self, point_xy: tuple[float, float]) -> bool:
        x, y = point_xy
        for k in self._candidates(x, y, x, y):
            poly = self.polygons[k]
            e = np.roll(poly, -1, axis=0) - poly
            r = np.asarray([x, y]) - poly
            if np.all(e[:, 0] * r[:, 1] - e[:, 1] * r[:, 0] >= 0):
                return True
        return False
