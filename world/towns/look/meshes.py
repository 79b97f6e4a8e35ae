"""Triangle meshes (vertices, indices) for flat surfaces and deck slabs; pure numpy.

Every triangle is wound counter-clockwise seen from where it should be lit (above for ground
surfaces and deck tops, below for deck undersides), so its normal faces the viewer.
"""

from __future__ import annotations

import cv2
import numpy as np

from agos.world.towns.streets import Surface

Mesh = tuple[np.ndarray, np.ndarray]
"""(V, 3) float vertices and (T*3,) int indices."""


def _ccw(v: np.ndarray, tri: np.ndarray, *, up: bool = True) -> np.ndarray:
    a, b, c = v[tri[:, 0], :2], v[tri[:, 1], :2], v[tri[:, 2], :2]
    cross = (b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (b[:, 1] - a[:, 1]) * (c[:, 0] - a[:, 0])
    flip = cross < 0 if up else cross > 0
    tri = tri.copy()
    tri[flip] = tri[flip][:, [0, 2, 1]]
    return tri


def strip_mesh(edge_a: np.ndarray, edge_b: np.ndarray, z: float, *, up: bool = True) -> Mesh:
    """Quads between two polylines of equal length (point i of one faces point i of the other)."""
    n = len(edge_a)
    v = np.concatenate([np.column_stack([edge_a, np.full(n, z)]), np.column_stack([edge_b, np.full(n, z)])])
    i = np.arange(n - 1)
    tri = np.concatenate([np.stack([i, i + 1, n + i + 1], 1), np.stack([i, n + i + 1, n + i], 1)])
    return v, _ccw(v, tri, up=up).ravel()


def fan_mesh(polygon: np.ndarray, z: float) -> Mesh:
    n = len(polygon)
    v = np.column_stack([polygon, np.full(n, z)])
    i = np.arange(1, n - 1)
    tri = np.stack([np.zeros_like(i), i, i + 1], 1)
    return v, _ccw(v, tri).ravel()


def region_mesh(polygon: np.ndarray, z: float, cell_m: float = 1.0) -> Mesh:
    """Any simple polygon: rasterized, rows merged into runs, runs merged into rectangles."""
    x0, y0 = polygon.min(axis=0) - cell_m
    w = int(np.ceil((polygon[:, 0].max() - x0) / cell_m)) + 2
    h = int(np.ceil((polygon[:, 1].max() - y0) / cell_m)) + 2
    mask = np.zeros((h, w), np.uint8)
    cv2.fillPoly(mask, [np.round((polygon - [x0, y0]) / cell_m).astype(np.int32)], 1)
    rects: list[list[int]] = []  # [col0, col1, row0, row1] (inclusive rows)
    open_runs: dict[tuple[int, int], list[int]] = {}
    for r in range(h):
        row = mask[r]
        edges = np.flatnonzero(np.diff(np.concatenate([[0], row, [0]])))
        runs = {(int(a), int(b)) for a, b in zip(edges[::2], edges[1::2], strict=True)}
        for key in list(open_runs):
            if key not in runs:
                rects.append(open_runs.pop(key))
        for key in runs:
            if key in open_runs:
                open_runs[key][3] = r
            else:
                open_runs[key] = [key[0], key[1], r, r]
    rects.extend(open_runs.values())
    verts, tris = [], []
    for k, (c0, c1, r0, r1) in enumerate(sorted(rects)):
        xa, xb = x0 + c0 * cell_m, x0 + c1 * cell_m
        ya, yb = y0 + r0 * cell_m, y0 + (r1 + 1) * cell_m
        verts += [(xa, ya, z), (xb, ya, z), (xb, yb, z), (xa, yb, z)]
        b = 4 * k
        tris += [(b, b + 1, b + 2), (b, b + 2, b + 3)]
    return np.asarray(verts, float).reshape(-1, 3), np.asarray(tris, int).ravel()


def surface_mesh(surface: Surface, z: float) -> Mesh:
    if surface.shape == "convex":
        return fan_mesh(surface.polygon_m, z)
    if surface.shape == "region":
        return region_mesh(surface.polygon_m, z)
    half = len(surface.polygon_m) // 2
    return strip_mesh(surface.polygon_m[:half], surface.polygon_m[half:][::-1], z)


def slab_mesh(polygon: np.ndarray, bottom_m: float, top_m: float) -> Mesh:
    """A closed deck: top face, underside, the two long sides and both end caps of a strip
    polygon (every vertical face drawn both ways, so no view finds an open side)."""
    half = len(polygon) // 2
    a, b = polygon[:half], polygon[half:][::-1]
    parts = [strip_mesh(a, b, top_m), strip_mesh(a, b, bottom_m, up=False)]
    caps = [np.stack([a[0], b[0]]), np.stack([a[-1], b[-1]])]
    for edge in (a, b, *caps):
        n = len(edge)
        v = np.concatenate([np.column_stack([edge, np.full(n, bottom_m)]), np.column_stack([edge, np.full(n, top_m)])])
        i = np.arange(n - 1)
        tri = np.concatenate([np.stack([i, i + 1, n + i + 1], 1), np.stack([i, n + i + 1, n + i], 1)])
        parts.append((v, tri.ravel()))
        parts.append((v, tri[:, ::-1].ravel()))  # both faces: seen from the road and from outside
    return merge(parts)


def merge(parts: list[Mesh]) -> Mesh:
    verts, idx, offset = [], [], 0
    for v, i in parts:
        verts.append(v)
        idx.append(i + offset)
        offset += len(v)
    return np.concatenate(verts), np.concatenate(idx)


def vertex_normals(vertices: np.ndarray, indices: np.ndarray) -> np.ndarray:
    """Unit normals per vertex, averaged over the (counter-clockwise) triangles that use it.
    PyBullet needs them: a mesh given without normals is lit by ambient light only."""
    tri = indices.reshape(-1, 3)
    a, b, c = vertices[tri[:, 0]], vertices[tri[:, 1]], vertices[tri[:, 2]]
    face = np.cross(b - a, c - a)
    normals = np.zeros_like(vertices)
    for k in range(3):
        np.add.at(normals, tri[:, k], face)
    length = np.linalg.norm(normals, axis=1, keepdims=True)
    return np.where(length > 0, normals / np.maximum(length, 1e-12), [0.0, 0.0, 1.0])


def chunks(parts: list[Mesh], max_vertices: int = 30_000) -> list[Mesh]:
    """Merge meshes into groups of at most ``max_vertices`` vertices."""
    out: list[Mesh] = []
    group: list[Mesh] = []
    count = 0
    for v, i in parts:
        if group and count + len(v) > max_vertices:
            out.append(merge(group))
            group, count = [], 0
        group.append((v, i))
        count += len(v)
    if group:
        out.append(merge(group))
    return out
