"""Textured triangle meshes (vertices, indices, normals, UVs) and the shapes the city is made of.

PyBullet maps a texture on a mesh by its UVs only (a texture on ``GEOM_BOX`` comes out one colour
a face), has no per-vertex colour and shades by the normals given, so every flat face here has
its own vertices and its face normal. UVs above 1 repeat the texture: ground-like meshes take
``world xy / tile size``, walls take bays and storeys. Pure numpy.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from agos.world.towns.look.meshes import strip_mesh


@dataclass
class TexMesh:
    vertices: np.ndarray
    """(V, 3) float64 metres."""
    indices: np.ndarray
    """(3T,) int64, counter-clockwise seen from the side the normal points to."""
    normals: np.ndarray
    """(V, 3) unit normals."""
    uvs: np.ndarray
    """(V, 2) texture coordinates (repeat above 1; v = 0 is the image's bottom row)."""

    @property
    def triangle_count(self) -> int:
        return len(self.indices) // 3


def merge(parts: list[TexMesh]) -> TexMesh:
    parts = [p for p in parts if len(p.indices)]
    if not parts:
        return TexMesh(np.zeros((0, 3)), np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros((0, 2)))
    offsets = np.cumsum([0] + [len(p.vertices) for p in parts[:-1]])
    return TexMesh(np.concatenate([p.vertices for p in parts]),
                   np.concatenate([p.indices + o for p, o in zip(parts, offsets, strict=True)]).astype(np.int64),
                   np.concatenate([p.normals for p in parts]), np.concatenate([p.uvs for p in parts]))


def chunked(mesh: TexMesh, max_vertices: int = 20_000) -> list[TexMesh]:
    """A mesh cut into meshes of at most ``max_vertices`` vertices (PyBullet refuses a shape of
    more than 131,072, and copies each one through Python lists), triangles kept in order."""
    if len(mesh.vertices) <= max_vertices:
        return [mesh] if len(mesh.indices) else []
    tris = mesh.indices.reshape(-1, 3)
    out = []
    step = max_vertices // 3
    for k in range(0, len(tris), step):
        batch = tris[k:k + step]
        used = np.unique(batch)
        local = np.searchsorted(used, batch).ravel()
        out.append(TexMesh(mesh.vertices[used], local.astype(np.int64), mesh.normals[used], mesh.uvs[used]))
    return out


def signed_area(poly: np.ndarray) -> float:
    x, y = poly[:, 0], poly[:, 1]
    return 0.5 * float(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1)))


def ccw(poly: np.ndarray) -> np.ndarray:
    return poly if signed_area(poly) >= 0 else poly[::-1]


def flat_polygon(poly: np.ndarray, z: float, tile_m: float, *, up: bool = True) -> TexMesh:
    """A convex polygon at height ``z`` as a fan, UV = xy / tile (facing up, or down)."""
    poly = ccw(np.asarray(poly, float))
    n = len(poly)
    if n < 3:
        return merge([])
    v = np.column_stack([poly, np.full(n, z)])
    i = np.arange(1, n - 1)
    tri = np.stack([np.zeros_like(i), i, i + 1], 1) if up else np.stack([np.zeros_like(i), i + 1, i], 1)
    normal = np.array([0.0, 0.0, 1.0 if up else -1.0])
    return TexMesh(v, tri.ravel().astype(np.int64), np.tile(normal, (n, 1)), poly / tile_m)


def flat_strip(edge_a: np.ndarray, edge_b: np.ndarray, z: float, tile_m: float) -> TexMesh:
    """Quads between two polylines (point i of one facing point i of the other), facing up:
    :func:`~agos.world.towns.look.meshes.strip_mesh` with normals and UV = xy / tile."""
    if len(edge_a) < 2:
        return merge([])
    v, idx = strip_mesh(edge_a, edge_b, z)
    return TexMesh(v, idx.astype(np.int64), np.tile([0.0, 0.0, 1.0], (len(v), 1)), v[:, :2] / tile_m)


