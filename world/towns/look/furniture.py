"""Trees and lamp posts of the rich look as meshes, merged by material; pure numpy.

A tree is a tapered trunk and a crown: an icosahedron whose vertices are pushed in and out by a
random amount (drawn from the dressing seed in the trees' order), squashed a little and
leaf-textured; two leaf textures alternate. A lamp post is a square pole,
an arm reaching over the road and a lamp head. Neither collides (as in the flat look).
"""

from __future__ import annotations

import math

import numpy as np

from agos.world.towns.dressing import Lamp
from agos.world.towns.look.texmesh import TexMesh, boxes, flat_polygon, footprints, merge, walls_batch
from agos.world.towns.placement import Tree

Meshes = dict[str, list[TexMesh]]
LAMP_HEIGHT_M = 7.0
ARM_M = 1.8
SIDES = 3

_PHI = (1 + 5 ** 0.5) / 2
_ICO_V = np.array([[-1, _PHI, 0], [1, _PHI, 0], [-1, -_PHI, 0], [1, -_PHI, 0], [0, -1, _PHI], [0, 1, _PHI],
                   [0, -1, -_PHI], [0, 1, -_PHI], [_PHI, 0, -1], [_PHI, 0, 1], [-_PHI, 0, -1], [-_PHI, 0, 1]], float)
_ICO_V /= np.linalg.norm(_ICO_V, axis=1, keepdims=True)
_ICO_F = np.array([[0, 11, 5], [0, 5, 1], [0, 1, 7], [0, 7, 10], [0, 10, 11], [1, 5, 9], [5, 11, 4], [11, 10, 2],
                   [10, 7, 6], [7, 1, 8], [3, 9, 4], [3, 4, 2], [3, 2, 6], [3, 6, 8], [3, 8, 9], [4, 9, 5], [2, 4, 11],
                   [6, 2, 10], [8, 6, 7], [9, 8, 1]])
_FACE_N = np.cross(_ICO_V[_ICO_F[:, 1]] - _ICO_V[_ICO_F[:, 0]], _ICO_V[_ICO_F[:, 2]] - _ICO_V[_ICO_F[:, 0]])
_ICO_F_OUT = np.where((np.sum(_FACE_N * _ICO_V[_ICO_F].mean(axis=1), axis=1) < 0)[:, None], _ICO_F[:, ::-1], _ICO_F)
"""The faces wound counter-clockwise seen from outside."""


def crown_centre(t: Tree) -> tuple[float, float, float]:
    return (t.position_world_m[0], t.position_world_m[1], t.height_m - t.crown_radius_m * 0.85)


def _crowns(trees: list[Tree], tile_m: float, seed: int) -> TexMesh:
    """Crowns as icosahedra pushed in and out per vertex, all at once: 12 shared vertices and 20
    triangles a crown, normals pointing away from the crown's centre (a soft, lumpy shading)."""
    n = len(trees)
    if n == 0:
        return merge([])
    rng = np.random.default_rng([seed & 0xFFFFFFFF, 11])
    r = np.array([t.crown_radius_m for t in trees])
    centre = np.array([crown_centre(t) for t in trees])
    radial = _ICO_V[None] * rng.uniform(0.82, 1.12, size=(n, len(_ICO_V), 1))
    pts = radial * np.stack([r, r, r * 0.88], axis=1)[:, None, :] + centre[:, None, :]  # (n, 12, 3)
    normals = pts - centre[:, None, :]
    normals /= np.maximum(np.linalg.norm(normals, axis=2, keepdims=True), 1e-12)
    verts = pts.reshape(-1, 3)
    idx = (_ICO_F_OUT.ravel()[None, :] + 12 * np.arange(n)[:, None]).ravel()
    uvs = np.column_stack([(verts[:, 0] + verts[:, 1]) / tile_m, verts[:, 2] / tile_m])
    return TexMesh(verts, idx.astype(np.int64), normals.reshape(-1, 3), uvs)


