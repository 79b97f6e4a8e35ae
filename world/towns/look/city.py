"""The rich look's static city, assembled from a town layout: what the scene turns into bodies.

:func:`build_city` gathers the street level (:mod:`~agos.world.towns.look.streetdressing`), the buildings
and the skyline (:mod:`~agos.world.towns.look.facades`), trees and lamp posts
(:mod:`~agos.world.towns.look.furniture`) and the cast shadows (:mod:`~agos.world.towns.look.shadows`) into
one :class:`CityPart` per material and semantic class, each a single merged mesh, so the number of
bodies stays small whatever the size of the town (render cost grows with it). Textures are
written once to ``texture_root`` (:func:`~agos.world.towns.look.textures.texture_file`).

Everything random comes from the layout's :class:`~agos.world.towns.dressing.Dressing` (stored in
the frozen asset) or is derived from it: two towns with the same asset hash build the same city.
"""

from __future__ import annotations

import hashlib
import io
import json
import pickle
import zipfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from agos.world.towns.buildcache import entry_path, read_entry, write_entry
from agos.world.towns.dressing import Dressing
from agos.world.towns.layout import TownLayout
from agos.world.towns.look.decorate import dress
from agos.world.towns.look.facades import ground_extent, skyline, skyline_meshes, town_buildings
from agos.world.towns.look.furniture import crown_centre, lamp_meshes, tree_meshes
from agos.world.towns.look.shadows import SHADOW_LIFT_M, ShadowSet, building_shadow, mesh_shadow, project, tree_shadows
from agos.world.towns.look.streetdressing import Layer, Z, street_level
from agos.world.towns.look.texmesh import TexMesh, convex_pieces_mesh, flat_polygon, merge
from agos.world.towns.look.textures import FACADES, GROUND_FLOORS, TILE_M, texture_file
from agos.world.towns.look.vehicles import VehicleMesh

SHADE_RGB = (0.52, 0.55, 0.64)
"""A surface in shadow: its texture times this (lit by the blue sky only)."""
VEHICLE_SHADE = 0.62
"""A vehicle standing in a building's shadow: its colours times this."""
VEHICLE_SHADOW_Z_M = Z["asphalt"] + 0.011
VEHICLE_SHADOW_RGB = (0.13, 0.135, 0.15)
PLAIN_RGB: dict[str, tuple[float, float, float]] = {
    "marking_white": (0.90, 0.90, 0.88), "marking_yellow": (0.90, 0.70, 0.12), "bark": (0.34, 0.25, 0.17),
    "pole": (0.24, 0.25, 0.27), "lamp_glass": (0.96, 0.94, 0.82)}
"""Materials drawn in one colour, without a texture."""
TEXTURED: tuple[str, ...] = ("asphalt", "lot", "paving", "grass", "kerb", "roof_gravel", "roof_membrane", "metal",
                             "leaves_a", "leaves_b", *FACADES, *GROUND_FLOORS)


@dataclass
class CityPart:
    material: str
    mesh: TexMesh
    rgb: tuple[float, float, float]
    """Multiplies the texture (or is the colour of a plain material)."""
    semantic: str
    specular: float = 0.03
    shadow: bool = False
    """Cast shadows on a layer (its texture darkened), drawn just above it."""


@dataclass
class City:
    parts: list[CityPart]
    texture_of: dict[str, str]
    """Material -> texture name (plain materials are absent)."""
    texture_files: dict[str, Path]
    dressing: Dressing
    building_shadows: ShadowSet
    triangles: int = 0
    """Triangles of the static city as built (``parts`` may be emptied once the scene has them)."""
    vehicle_shade: float = VEHICLE_SHADE
    vehicle_shadow_rgb: tuple[float, float, float] = VEHICLE_SHADOW_RGB
    """Plain dark asphalt (a texture would be copied into each vehicle)."""

    @property
    def sun_direction(self) -> np.ndarray:
        return self.dressing.sun_direction

    def in_building_shadow(self, xy: tuple[float, float], height_m: float = 1.0) -> bool:
        """Whether the sun is hidden by a building from a point ``height_m`` above the ground."""
        ground = project(np.array([[xy[0], xy[1], height_m]]), self.sun_direction)[0]
        return self.building_shadows.contains((float(ground[0]), float(ground[1])))