def footprint(centre: tuple[float, float], size: tuple[float, float], yaw_rad: float) -> np.ndarray:
    """The 4 corners (counter-clockwise) of a rectangle turned by ``yaw_rad``."""
    hx, hy = size[0] / 2, size[1] / 2
    c, s = np.cos(yaw_rad), np.sin(yaw_rad)
    local = np.array([[-hx, -hy], [hx, -hy], [hx, hy], [-hx, hy]])
    return local @ np.array([[c, s], [-s, c]]) + np.asarray(centre, float)


def offset_line(points: np.ndarray, left_m: float | np.ndarray) -> np.ndarray:
    """A polyline shifted ``left_m`` to the left of its direction (negative: right)."""
    d = np.gradient(points, axis=0)
    d /= np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-9)
    left = np.stack([-d[:, 1], d[:, 0]], axis=1)
    return points + left * np.asarray(left_m, float).reshape(-1, 1)


def cut(points: np.ndarray, s0: float, s1: float) -> np.ndarray:
    """The part of a polyline between arc lengths s0 and s1 (clamped), endpoints interpolated."""
    seg = np.linalg.norm(np.diff(points, axis=0), axis=1)
    arc = np.concatenate([[0.0], np.cumsum(seg)])
    s0, s1 = max(0.0, s0), min(float(arc[-1]), s1)
    if s1 - s0 < 1e-3:
        return points[:0]
    s = np.concatenate([[s0], arc[(arc > s0) & (arc < s1)], [s1]])
    return np.stack([np.interp(s, arc, points[:, 0]), np.interp(s, arc, points[:, 1])], axis=1)


def arc_length(points: np.ndarray) -> float:
    return float(np.linalg.norm(np.diff(points, axis=0), axis=1).sum()) if len(points) > 1 else 0.0


def simplify_strip(edge_a: np.ndarray, edge_b: np.ndarray, *, max_len_m: float = 12.0,
                   tol_m: float = 0.04) -> tuple[np.ndarray, np.ndarray]:
    """Drop strip cross-sections where both edges run straight (within about ``tol_m``: a run of
    length L whose heading varies by dθ strays at most L·dθ/4 from its chord), keeping pieces at
    most ``max_len_m`` long (long thin triangles cost the rasterizer their bounding box)."""
    n = len(edge_a)
    if n <= 2:
        return edge_a, edge_b
    keep = [0]
    d_a, d_b = np.diff(edge_a, axis=0), np.diff(edge_b, axis=0)
    h_a = np.unwrap(np.arctan2(d_a[:, 1], d_a[:, 0])).tolist()
    h_b = np.unwrap(np.arctan2(d_b[:, 1], d_b[:, 0])).tolist()
    s_a = np.hypot(d_a[:, 0], d_a[:, 1]).tolist()
    i = 0
    while i < n - 1:
        lo_a = hi_a = h_a[i]
        lo_b = hi_b = h_b[i]
        length = s_a[i]
        j = i + 1
        while j < n - 1:
            lo_a, hi_a = min(lo_a, h_a[j]), max(hi_a, h_a[j])
            lo_b, hi_b = min(lo_b, h_b[j]), max(hi_b, h_b[j])
            new_len = length + s_a[j]
            if new_len > max_len_m or new_len * max(hi_a - lo_a, hi_b - lo_b) / 4 > tol_m:
                break
            length = new_len
            j += 1
        keep.append(j)
        i = j
    idx = np.asarray(keep)
    return edge_a[idx], edge_b[idx]


def walls_batch(p0: np.ndarray, p1: np.ndarray, z0: np.ndarray | float, z1: np.ndarray | float,
                u1: np.ndarray | float, v0: np.ndarray | float, v1: np.ndarray | float) -> TexMesh:
    """Many vertical quads from p0 to p1 (xy, (N, 2)) between heights z0 and z1, each facing right of
    p0 -> p1 (outwards for a counter-clockwise footprint), u from 0 to ``u1``, v from ``v0`` to ``v1``."""
    n = len(p0)
    if n == 0:
        return merge([])
    p0, p1 = np.asarray(p0, float), np.asarray(p1, float)
    z0, z1 = np.broadcast_to(z0, (n,)).astype(float), np.broadcast_to(z1, (n,)).astype(float)
    d = p1 - p0
    length = np.maximum(np.hypot(d[:, 0], d[:, 1]), 1e-9)
    normal = np.column_stack([d[:, 1] / length, -d[:, 0] / length, np.zeros(n)])
    verts = np.stack([np.column_stack([p0, z0]), np.column_stack([p1, z0]), np.column_stack([p1, z1]),
                      np.column_stack([p0, z1])], axis=1).reshape(-1, 3)
    u1, v0, v1 = (np.broadcast_to(np.asarray(a, float), (n,)) for a in (u1, v0, v1))
    zero = np.zeros(n)
    uvs = np.stack([np.column_stack([zero, v0]), np.column_stack([u1, v0]), np.column_stack([u1, v1]),
                    np.column_stack([zero, v1])], axis=1).reshape(-1, 2)
    idx = (np.array([0, 1, 2, 0, 2, 3])[None, :] + 4 * np.arange(n)[:, None]).ravel()
    return TexMesh(verts, idx.astype(np.int64), np.repeat(normal, 4, axis=0), uvs)


