"""The PyBullet scene: the only module of agos that imports pybullet (STYLE.md item 5).

It builds a town's static geometry, adds and removes episode vehicles, renders camera images
(RGB, metric depth, instance ids) and answers line-of-sight ray queries. Everything else in
the world talks to it through these small named queries.

Each process opens its own DIRECT client (never share one across a fork).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from agos.world.towns.catalog import CARGO_WHITE, GLASS, TYRE, body_type, colour_rgb
from agos.world.towns.layout import TownLayout
from agos.world.towns.meshes import chunks, slab_mesh, strip_mesh, surface_mesh, vertex_normals
from agos.world.towns.vehicles import FIXED_RGB, VehicleAttributes, vehicle_mesh


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

# Semantic classes of the uint8 semantic map.
SEM_NONE, SEM_GROUND, SEM_ROAD, SEM_SIDEWALK, SEM_BUILDING, SEM_VEHICLE, SEM_MARKING, SEM_VEGETATION = range(8)
SEMANTIC_NAMES = ("none", "ground", "road", "sidewalk", "building", "vehicle", "marking", "vegetation")
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
"""``flat``: vehicles as coloured boxes (the default, unchanged); ``rich``: vehicles as meshes by body
type with glass, wheels, lights and plates (world/towns/vehicles.py)."""


@dataclass
class RenderResult:
    rgb: np.ndarray
    """(H, W, 3) uint8."""
    depth_m: np.ndarray
    """(H, W) float32 metric depth along the optical axis."""
    instance: np.ndarray
    """(H, W) int32 body ids, -1 where nothing was hit."""


class Scene:
    """A town in a private PyBullet DIRECT client."""

    def __init__(self, layout: TownLayout, *, renderer: str = "tiny", look: str = "flat") -> None:
        if look not in LOOKS:
            raise ValueError(f"unknown look {look!r}; known: {', '.join(LOOKS)}")
        self.look = look
        self.client = pb.connect(pb.DIRECT)
        self.renderer = renderer
        self._renderer_flag = pb.ER_TINY_RENDERER
        if renderer == "egl":
            # The plugin must be loaded before any body exists, or renders come back empty.
            import importlib.util

            egl = importlib.util.find_spec("eglRenderer")
            if egl is None or egl.origin is None or pb.loadPlugin(egl.origin, "_eglRendererPlugin",
                                                                  physicsClientId=self.client) < 0:
                raise RuntimeError("EGL renderer plugin could not be loaded")
            self._renderer_flag = pb.ER_BULLET_HARDWARE_OPENGL
        self._semantic: dict[int, int] = {}
        self._shape_cache: dict[tuple, int] = {}
        self._build_static(layout)

    # ----- construction -------------------------------------------------------------------
    def _visual_box(self, half_extents: tuple[float, float, float], rgb: tuple[float, float, float]) -> int:
        key = ("v", *(round(h, 4) for h in half_extents), *(round(c, 4) for c in rgb))
        if key not in self._shape_cache:
            self._shape_cache[key] = pb.createVisualShape(
                pb.GEOM_BOX, halfExtents=list(half_extents), rgbaColor=[*rgb, 1.0],
                specularColor=[0.05, 0.05, 0.05], physicsClientId=self.client)
        return self._shape_cache[key]

    def _collision_box(self, half_extents: tuple[float, float, float],
                       centre: tuple[float, float, float] | None = None) -> int:
        if centre is None:  # the flat look's boxes, centred on their link
            key: tuple = ("c", *(round(h, 4) for h in half_extents))
            if key not in self._shape_cache:
                self._shape_cache[key] = pb.createCollisionShape(
                    pb.GEOM_BOX, halfExtents=list(half_extents), physicsClientId=self.client)
            return self._shape_cache[key]
        key = ("c", *(round(h, 4) for h in half_extents), "at", *(round(c, 4) for c in centre))
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

    def _mesh_body(self, parts: list, rgb: tuple[float, float, float], semantic: int) -> None:
        for vertices, indices in chunks(parts):
            shape = pb.createVisualShape(pb.GEOM_MESH, vertices=vertices.tolist(), indices=indices.tolist(),
                                         normals=vertex_normals(vertices, indices).tolist(), rgbaColor=[*rgb, 1.0],
                                         specularColor=[0.02, 0.02, 0.02], physicsClientId=self.client)
            uid = pb.createMultiBody(baseMass=0, baseVisualShapeIndex=shape, physicsClientId=self.client)
            self._semantic[uid] = semantic

    def _build_static(self, layout: TownLayout) -> None:
        x0, y0, x1, y1 = layout.bounds_world_m(pad_m=0.0)
        pad = 200.0
        self._static_box(((x0 + x1) / 2, (y0 + y1) / 2, -0.05),
                         ((x1 - x0) / 2 + pad, (y1 - y0) / 2 + pad, 0.05), (0.55, 0.53, 0.48), SEM_GROUND)
        by_kind: dict[str, list] = {}
        for surface in layout.surfaces:
            by_kind.setdefault(surface.kind, []).append(surface_mesh(surface, SURFACE_Z[surface.kind]))
        if "road" not in by_kind:  # imported maps: the lanes are the road surface
            by_kind["road"] = []
            for lane in layout.network.lanes.values():
                left, right = lane.boundary()
                by_kind["road"].append(strip_mesh(left[::2] if len(left) > 4 else left,
                                                  right[::2] if len(right) > 4 else right, SURFACE_Z["road"]))
        for kind, parts in by_kind.items():
            self._mesh_body(parts, SURFACE_RGB[kind], SURFACE_SEMANTIC[kind])
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
            return self._add_mesh_vehicle(model, colour, position_world_m, yaw_rad, attributes or VehicleAttributes())
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
        for material in sorted(mesh.triangles):
            rgb = colours[material]
            key = ("mesh", model, attributes, material, *(round(c, 4) for c in rgb))
            if key not in self._shape_cache:
                vertices, indices, normals = mesh.arrays(material)
                specular = 0.35 if material == "glass" else 0.05
                self._shape_cache[key] = pb.createVisualShape(
                    pb.GEOM_MESH, vertices=vertices.tolist(), indices=indices.tolist(), normals=normals.tolist(),
                    rgbaColor=[*rgb, 1.0], specularColor=[specular] * 3, physicsClientId=self.client)
            visuals.append(self._shape_cache[key])
        # Every link carries a material's mesh, the first ones also a collision box (a link with a
        # collision box and no visual shape would be drawn as that box).
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
        return uid

    def remove(self, uid: int) -> None:
        pb.removeBody(uid, physicsClientId=self.client)
        self._semantic.pop(uid, None)

    def move(self, uid: int, offset_world_m: np.ndarray) -> None:
        """Translate a body by an offset (used to carry a vehicle to the studio and back)."""
        pos, orn = pb.getBasePositionAndOrientation(uid, physicsClientId=self.client)
        pb.resetBasePositionAndOrientation(uid, (np.asarray(pos) + offset_world_m).tolist(), orn,
                                           physicsClientId=self.client)

    # ----- queries --------------------------------------------------------------------------
    def render(self, eye_world_m: np.ndarray, forward: np.ndarray, up: np.ndarray, *, fov_deg: float,
               width_px: int, height_px: int, near_m: float = 0.3, far_m: float = 400.0) -> RenderResult:
        view = pb.computeViewMatrix(eye_world_m.tolist(), (eye_world_m + forward).tolist(), up.tolist())
        proj = pb.computeProjectionMatrixFOV(fov_deg, width_px / height_px, near_m, far_m)
        _, _, rgba, depth, seg = pb.getCameraImage(
            width_px, height_px, view, proj, renderer=self._renderer_flag, shadow=0,
            lightDirection=[0.35, 0.25, 1.0], lightAmbientCoeff=0.55, lightDiffuseCoeff=0.45,
            lightSpecularCoeff=0.05, physicsClientId=self.client)
        rgb = np.asarray(rgba, dtype=np.uint8).reshape(height_px, width_px, 4)[:, :, :3].copy()
        instance = np.asarray(seg, dtype=np.int64).reshape(height_px, width_px)
        instance = np.where(instance < 0, -1, instance & ((1 << 24) - 1)).astype(np.int32)
        rgb[instance < 0] = SKY_RGB
        zbuf = np.asarray(depth, dtype=np.float32).reshape(height_px, width_px)
        depth_m = far_m * near_m / (far_m - (far_m - near_m) * zbuf)
        return RenderResult(rgb, depth_m.astype(np.float32), instance)

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
        if self.client >= 0:
            pb.disconnect(physicsClientId=self.client)
            self.client = -1
