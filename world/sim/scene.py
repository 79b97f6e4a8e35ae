"""The PyBullet scene: the only module of agos that imports pybullet (STYLE.md item 5).

It builds a town's static geometry, adds and removes episode vehicles, renders camera images
(RGB, metric depth, instance ids) and answers line-of-sight ray queries. Everything else in
the world talks to it through these small named queries.

Each process opens its own DIRECT client (never share one across a fork).
"""

from __future__ import annotations

import hashlib
import io
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from agos.runtime.settings import DEFAULTS
from agos.world.towns.catalog import CARGO_WHITE, GLASS, TYRE, body_type, colour_rgb
from agos.world.towns.layout import TownLayout
from agos.world.towns.look.city import City, stored_city, vehicle_shadow_mesh
from agos.world.towns.look.meshes import chunks, slab_mesh, strip_mesh, surface_mesh, vertex_normals
from agos.world.towns.look.texmesh import TexMesh, chunked
from agos.world.towns.look.vehicles import FIXED_RGB, VehicleAttributes, vehicle_mesh


def _import_pybullet_quietly():
    """pybullet prints a build banner from C on import; keep it out of user-facing output."""
    import os
    import sys

    sys.stdout.flush()
    sys.stderr.flush()
    saved = [os.dup(1), os.dup(2)]
    devnull = os.open(os.devnull, os.O_WRONLY)
    try:
        os.dup2(devnull, 1)
        os.dup2(devnull, 2)
        import pybullet

        return pybullet
    finally:
        os.dup2(saved[0], 1)
        os.dup2(saved[1], 2)
        for fd in (*saved, devnull):
            os.close(fd)


pb = _import_pybullet_quietly()


def obj_text(vertices: np.ndarray, indices: np.ndarray, normals: np.ndarray | None = None,
             uvs: np.ndarray | None = None) -> bytes:
    """A triangle mesh as Wavefront OBJ text: ``v`` lines, ``vt`` and ``vn`` lines where given (one per
    vertex, so each face corner names the same index for all three), ``f`` lines (1-based)."""
    buf = io.BytesIO()
    np.savetxt(buf, np.asarray(vertices, np.float64).reshape(-1, 3), fmt="v %.9g %.9g %.9g")
    if uvs is not None:
        np.savetxt(buf, np.asarray(uvs, np.float64).reshape(-1, 2), fmt="vt %.9g %.9g")
    if normals is not None:
        np.savetxt(buf, np.asarray(normals, np.float64).reshape(-1, 3), fmt="vn %.7g %.7g %.7g")
    corner = {(False, False): "%d", (True, False): "%d/%d", (False, True): "%d//%d",
              (True, True): "%d/%d/%d"}[(uvs is not None, normals is not None)]
    tris = np.asarray(indices, np.int64).reshape(-1, 3) + 1
    np.savetxt(buf, np.repeat(tris, corner.count("%"), axis=1), fmt=" ".join(["f", corner, corner, corner]))
    return buf.getvalue()