def _trunks(trees: list[Tree]) -> TexMesh:
    """Tapered three-sided trunks from the ground into the crown: 6 shared vertices, 6 triangles."""
    n = len(trees)
    if n == 0:
        return merge([])
    xy = np.array([t.position_world_m for t in trees], float)
    top = np.array([t.height_m - t.crown_radius_m * 1.2 for t in trees])
    r0 = np.array([0.16 + 0.02 * t.crown_radius_m for t in trees])
    a = np.arange(SIDES) * 2 * math.pi / SIDES
    ring = np.stack([np.cos(a), np.sin(a)], axis=1)  # (3, 2)
    bottom = np.concatenate([xy[:, None, :] + r0[:, None, None] * ring[None], np.zeros((n, SIDES, 1))], axis=2)
    upper = np.concatenate([xy[:, None, :] + 0.09 * ring[None], np.repeat(top[:, None, None], SIDES, axis=1)], axis=2)
    verts = np.concatenate([bottom, upper], axis=1).reshape(-1, 3)  # per tree: 3 bottom, 3 top
    normals = np.tile(np.column_stack([ring, np.zeros(SIDES)]), (n, 2, 1)).reshape(-1, 3)
    quads = [(k, (k + 1) % SIDES, SIDES + (k + 1) % SIDES, SIDES + k) for k in range(SIDES)]
    local = np.array([[q[0], q[1], q[2], q[0], q[2], q[3]] for q in quads]).ravel()
    idx = (local[None, :] + 2 * SIDES * np.arange(n)[:, None]).ravel()
    uvs = np.column_stack([np.tile(np.repeat([0.0, 1.0], SIDES), n), verts[:, 2] / 2.0])
    return TexMesh(verts, idx.astype(np.int64), normals, uvs)


def tree_meshes(trees: list[Tree], leaf_tile_m: float, seed: int) -> Meshes:
    """Crowns in ``leaves_a`` / ``leaves_b`` (alternating by position) and trunks in ``bark``."""
    first = [(round(t.position_world_m[0]) + round(t.position_world_m[1])) % 2 == 0 for t in trees]
    return {"leaves_a": [_crowns([t for t, f in zip(trees, first, strict=True) if f], leaf_tile_m, seed)],
            "leaves_b": [_crowns([t for t, f in zip(trees, first, strict=True) if not f], leaf_tile_m, seed + 1)],
            "bark": [_trunks(trees)]}


def lamp_meshes(lamps: list[Lamp]) -> Meshes:
    """A square pole (sides only), one box for arm and head reaching over the road, all in
    ``pole``; the lamp's glass under the head's end in ``lamp_glass``."""
    if not lamps:
        return {}
    xy = np.array([lamp.position_world_m for lamp in lamps], float)
    yaw = np.array([lamp.arm_yaw_rad for lamp in lamps], float)
    c, s = np.cos(yaw), np.sin(yaw)
    n = len(lamps)
    foot = footprints(xy, np.full((n, 2), 0.14), yaw)
    pole = walls_batch(foot.reshape(-1, 2), np.roll(foot, -1, axis=1).reshape(-1, 2), 0.0, LAMP_HEIGHT_M, 1.0, 0.0, 1.0)
    arm = np.column_stack([xy[:, 0] + c * ARM_M / 2, xy[:, 1] + s * ARM_M / 2, np.full(n, LAMP_HEIGHT_M - 0.08)])
    heads = boxes(arm, np.tile([ARM_M / 2, 0.09, 0.06], (n, 1)), yaw, 1.0)
    end = np.column_stack([xy[:, 0] + c * (ARM_M - 0.3), xy[:, 1] + s * (ARM_M - 0.3)])
    glass = [flat_polygon(p, LAMP_HEIGHT_M - 0.145, 1.0, up=False)
             for p in footprints(end, np.tile([0.5, 0.16], (n, 1)), yaw)]
    return {"pole": [pole, heads], "lamp_glass": [merge(glass)]}