def build_city(layout: TownLayout, *, texture_root: Path) -> City:
    dressing = layout.dressing if layout.dressing is not None else dress(layout)
    sun = dressing.sun_direction
    level = street_level(layout)
    sky = skyline(layout, dressing)
    extent = ground_extent(layout)
    x0, y0, x1, y1 = extent
    # the ground: one quad under everything (cutting it to the lots between roads saves pixel tests
    # in UAV views but costs more in triangles, which every render pays, on screen or not)
    ground = Layer("lot", Z["ground"], "ground", [np.array([[x0, y0], [x1, y0], [x1, y1], [x0, y1]])])
    sky_streets = Layer("asphalt", Z["asphalt"], "road", list(sky.streets))
    layers = [ground, *level.layers, sky_streets]
    parts: list[CityPart] = []
    grouped: dict[tuple[str, str], list[TexMesh]] = {}

    def add(material: str, semantic: str, meshes: list[TexMesh]) -> None:
        grouped.setdefault((material, semantic), []).extend(meshes)

    for layer in layers:
        add(layer.material, layer.semantic, [layer.mesh()])
    add("kerb", "sidewalk", [level.kerbs])
    for material, meshes in town_buildings(layout, dressing).items():
        add(material, "building", meshes)
    for material, meshes in skyline_meshes(sky).items():
        add(material, "skyline", meshes)
    trees = list(layout.trees) + list(dressing.street_trees)
    for material, meshes in tree_meshes(trees, TILE_M["leaves_a"], dressing.texture_seed).items():
        add(material, "vegetation", meshes)
    for material, meshes in lamp_meshes(list(dressing.lamps)).items():
        add(material, "furniture", meshes)
    # shadows: buildings (town and skyline) and trees, on every layer, in its texture darkened
    building_polys = [building_shadow(b, sun) for b in layout.buildings]
    street_trees = list(dressing.street_trees)
    casters = ShadowSet(building_polys  # not the skyline's: 4,000 triangles for views of the town's edge
                        + tree_shadows(street_trees, np.array([crown_centre(t) for t in street_trees]).reshape(-1, 3), sun))
    park_trees = list(layout.trees)  # inside parks (3 m from their edge): their shadows fall on the grass
    on_grass = ShadowSet(tree_shadows(park_trees, np.array([crown_centre(t) for t in park_trees]).reshape(-1, 3), sun))
    shadow_parts: list[CityPart] = []
    for layer in layers:
        own = layer.pieces
        pieces = casters.on(own) + (on_grass.on(own) if layer.material == "grass" else [])
        if pieces:
            mesh = convex_pieces_mesh(pieces, layer.z_m + SHADOW_LIFT_M, TILE_M.get(layer.material, 1.0))
            rgb = tuple(c * s for c, s in zip(PLAIN_RGB.get(layer.material, (1.0, 1.0, 1.0)), SHADE_RGB, strict=True))
            shadow_parts.append(CityPart(layer.material, mesh, rgb, layer.semantic, shadow=True))  # type: ignore[arg-type]
    for (material, semantic), meshes in sorted(grouped.items()):
        mesh = merge(meshes)
        if mesh.triangle_count:
            specular = 0.25 if material.startswith("glass") else 0.03
            parts.append(CityPart(material, mesh, PLAIN_RGB.get(material, (1.0, 1.0, 1.0)), semantic, specular))
    parts = sorted(parts + shadow_parts, key=_draw_rank)
    texture_of = {m: m for m in sorted({p.material for p in parts}) if m in TEXTURED}
    files = {name: texture_file(name, dressing.texture_seed, texture_root) for name in sorted(set(texture_of.values()))}
    return City(parts, texture_of, files, dressing, ShadowSet(building_polys),
                triangles=sum(p.mesh.triangle_count for p in parts))


def stored_city(layout: TownLayout, *, texture_root: Path, cache_root: Path) -> City:
    """:func:`build_city`'s city through the build cache (world/towns/buildcache.py), keyed by the layout's
    content: the sha256 of its pickle (the same bytes, the same layout; a layout pickled differently only
    misses). A hit gives the parts' meshes (npz), materials and colours as stored, and the textures' files,
    which must still be in ``texture_root``; anything missing or unreadable, and the city is built again."""
    key = hashlib.sha256(pickle.dumps(layout, protocol=5)).hexdigest()[:32]
    entry = entry_path(cache_root, f"city-{key}.npz")
    payload = read_entry(entry)
    city = None if payload is None else _city_from_entry(payload, layout, texture_root)
    if city is None:
        city = build_city(layout, texture_root=texture_root)
        write_entry(entry, _city_entry(city, texture_root))
    return city