def box_mesh(half: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A box centred on the origin as a triangle mesh: four vertices a face, its outward normal on
    each, counter-clockwise seen from outside."""
    vertices: list[np.ndarray] = []
    normals: list[np.ndarray] = []
    indices: list[int] = []
    for axis in range(3):
        u, v = (axis + 1) % 3, (axis + 2) % 3
        for sign in (1.0, -1.0):
            corners = []
            for a, b in ((-1, -1), (1, -1), (1, 1), (-1, 1)):
                p = np.zeros(3)
                p[axis], p[u], p[v] = sign * half[axis], a * half[u], sign * b * half[v]
                corners.append(p)
            k = len(vertices)
            vertices += corners
            normals += [np.eye(3)[axis] * sign] * 4
            indices += [k, k + 1, k + 2, k, k + 2, k + 3]
    return np.array(vertices), np.array(indices), np.array(normals)


def obj_file(text: bytes, root: Path) -> Path:
    """The OBJ's path under ``root``, named by the sha256 of its text and written on first use;
    concurrent writers (world workers sharing the cache) race harmlessly (write, then rename)."""
    path = root / f"{hashlib.sha256(text).hexdigest()[:32]}.obj"
    if not path.exists():
        root.mkdir(parents=True, exist_ok=True)
        tmp = path.with_suffix(f".{os.getpid()}.tmp")
        tmp.write_bytes(text)
        os.replace(tmp, path)
    return path

EGL_PACKAGES = "libegl1 libegl-mesa0 libgl1-mesa-dri"
"""Debian packages that give PyBullet's EGL plugin a display: the EGL loader, Mesa's EGL and its
drivers (llvmpipe, software, where there is no GPU; a GPU's vendor brings its own EGL library)."""


def egl_problem() -> str | None:
    """Why PyBullet's EGL plugin cannot render here, or None where it can. The plugin ends the whole
    process (``exit(1)``) when EGL fails it, so this walks its steps first, through ctypes: load
    libEGL.so.1, list the EGL devices, initialise a display on one (the one ``EGL_VISIBLE_DEVICES``
    names, as the plugin does) and find an OpenGL pbuffer configuration on it."""
    import ctypes
    import importlib.util

    if importlib.util.find_spec("eglRenderer") is None:
        return "pybullet's eglRenderer plugin is not installed (a pybullet wheel without it)"
    try:
        egl = ctypes.CDLL("libEGL.so.1")
    except OSError as exc:
        return f"libEGL.so.1 cannot be loaded ({exc}); on Debian: apt-get install {EGL_PACKAGES}"
    egl.eglGetProcAddress.restype = ctypes.c_void_p
    egl.eglGetProcAddress.argtypes = [ctypes.c_char_p]
    query_address = egl.eglGetProcAddress(b"eglQueryDevicesEXT")
    display_address = egl.eglGetProcAddress(b"eglGetPlatformDisplayEXT")
    if not query_address or not display_address:
        return "libEGL.so.1 has no EGL_EXT_device_enumeration / EGL_EXT_platform_device (an EGL vendor library missing?)"
    query = ctypes.CFUNCTYPE(ctypes.c_uint, ctypes.c_int, ctypes.POINTER(ctypes.c_void_p),
                             ctypes.POINTER(ctypes.c_int))(query_address)
    get_display = ctypes.CFUNCTYPE(ctypes.c_void_p, ctypes.c_uint, ctypes.c_void_p, ctypes.c_void_p)(display_address)
    devices = (ctypes.c_void_p * 32)()
    count = ctypes.c_int(0)
    if not query(32, devices, ctypes.byref(count)) or count.value == 0:
        return f"EGL lists no device (no GPU driver and no Mesa software driver?); on Debian: apt-get install {EGL_PACKAGES}"
    chosen = range(count.value)
    visible = os.environ.get("EGL_VISIBLE_DEVICES")
    if visible is not None:
        index = int(visible) if visible.strip().lstrip("-").isdigit() else -1
        if not 0 <= index < count.value:
            return f"EGL_VISIBLE_DEVICES={visible} names no device (EGL lists {count.value})"
        chosen = range(index, index + 1)
    egl.eglInitialize.argtypes = [ctypes.c_void_p, ctypes.c_void_p, ctypes.c_void_p]
    egl.eglChooseConfig.argtypes = [ctypes.c_void_p, ctypes.POINTER(ctypes.c_int), ctypes.c_void_p, ctypes.c_int,
                                    ctypes.POINTER(ctypes.c_int)]
    egl.eglTerminate.argtypes = [ctypes.c_void_p]
    # the plugin's configuration: 8-bit RGB and depth, a pbuffer surface, desktop OpenGL
    attributes = (ctypes.c_int * 15)(0x3024, 8, 0x3023, 8, 0x3022, 8, 0x3025, 8, 0x3033, 0x0001, 0x3040, 0x0008,
                                     0x3038, 0x3038, 0x3038)
    for k in chosen:
        display = get_display(0x313F, devices[k], None)  # EGL_PLATFORM_DEVICE_EXT
        if not display or not egl.eglInitialize(display, None, None):
            continue
        configs = ctypes.c_int(0)
        found = egl.eglChooseConfig(display, attributes, None, 0, ctypes.byref(configs)) and configs.value > 0
        egl.eglTerminate(display)
        if found:
            return None
    return (f"no EGL device of {count.value} initialises with an OpenGL pbuffer configuration; "
            f"on Debian: apt-get install {EGL_PACKAGES}")


# Semantic classes of the uint8 semantic map (furniture: lamp posts of the rich look).
SEM_NONE, SEM_GROUND, SEM_ROAD, SEM_SIDEWALK, SEM_BUILDING, SEM_VEHICLE, SEM_MARKING, SEM_VEGETATION, SEM_FURNITURE = range(9)
SEMANTIC_NAMES = ("none", "ground", "road", "sidewalk", "building", "vehicle", "marking", "vegetation", "furniture")
# Heights keep coplanar surfaces apart (no z-fighting) and cameras off mesh vertices.
SURFACE_Z = {"park": 0.015, "plaza": 0.02, "road": 0.02, "junction": 0.025, "marking_white": 0.035,
             "marking_yellow": 0.035, "sidewalk": 0.12}
SURFACE_RGB = {"park": (0.30, 0.52, 0.26), "plaza": (0.62, 0.60, 0.56), "road": (0.22, 0.22, 0.23),
               "junction": (0.24, 0.24, 0.25), "marking_white": (0.85, 0.85, 0.85),
               "marking_yellow": (0.85, 0.72, 0.15), "sidewalk": (0.68, 0.68, 0.66)}
SURFACE_SEMANTIC = {"park": SEM_VEGETATION, "plaza": SEM_SIDEWALK, "road": SEM_ROAD, "junction": SEM_ROAD,
                    "marking_white": SEM_MARKING, "marking_yellow": SEM_MARKING, "sidewalk": SEM_SIDEWALK}
SKY_RGB = np.array([178, 204, 230], dtype=np.uint8)
STUDIO_OFFSET_M = np.array([10_000.0, 10_000.0, 0.0])
"""Where a vehicle is moved, alone, to render its reference views."""

_PAINTS = {"glass": GLASS, "tyre": TYRE, "cargo": CARGO_WHITE}
LOOKS: tuple[str, ...] = ("flat", "rich")
"""``flat``: boxes and flat colours (the default, unchanged); ``rich``: vehicles as meshes by body type
(world/towns/look/vehicles.py) in a textured city with drawn shadows (world/towns/look/city.py)."""
_FLAT_LIGHT = {"lightDirection": [0.35, 0.25, 1.0], "lightAmbientCoeff": 0.55, "lightDiffuseCoeff": 0.45,
               "lightSpecularCoeff": 0.05}
RICH_AMBIENT, RICH_DIFFUSE = 0.5, 0.55
_COMPOUND_MAX = 16
SKY_ZENITH_RGB, SKY_HORIZON_RGB = (118, 156, 206), (204, 218, 230)


@dataclass
class _VehicleExtras:
    """What the rich look adds to a vehicle: its drawn shadow (its last link, so it moves and goes
    with it without a body of its own) and the colours of its other links."""

    shadow_link: int
    link_rgb: list[tuple[int, tuple[float, float, float]]]
    """(link index, -1 for the base; its colour in sunlight)."""
    shaded: bool = False


_SEMANTIC_OF = {"ground": SEM_GROUND, "road": SEM_ROAD, "sidewalk": SEM_SIDEWALK, "building": SEM_BUILDING,
                "skyline": SEM_BUILDING,
                "marking": SEM_MARKING, "vegetation": SEM_VEGETATION, "furniture": SEM_FURNITURE}


@dataclass
class RenderResult:
    rgb: np.ndarray
    """(H, W, 3) uint8."""
    depth_m: np.ndarray
    """(H, W) float32 metric depth along the optical axis."""
    instance: np.ndarray
    """(H, W) int32 body ids, -1 where nothing was hit."""


class Scene:
    """A town in a private PyBullet DIRECT client; a context manager that disconnects it."""

    def __init__(self, layout: TownLayout, *, look: str, renderer: str = DEFAULTS.world.renderer) -> None:
        if look not in LOOKS:
            raise ValueError(f"unknown look {look!r}; known: {', '.join(LOOKS)}")
        self.look = look
        self.client = pb.connect(pb.DIRECT)
        self.renderer = renderer
        self._renderer_flag = pb.ER_TINY_RENDERER
        if renderer == "egl":
            # The plugin must be loaded before any body exists, or renders come back empty; it ends the
            # process when EGL fails it, so first ask EGL ourselves.
            import importlib.util

            problem = egl_problem()
            if problem is not None:
                pb.disconnect(physicsClientId=self.client)
                raise RuntimeError(f"the EGL renderer cannot run here: {problem}")
            egl = importlib.util.find_spec("eglRenderer")
            if egl is None or egl.origin is None or pb.loadPlugin(egl.origin, "_eglRendererPlugin",
                                                                  physicsClientId=self.client) < 0:
                raise RuntimeError("EGL renderer plugin could not be loaded")
            self._renderer_flag = pb.ER_BULLET_HARDWARE_OPENGL
        self._semantic: dict[int, int] = {}
        self._shape_cache: dict[tuple, int] = {}
        self._extras: dict[int, _VehicleExtras] = {}
        self._shadow_lut: np.ndarray | None = None
        self._shadow_proxy = -1
        """Instance id shown for vehicles' shadow pixels (a hidden body of class road)."""
        self._city: City | None = None
        self._textures: dict[str, int] = {}
        self._sky: dict[tuple[int, int], np.ndarray] = {}
        if look == "rich":
            self._build_rich(layout)
        else:
            self._build_static(layout)

    # ----- construction -------------------------------------------------------------------
    def _visual_box(self, half_extents: tuple[float, float, float], rgb: tuple[float, float, float]) -> int:
        key = ("v", *(round(h, 4) for h in half_extents), *(round(c, 4) for c in rgb))
        if key not in self._shape_cache and self.renderer == "egl":
            # the plugin draws a box as the convex hull of points on it, lit by normals pointing away from
            # its centre (a shaded gradient across every face), and flattens a thin wide one: a mesh
            vertices, indices, normals = box_mesh(np.asarray(half_extents, dtype=np.float64))
            self._shape_cache[key] = self._visual_mesh(vertices, indices, normals, rgbaColor=[*rgb, 1.0],
                                                       specularColor=[0.05, 0.05, 0.05])
        if key not in self._shape_cache:
            self._shape_cache[key] = pb.createVisualShape(
                pb.GEOM_BOX, halfExtents=list(half_extents), rgbaColor=[*rgb, 1.0],
                specularColor=[0.05, 0.05, 0.05], physicsClientId=self.client)
        return self._shape_cache[key]

    def _collision_box(self, half_extents: tuple[float, float, float],
                       centre: tuple[float, float, float] = (0.0, 0.0, 0.0)) -> int:
        """A box shape centred ``centre`` in its link's frame (made once per scene)."""
        key = ("c", *(round(h, 4) for h in half_extents), *(round(c, 4) for c in centre))
        if key not in self._shape_cache:
            self._shape_cache[key] = pb.createCollisionShape(
                pb.GEOM_BOX, halfExtents=list(half_extents), collisionFramePosition=list(centre),
                physicsClientId=self.client)
        return self._shape_cache[key]

    def _static_box(self, center: tuple[float, float, float], half: tuple[float, float, float],
                    rgb: tuple[float, float, float], semantic: int, *, yaw: float = 0.0,
                    solid: bool = False) -> int:
        uid = pb.createMultiBody(
            baseMass=0, baseVisualShapeIndex=self._visual_box(half, rgb),
            baseCollisionShapeIndex=self._collision_box(half) if solid else -1,
            basePosition=list(center), baseOrientation=pb.getQuaternionFromEuler([0, 0, yaw]),
            physicsClientId=self.client)
        self._semantic[uid] = semantic
        return uid

    def _visual_mesh(self, vertices: np.ndarray, indices: np.ndarray, normals: np.ndarray | None = None,
                     uvs: np.ndarray | None = None, **style: list[float]) -> int:
        """A triangle-mesh visual shape (``style``: rgbaColor, specularColor). TinyRenderer takes the
        arrays themselves. PyBullet's EGL plugin reads meshes from files only: its converter has no
        branch for a mesh given as arrays (it warns "issue extracting mesh from COLLADA/STL file", draws
        nothing, and the rich look's renders then crash), so for EGL the mesh goes through a Wavefront
        OBJ in the asset cache (``$AGOS_ASSET_CACHE/meshes/``), named by its content."""
        if self.renderer != "egl":
            arrays: dict[str, list] = {"vertices": vertices.tolist(), "indices": indices.tolist()}
            if normals is not None:
                arrays["normals"] = normals.tolist()
            if uvs is not None:
                arrays["uvs"] = uvs.tolist()
            return pb.createVisualShape(pb.GEOM_MESH, **arrays, **style, physicsClientId=self.client)
        from agos.world.towns.asset import cache_dir

        path = obj_file(obj_text(vertices, indices, normals, uvs), cache_dir() / "meshes")
        return pb.createVisualShape(pb.GEOM_MESH, fileName=str(path), meshScale=[1.0, 1.0, 1.0], **style,
                                    physicsClientId=self.client)

    def _layer_origin(self, draw_rank: int) -> np.ndarray:
        """Where a static body whose mesh is given in world coordinates has its origin. TinyRenderer:
        the world's. EGL: ``draw_rank`` metres above it. The EGL context has a 16-bit depth buffer
        (the plugin asks for ``EGL_DEPTH_SIZE`` 8 and EGL hands out the smallest that fits: 0.3 m a
        step at 80 m), so the town's stacked flat layers (markings 1.5 cm above the road, shadows
        6 mm above their surface) come out at equal depths, and the first one drawn wins
        (``GL_LESS``). The plugin draws opaque shapes in the order of their body's origin along the
        view direction, farthest first (GLInstancingRenderer::renderSceneInternal); for any camera
        looking down, a lower origin is farther, so a layer on top takes a lower rank and is drawn
        before the layers under it. For the UAV's nadir camera, vehicles (origins on the ground)
        and so their drawn shadows come before every layer as well."""
        return np.array([0.0, 0.0, float(draw_rank) if self.renderer == "egl" else 0.0])

    def _mesh_body(self, parts: list, rgb: tuple[float, float, float], semantic: int, *, draw_rank: int = 0) -> None:
        origin = self._layer_origin(draw_rank)
        for vertices, indices in chunks(parts):
            normals = vertex_normals(vertices, indices)
            if self.renderer == "egl":
                vertices = vertices - origin
            shape = self._visual_mesh(vertices, indices, normals, rgbaColor=[*rgb, 1.0],
                                      specularColor=[0.02, 0.02, 0.02])
            uid = pb.createMultiBody(baseMass=0, baseVisualShapeIndex=shape, basePosition=origin.tolist(),
                                     physicsClientId=self.client)
            self._semantic[uid] = semantic

    def _build_static(self, layout: TownLayout) -> None:
        x0, y0, x1, y1 = layout.bounds_world_m(pad_m=0.0)
        pad = 200.0
        by_kind: dict[str, list] = {}
        for surface in layout.surfaces:
            by_kind.setdefault(surface.kind, []).append(surface_mesh(surface, SURFACE_Z[surface.kind]))
        if "road" not in by_kind:  # imported maps: the lanes are the road surface
            by_kind["road"] = []
            for lane in layout.network.lanes.values():
                left, right = lane.boundary()
                by_kind["road"].append(strip_mesh(left[::2] if len(left) > 4 else left,
                                                  right[::2] if len(right) > 4 else right, SURFACE_Z["road"]))
        # draw ranks (EGL): the highest surfaces first, the ground last
        heights = sorted({SURFACE_Z[kind] for kind in by_kind}, reverse=True)
        ground_centre = ((x0 + x1) / 2, (y0 + y1) / 2, -0.05)
        ground_half = ((x1 - x0) / 2 + pad, (y1 - y0) / 2 + pad, 0.05)
        if self.renderer == "egl":  # the ground drawn last; a mesh (the plugin's hull of a box 0.1 m thick and
            # hundreds of metres wide lies 5 cm low)
            origin = self._layer_origin(len(heights) + 1)
            vertices, indices, normals = box_mesh(np.asarray(ground_half))
            shape = self._visual_mesh(vertices + np.asarray(ground_centre) - origin, indices, normals,
                                      rgbaColor=[0.55, 0.53, 0.48, 1.0], specularColor=[0.05, 0.05, 0.05])
            uid = pb.createMultiBody(baseMass=0, baseVisualShapeIndex=shape, basePosition=origin.tolist(),
                                     physicsClientId=self.client)
            self._semantic[uid] = SEM_GROUND
        else:
            self._static_box(ground_centre, ground_half, (0.55, 0.53, 0.48), SEM_GROUND)
        for kind, parts in by_kind.items():
            self._mesh_body(parts, SURFACE_RGB[kind], SURFACE_SEMANTIC[kind],
                            draw_rank=1 + heights.index(SURFACE_Z[kind]))
        if layout.decks:
            self._mesh_body([slab_mesh(d.polygon_m, d.bottom_m, d.top_m) for d in layout.decks], (0.52, 0.50, 0.47),
                            SEM_BUILDING)
        for bld in layout.buildings:
            sx, sy, sz = bld.size_m
            self._static_box((bld.center_world_m[0], bld.center_world_m[1], sz / 2),
                             (sx / 2, sy / 2, sz / 2), bld.colour, SEM_BUILDING, yaw=bld.yaw_rad, solid=True)
        self._add_trees(layout)
        slots = {s.slot_id: s for s in layout.slots}
        for car in layout.parked:
            slot = slots[car.slot_id]
            self.add_vehicle(car.model, car.colour, (*slot.position_world_m, 0.0), slot.yaw_rad)

    def _build_rich(self, layout: TownLayout) -> None:
        """The textured city (world/towns/look/city.py): one body per material and chunk, the buildings'
        collision boxes in compound bodies, then the parked traffic with shadows. The city's meshes come
        from the build cache where an earlier process built them for this layout and code."""
        from agos.world.towns.asset import cache_dir

        city = stored_city(layout, texture_root=cache_dir() / "textures", cache_root=cache_dir())
        self._city = city
        rank = 0
        while city.parts:  # PyBullet copies each mesh: let go of ours as we go (peak memory)
            part = city.parts.pop(0)
            rank += 1  # the parts come in draw order (city._draw_rank): EGL keeps it (_layer_origin)
            self._textured_body(part.mesh, part.material, part.rgb, _SEMANTIC_OF[part.semantic], specular=part.specular,
                                draw_rank=rank)
        if layout.decks:
            self._mesh_body([slab_mesh(d.polygon_m, d.bottom_m, d.top_m) for d in layout.decks], (0.56, 0.55, 0.52),
                            SEM_BUILDING)
        self._building_colliders(layout)
        self._shadow_proxy = pb.createMultiBody(baseMass=0, baseVisualShapeIndex=self._hidden_visual(),
                                                physicsClientId=self.client)
        self._semantic[self._shadow_proxy] = SEM_ROAD
        slots = {s.slot_id: s for s in layout.slots}
        for car in layout.parked:
            slot = slots[car.slot_id]
            self.add_vehicle(car.model, car.colour, (*slot.position_world_m, 0.0), slot.yaw_rad)

    def _building_colliders(self, layout: TownLayout) -> None:
        """The buildings' boxes as compound collision shapes (PyBullet keeps at most 16 children a
        compound) on bodies whose only visual is one tiny triangle far below the ground (a body
        without a visual shape is drawn as its collision shapes)."""
        boxes = [((b.center_world_m[0], b.center_world_m[1], b.size_m[2] / 2),
                  (b.size_m[0] / 2, b.size_m[1] / 2, b.size_m[2] / 2), b.yaw_rad) for b in layout.buildings]
        if not boxes:
            return
        hidden = self._hidden_visual()
        for k in range(0, len(boxes), _COMPOUND_MAX):
            group = boxes[k:k + _COMPOUND_MAX]
            collision = pb.createCollisionShapeArray(
                [pb.GEOM_BOX] * len(group), halfExtents=[list(h) for _, h, _ in group],
                collisionFramePositions=[list(c) for c, _, _ in group],
                collisionFrameOrientations=[pb.getQuaternionFromEuler([0, 0, y]) for _, _, y in group],
                physicsClientId=self.client)
            uid = pb.createMultiBody(baseMass=0, baseCollisionShapeIndex=collision, baseVisualShapeIndex=hidden,
                                     physicsClientId=self.client)
            self._semantic[uid] = SEM_BUILDING

    def _hidden_visual(self) -> int:
        key = ("hidden",)
        if key not in self._shape_cache:
            self._shape_cache[key] = self._visual_mesh(
                np.array([[0, 0, -500.0], [0.01, 0, -500.0], [0, 0.01, -500.0]]), np.array([0, 1, 2]))
        return self._shape_cache[key]

    def _texture(self, name: str) -> int:
        if name not in self._textures:
            assert self._city is not None
            self._textures[name] = pb.loadTexture(str(self._city.texture_files[name]), physicsClientId=self.client)
        return self._textures[name]

    def _textured_body(self, mesh: TexMesh, material: str, rgb: tuple[float, float, float], semantic: int, *,
                       specular: float = 0.03, draw_rank: int = 0) -> list[int]:
        """One body a chunk of the mesh, with the material's texture (if it has one) times ``rgb``.

        EGL: the plugin's changeShapeTexture hands the renderer a graphics instance id where it wants
        a shape index, so a texture reaches the right body only while every shape so far has exactly
        one instance. The city's bodies come first in a scene, each with a mesh of its own; no
        textured body may follow a shared shape (vehicles, boxes, the hidden triangle)."""
        uids = []
        assert self._city is not None
        texture = self._city.texture_of.get(material)
        origin = self._layer_origin(draw_rank)
        for part in chunked(mesh):
            vertices = part.vertices - origin if self.renderer == "egl" else part.vertices
            shape = self._visual_mesh(vertices, part.indices, part.normals, part.uvs if texture else None,
                                      rgbaColor=[*rgb, 1.0], specularColor=[specular] * 3)
            uid = pb.createMultiBody(baseMass=0, baseVisualShapeIndex=shape, basePosition=origin.tolist(),
                                     physicsClientId=self.client)
            if texture:
                pb.changeVisualShape(uid, -1, textureUniqueId=self._texture(texture), physicsClientId=self.client)
            self._semantic[uid] = semantic
            uids.append(uid)
        return uids

    def _add_trees(self, layout: TownLayout) -> None:
        # Trees in three size classes, each created in one batched call.
        classes: dict[tuple[float, float], list[tuple[float, float]]] = {}
        for tree in layout.trees:
            key = (round(tree.height_m / 2.5) * 2.5, round(tree.crown_radius_m * 2) / 2)
            classes.setdefault(key, []).append(tree.position_world_m)
        for (height, radius), positions in sorted(classes.items()):
            trunk = pb.createVisualShape(pb.GEOM_CYLINDER, radius=0.25, length=height,
                                         rgbaColor=[0.35, 0.25, 0.15, 1], physicsClientId=self.client)
            crown = pb.createVisualShape(pb.GEOM_SPHERE, radius=radius, rgbaColor=[0.18, 0.45, 0.18, 1],
                                         physicsClientId=self.client)
            for shape, z in ((trunk, height / 2), (crown, height)):
                uids = pb.createMultiBody(baseMass=0, baseVisualShapeIndex=shape,
                                          batchPositions=[[x, y, z] for x, y in positions], physicsClientId=self.client)
                for uid in (uids if isinstance(uids, list | tuple) else [uids]):
                    self._semantic[uid] = SEM_VEGETATION

    def add_vehicle(self, model: str, colour: str, position_world_m: tuple[float, float, float],
                    yaw_rad: float, *, attributes: VehicleAttributes | None = None) -> int:
        """Place a vehicle of a body type and paint; return its body id. ``attributes`` (roof,
        rack, stripe) need the rich look."""
        if self.look == "rich":
            uid = self._add_mesh_vehicle(model, colour, position_world_m, yaw_rad, attributes or VehicleAttributes())
            self._update_shade(uid)
            return uid
        if attributes is not None and attributes != VehicleAttributes():
            raise ValueError("vehicle attributes need look='rich'")
        body = body_type(model)
        paint = colour_rgb(colour)
        visuals, collisions, centres = [], [], []
        for part in body.parts:
            rgb = paint if part.paint == "body" else _PAINTS[part.paint]
            visuals.append(self._visual_box(part.half_extents_m, rgb))
            collisions.append(self._collision_box(part.half_extents_m))
            centres.append(list(part.center_m))
        n = len(body.parts) - 1
        uid = pb.createMultiBody(
            baseMass=0, baseVisualShapeIndex=visuals[0], baseCollisionShapeIndex=collisions[0],
            basePosition=[position_world_m[0], position_world_m[1], position_world_m[2] + centres[0][2]],
            baseOrientation=pb.getQuaternionFromEuler([0, 0, yaw_rad]),
            linkMasses=[0] * n, linkCollisionShapeIndices=collisions[1:], linkVisualShapeIndices=visuals[1:],
            linkPositions=[[c[0] - centres[0][0], c[1] - centres[0][1], c[2] - centres[0][2]] for c in centres[1:]],
            linkOrientations=[[0, 0, 0, 1]] * n, linkInertialFramePositions=[[0, 0, 0]] * n,
            linkInertialFrameOrientations=[[0, 0, 0, 1]] * n, linkParentIndices=[0] * n,
            linkJointTypes=[pb.JOINT_FIXED] * n, linkJointAxis=[[0, 0, 1]] * n,
            physicsClientId=self.client)
        self._semantic[uid] = SEM_VEHICLE
        return uid

    def _add_mesh_vehicle(self, model: str, colour: str, position_world_m: tuple[float, float, float],
                          yaw_rad: float, attributes: VehicleAttributes) -> int:
        """A rich-look vehicle: one link per material of its mesh (the segmentation reports the
        body id for every link) and a few collision boxes; shapes are made once per scene."""
        mesh = vehicle_mesh(model, attributes)
        paint = colour_rgb(colour)
        colours = {"paint": paint, "roof": colour_rgb(attributes.roof) if attributes.roof else paint,
                   "stripe": colour_rgb(attributes.stripe) if attributes.stripe else paint, **FIXED_RGB}
        visuals = []
        link_rgb: list[tuple[int, tuple[float, float, float]]] = []
        for k, material in enumerate(sorted(mesh.triangles)):
            rgb = colours[material]
            link_rgb.append((k - 1, rgb))
            key = ("mesh", model, attributes, material, *(round(c, 4) for c in rgb))
            if key not in self._shape_cache:
                vertices, indices, normals = mesh.arrays(material)
                specular = 0.35 if material == "glass" else 0.05
                self._shape_cache[key] = self._visual_mesh(vertices, indices, normals, rgbaColor=[*rgb, 1.0],
                                                           specularColor=[specular] * 3)
            visuals.append(self._shape_cache[key])
        if self._city is not None:  # the rich city: the vehicle's shadow as its last link, in its frame
            key = ("shadow", model, attributes, yaw_rad)  # its outline turns with the yaw (slots repeat)
            if key not in self._shape_cache:
                shadow = vehicle_shadow_mesh(self._city, mesh, yaw_rad)
                self._shape_cache[key] = self._visual_mesh(
                    shadow.vertices, shadow.indices, shadow.normals, rgbaColor=[*self._city.vehicle_shadow_rgb, 1.0],
                    specularColor=[0.0] * 3)
            visuals.append(self._shape_cache[key])
        # Every link carries a mesh, the first ones also a collision box (a link with a collision box
        # and no visual shape would be drawn as that box).
        collisions = [self._collision_box(half, centre) for centre, half in mesh.collision_boxes]
        collisions += [-1] * (len(visuals) - len(collisions))
        n = len(visuals) - 1
        uid = pb.createMultiBody(
            baseMass=0, baseVisualShapeIndex=visuals[0], baseCollisionShapeIndex=collisions[0],
            basePosition=list(position_world_m), baseOrientation=pb.getQuaternionFromEuler([0, 0, yaw_rad]),
            linkMasses=[0] * n, linkCollisionShapeIndices=collisions[1:], linkVisualShapeIndices=visuals[1:],
            linkPositions=[[0.0, 0.0, 0.0]] * n, linkOrientations=[[0, 0, 0, 1]] * n,
            linkInertialFramePositions=[[0, 0, 0]] * n, linkInertialFrameOrientations=[[0, 0, 0, 1]] * n,
            linkParentIndices=[0] * n, linkJointTypes=[pb.JOINT_FIXED] * n, linkJointAxis=[[0, 0, 1]] * n,
            physicsClientId=self.client)
        self._semantic[uid] = SEM_VEHICLE
        if self._city is not None:
            self._extras[uid] = _VehicleExtras(n - 1, link_rgb)
            self._shadow_lut = None
        return uid

    def _update_shade(self, uid: int) -> None:
        """Darken a rich-look vehicle standing in a building's shadow (and light it again out of it)."""
        extras = self._extras[uid]
        assert self._city is not None
        pos, _ = pb.getBasePositionAndOrientation(uid, physicsClientId=self.client)
        shaded = self._city.in_building_shadow((pos[0], pos[1]))
        if shaded == extras.shaded:
            return
        k = self._city.vehicle_shade if shaded else 1.0
        for link, rgb in extras.link_rgb:
            pb.changeVisualShape(uid, link, rgbaColor=[rgb[0] * k, rgb[1] * k, rgb[2] * k, 1.0],
                                 physicsClientId=self.client)
        extras.shaded = shaded

    def remove(self, uid: int) -> None:
        pb.removeBody(uid, physicsClientId=self.client)
        self._semantic.pop(uid, None)
        if self._extras.pop(uid, None) is not None:
            self._shadow_lut = None

    def move(self, uid: int, offset_world_m: np.ndarray) -> None:
        """Translate a body by an offset (used to carry a vehicle to the studio and back); a rich-look
        vehicle's shadow goes with it, and its shading follows the place it arrives at."""
        pos, orn = pb.getBasePositionAndOrientation(uid, physicsClientId=self.client)
        pb.resetBasePositionAndOrientation(uid, (np.asarray(pos) + offset_world_m).tolist(), orn,
                                           physicsClientId=self.client)
        if uid in self._extras:
            self._update_shade(uid)

    # ----- queries --------------------------------------------------------------------------
    def render(self, eye_world_m: np.ndarray, forward: np.ndarray, up: np.ndarray, *, fov_deg: float,
               width_px: int, height_px: int, near_m: float = 0.3, far_m: float = 400.0) -> RenderResult:
        view = pb.computeViewMatrix(eye_world_m.tolist(), (eye_world_m + forward).tolist(), up.tolist())
        proj = pb.computeProjectionMatrixFOV(fov_deg, width_px / height_px, near_m, far_m)
        light = _FLAT_LIGHT if self._city is None else {
            "lightDirection": self._city.sun_direction.tolist(), "lightAmbientCoeff": RICH_AMBIENT,
            "lightDiffuseCoeff": RICH_DIFFUSE, "lightSpecularCoeff": 0.05}
        flags = {} if self._city is None else {"flags": pb.ER_SEGMENTATION_MASK_OBJECT_AND_LINKINDEX}
        _, _, rgba, depth, seg = pb.getCameraImage(
            width_px, height_px, view, proj, renderer=self._renderer_flag, shadow=0, physicsClientId=self.client,
            **light, **flags)
        rgb = np.asarray(rgba, dtype=np.uint8).reshape(height_px, width_px, 4)[:, :, :3].copy()
        raw = np.asarray(seg, dtype=np.int64).reshape(height_px, width_px)
        instance = np.where(raw < 0, -1, raw & ((1 << 24) - 1)).astype(np.int32)
        if self._extras:  # a vehicle's shadow link is not the vehicle: its pixels show the shadow proxy
            lut = self._shadow_links()
            body = np.clip(instance, 0, len(lut) - 1)
            shadow = (raw >= 0) & ((raw >> 24) - 1 == lut[body])
            instance[shadow] = self._shadow_proxy
        if self._city is None:
            rgb[instance < 0] = SKY_RGB
        else:
            sky = instance < 0
            rgb[sky] = self._sky_gradient(height_px, width_px)[sky]
        zbuf = np.asarray(depth, dtype=np.float32).reshape(height_px, width_px)
        depth_m = far_m * near_m / (far_m - (far_m - near_m) * zbuf)
        return RenderResult(rgb, depth_m.astype(np.float32), instance)

    def _shadow_links(self) -> np.ndarray:
        """body id -> link index of its drawn shadow (-9 for bodies without one)."""
        if self._shadow_lut is None:
            lut = np.full(max(self._extras, default=0) + 1, -9, np.int64)
            for uid, extras in self._extras.items():
                lut[uid] = extras.shadow_link
            self._shadow_lut = lut
        return self._shadow_lut

    def _sky_gradient(self, height_px: int, width_px: int) -> np.ndarray:
        key = (height_px, width_px)
        if key not in self._sky:
            t = np.linspace(0.0, 1.0, height_px)[:, None] ** 0.7  # 0 at the top row, 1 at the bottom
            col = np.asarray(SKY_ZENITH_RGB) * (1 - t) + np.asarray(SKY_HORIZON_RGB) * t
            self._sky[key] = np.repeat(np.round(col).astype(np.uint8)[:, None, :], width_px, axis=1)
        return self._sky[key]

    def semantic(self, instance: np.ndarray) -> np.ndarray:
        """uint8 class map (SEMANTIC_NAMES) of an instance image."""
        lut = np.zeros(max(self._semantic, default=0) + 2, dtype=np.uint8)
        for uid, cls in self._semantic.items():
            lut[uid] = cls
        out = lut[np.clip(instance, 0, len(lut) - 1)]
        out[instance < 0] = SEM_NONE
        return out

    def line_of_sight(self, eye_world_m: np.ndarray, target_uid: int, targets_world_m: np.ndarray) -> bool:
        """True if at least one ray from the eye to the given points first hits ``target_uid``."""
        starts = [eye_world_m.tolist()] * len(targets_world_m)
        hits = pb.rayTestBatch(starts, targets_world_m.tolist(), physicsClientId=self.client)
        return any(hit[0] == target_uid for hit in hits)

    def clear_line(self, a_world_m: np.ndarray, b_world_m: np.ndarray) -> bool:
        """True if nothing solid lies between two points (radio line of sight)."""
        hit = pb.rayTest(a_world_m.tolist(), b_world_m.tolist(), physicsClientId=self.client)[0]
        return hit[0] < 0

    def renderer_name(self) -> str:
        return "pybullet-egl" if self.renderer == "egl" else "pybullet-tiny"

    def close(self) -> None:
        """Disconnect the PyBullet client; a second call does nothing."""
        if self.client >= 0:
            pb.disconnect(physicsClientId=self.client)
            self.client = -1

    def __enter__(self) -> Scene:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