def flat_fans(polys: np.ndarray, z: np.ndarray | float, tile_m: float, *, unit_uv: bool = False) -> TexMesh:
    """Many convex polygons of one vertex count (N, K, 2), each at its height, facing up, as fans;
    UV = xy / tile (or, with ``unit_uv``, for quads, the whole texture once over each)."""
    n = len(polys)
    if n == 0:
        return merge([])
    q = np.asarray(polys, float).copy()
    k = q.shape[1]
    x, y = q[:, :, 0], q[:, :, 1]
    area = (x * np.roll(y, -1, axis=1) - y * np.roll(x, -1, axis=1)).sum(axis=1)
    q[area < 0] = q[area < 0][:, ::-1]
    zz = np.repeat(np.broadcast_to(np.asarray(z, float), (n,)), k)
    verts = np.column_stack([q.reshape(-1, 2), zz])
    i = np.arange(1, k - 1)
    fan = np.stack([np.zeros_like(i), i, i + 1], 1).ravel()
    idx = (fan[None, :] + k * np.arange(n)[:, None]).ravel()
    if unit_uv:
        assert k == 4, "unit_uv maps the texture onto quads"
        uvs = np.tile([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]], (n, 1))
    else:
        uvs = q.reshape(-1, 2) / tile_m
    return TexMesh(verts, idx.astype(np.int64), np.tile([0.0, 0.0, 1.0], (k * n, 1)), uvs)


def convex_pieces_mesh(pieces: list[np.ndarray], z: float, tile_m: float) -> TexMesh:
    """Fans of many convex polygons at one height, vectorised by vertex count (:func:`flat_fans`)."""
    by_n: dict[int, list[np.ndarray]] = {}
    for p in pieces:
        if len(p) >= 3:
            by_n.setdefault(len(p), []).append(p)
    return merge([flat_fans(np.stack(group), z, tile_m) for _, group in sorted(by_n.items())])


def footprints(centres: np.ndarray, sizes: np.ndarray, yaws: np.ndarray) -> np.ndarray:
    """(N, 4, 2) corners (counter-clockwise) of rectangles turned by their yaws."""
    centres, sizes, yaws = np.asarray(centres, float), np.asarray(sizes, float), np.asarray(yaws, float)
    signs = np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]], float)
    local = signs[None, :, :] * (sizes[:, None, :] / 2)
    c, s = np.cos(yaws)[:, None], np.sin(yaws)[:, None]
    return np.stack([local[:, :, 0] * c - local[:, :, 1] * s, local[:, :, 0] * s + local[:, :, 1] * c], axis=2) \
        + centres[:, None, :]


def boxes(centres: np.ndarray, halves: np.ndarray, yaws: np.ndarray, tile_m: float) -> TexMesh:
    """Many boxes (sides and top), UV in metres / tile."""
    centres, halves = np.asarray(centres, float).reshape(-1, 3), np.asarray(halves, float).reshape(-1, 3)
    n = len(centres)
    if n == 0:
        return merge([])
    foot = footprints(centres[:, :2], 2 * halves[:, :2], np.asarray(yaws, float))
    p0 = foot.reshape(-1, 2)
    p1 = np.roll(foot, -1, axis=1).reshape(-1, 2)
    z0 = np.repeat(centres[:, 2] - halves[:, 2], 4)
    z1 = np.repeat(centres[:, 2] + halves[:, 2], 4)
    length = np.hypot(*(p1 - p0).T)
    sides = walls_batch(p0, p1, z0, z1, length / tile_m, z0 / tile_m, z1 / tile_m)
    return merge([sides, flat_fans(foot, centres[:, 2] + halves[:, 2], tile_m)])