def _city_entry(city: City, texture_root: Path) -> bytes:
    arrays: dict[str, Any] = {}  # np.savez's keywords (its stubs type them as its own options)
    parts = []
    for k, part in enumerate(city.parts):
        mesh = part.mesh
        arrays |= {f"v{k}": mesh.vertices, f"i{k}": mesh.indices, f"n{k}": mesh.normals, f"u{k}": mesh.uvs}
        parts.append([part.material, part.semantic, list(part.rgb), part.specular, part.shadow])
    meta = {"parts": parts, "texture_of": city.texture_of, "triangles": city.triangles,
            "texture_files": {name: str(path.relative_to(texture_root)) for name, path in city.texture_files.items()}}
    buf = io.BytesIO()
    np.savez(buf, meta=np.frombuffer(json.dumps(meta).encode(), np.uint8), **arrays)
    return buf.getvalue()


def _city_from_entry(payload: bytes, layout: TownLayout, texture_root: Path) -> City | None:
    try:
        with np.load(io.BytesIO(payload), allow_pickle=False) as stored:
            meta = json.loads(stored["meta"].tobytes())
            parts = [CityPart(material, TexMesh(stored[f"v{k}"], stored[f"i{k}"], stored[f"n{k}"], stored[f"u{k}"]),
                              (rgb[0], rgb[1], rgb[2]), semantic, specular, shadow)
                     for k, (material, semantic, rgb, specular, shadow) in enumerate(meta["parts"])]
        files = {name: texture_root / file for name, file in meta["texture_files"].items()}
    except (ValueError, KeyError, TypeError, IndexError, OSError, EOFError, zipfile.BadZipFile):
        return None
    if not all(path.is_file() for path in files.values()):
        return None
    dressing = layout.dressing if layout.dressing is not None else dress(layout)
    shadows = ShadowSet([building_shadow(b, dressing.sun_direction) for b in layout.buildings])
    return City(parts, meta["texture_of"], files, dressing, shadows, triangles=meta["triangles"])


_LAYER_RANK = {"marking_white": 2, "marking_yellow": 2, "paving": 3, "kerb": 3, "asphalt": 4, "grass": 5, "lot": 6}


def _draw_rank(part: CityPart) -> tuple[int, float, int]:
    """Draw order, front to back as the cameras see them (TinyRenderer draws bodies in creation
    order, and a pixel that fails the depth test costs a third of one that is shaded): buildings,
    trees and lamps first, then the flat layers from the top down, each layer's shadows (a few
    millimetres above it) before the layer."""
    if part.semantic == "building":
        return (0, 0.0, 0)
    if part.semantic in ("vegetation", "furniture") and part.material != "grass":
        return (1, 0.0, 0)
    if part.semantic == "skyline":
        return (1, 0.0, 1)
    top = float(part.mesh.vertices[:, 2].max()) if len(part.mesh.vertices) else 0.0
    return (_LAYER_RANK.get(part.material, 7), -top, 0 if part.shadow else 1)


def vehicle_shadow_mesh(city: City, mesh: VehicleMesh, yaw_rad: float) -> TexMesh:
    """A vehicle's shadow on the road under it, in the vehicle's frame (the sun is fixed in the
    world, so the outline depends on the vehicle's yaw, not on where it stands)."""
    c, s = np.cos(yaw_rad), np.sin(yaw_rad)
    verts = np.concatenate([t.reshape(-1, 3) for t in mesh.triangles.values()])
    world = np.column_stack([verts[:, 0] * c - verts[:, 1] * s, verts[:, 0] * s + verts[:, 1] * c, verts[:, 2]])
    outline = mesh_shadow(world, city.sun_direction)
    local = np.column_stack([outline[:, 0] * c + outline[:, 1] * s, -outline[:, 0] * s + outline[:, 1] * c])
    return flat_polygon(local, VEHICLE_SHADOW_Z_M, TILE_M["asphalt"])