def triangulate(polygon: np.ndarray) -> list[tuple[int, int, int]]:
    """Ear clipping of a simple polygon (any orientation): triangles as vertex indices, each
    counter-clockwise. O(n^2), meant for outlines of a few hundred vertices."""
    poly = np.asarray(polygon, float)
    idx = list(range(len(poly)))
    if signed_area(poly) < 0:
        idx.reverse()
    out: list[tuple[int, int, int]] = []
    guard = 0
    while len(idx) > 3 and guard < 10 * len(poly) ** 2:
        guard += 1
        n = len(idx)
        for k in range(n):
            i0, i1, i2 = idx[k - 1], idx[k], idx[(k + 1) % n]
            a, b, c = poly[i0], poly[i1], poly[i2]
            if (b[0] - a[0]) * (c[1] - a[1]) - (b[1] - a[1]) * (c[0] - a[0]) <= 1e-12:
                continue  # reflex or degenerate corner
            if any(_in_triangle(poly[j], a, b, c) for j in idx if j not in (i0, i1, i2)):
                continue
            out.append((i0, i1, i2))
            del idx[k]
            break
        else:  # no ear (numerically degenerate outline): drop the flattest corner
            del idx[0]
    if len(idx) == 3:
        out.append((idx[0], idx[1], idx[2]))
    return out


def _in_triangle(p: np.ndarray, a: np.ndarray, b: np.ndarray, c: np.ndarray) -> bool:
    def side(u: np.ndarray, v: np.ndarray) -> float:
        return float((v[0] - u[0]) * (p[1] - u[1]) - (v[1] - u[1]) * (p[0] - u[0]))

    return side(a, b) >= 0 and side(b, c) >= 0 and side(c, a) >= 0


def convex_decomposition(polygon: np.ndarray) -> list[np.ndarray]:
    """A simple polygon as a few convex counter-clockwise pieces: ear clipping, then pieces merged
    across each shared edge while the union stays convex (Hertel-Mehlhorn)."""
    poly = np.asarray(polygon, float)
    pieces: dict[int, list[int]] = {k: list(t) for k, t in enumerate(triangulate(poly))}
    owner: dict[tuple[int, int], int] = {}
    for k, p in pieces.items():
        for a in range(len(p)):
            owner[(p[a], p[(a + 1) % len(p)])] = k
    for u, v in sorted(owner):
        mine = _find(pieces, owner, u, v)
        other = _find(pieces, owner, v, u)
        if mine is None or other is None or mine == other:
            continue
        joined = _join(pieces[mine], pieces[other], poly)
        if joined is None:
            continue
        pieces[mine] = joined
        del pieces[other]
        for a in range(len(joined)):
            owner[(joined[a], joined[(a + 1) % len(joined)])] = mine
        owner.pop((u, v), None)
        owner.pop((v, u), None)
    return [poly[p] for _, p in sorted(pieces.items())]


def _find(pieces: dict[int, list[int]], owner: dict[tuple[int, int], int], u: int, v: int) -> int | None:
    k = owner.get((u, v))
    return k if k is not None and k in pieces else None


def _join(p: list[int], q: list[int], poly: np.ndarray) -> list[int] | None:
    """The union of two convex pieces sharing an edge, if convex."""
    for a in range(len(p)):
        u, v = p[a], p[(a + 1) % len(p)]
        for b in range(len(q)):
            if q[b] == v and q[(b + 1) % len(q)] == u:
                # walk p from v round to u, then q from u round to v (skipping the shared edge)
                ring = [p[(a + 1 + k) % len(p)] for k in range(len(p))]
                rest = [q[(b + 2 + k) % len(q)] for k in range(len(q) - 2)]
                cand = ring + rest
                pts = poly[cand]
                e = np.roll(pts, -1, axis=0) - pts
                cross = e[:, 0] * np.roll(e, -1, axis=0)[:, 1] - e[:, 1] * np.roll(e, -1, axis=0)[:, 0]
                return cand if np.all(cross >= -1e-9) else None
    return None
