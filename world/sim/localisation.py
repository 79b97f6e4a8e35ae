"""Localisation error in the world: the degraded zone and the believed poses (runtime/sensing.py).

Contract: the world keeps the truth (where vehicles are, what cameras see, the CONFIRM checker, the
scores); a role is shown, sends and projects from its *believed* pose, the truth plus its fix at
that instant. :func:`believed_shot` moves a camera's pose by the fix (the picture stays what the
camera really saw), so E2A, which projects the UAV's annotated cell from its nadir camera's pose,
places the candidate where the UAV believes it looked.

The degraded zone (a rule of our own, docs/COMMS.md): from the receiver's antenna, 16 rays at 30
degrees of elevation, evenly spread in azimuth, reach 150 m; where at least half of them hit
something solid (the town's buildings, in practice), the sky is crowded and the role's drift and
noise grow by its profile's ``urban_factor``. A UAV above the rooftops never is; a UGV in a street
between tall blocks is.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pybullet as pb

from agos.runtime.sensing import Fix
from agos.world.sim.scene import Scene
from agos.world.sim.sensors import Shot

SKY_RAYS = 16
SKY_ELEVATION_DEG = 30.0
SKY_REACH_M = 150.0
CROWDED_SHARE = 0.5
"""The degraded zone: at least this share of the sky rays blocked."""


def sky_blocked_share(scene: Scene, antenna_world_m: tuple[float, float, float]) -> float:
    """The share of :data:`SKY_RAYS` rays from the antenna, at :data:`SKY_ELEVATION_DEG`, that hit something
    within :data:`SKY_REACH_M`."""
    el = math.radians(SKY_ELEVATION_DEG)
    start = list(antenna_world_m)
    ends = [[start[0] + SKY_REACH_M * math.cos(el) * math.cos(az), start[1] + SKY_REACH_M * math.cos(el) * math.sin(az),
             start[2] + SKY_REACH_M * math.sin(el)]
            for az in (2 * math.pi * k / SKY_RAYS for k in range(SKY_RAYS))]
    hits = pb.rayTestBatch([start] * SKY_RAYS, ends, physicsClientId=scene.client)
    return sum(hit[0] >= 0 for hit in hits) / SKY_RAYS


def in_degraded_zone(scene: Scene, antenna_world_m: tuple[float, float, float]) -> bool:
    return sky_blocked_share(scene, antenna_world_m) >= CROWDED_SHARE


def moved(world_from_camera: np.ndarray, fix: Fix, about_xy: tuple[float, float]) -> np.ndarray:
    """A 4x4 world pose as believed: turned by the fix's heading error about the vehicle (``about_xy``),
    then shifted by its position error."""
    c, s = math.cos(fix.dyaw_rad), math.sin(fix.dyaw_rad)
    ax, ay = about_xy
    believed = np.array([[c, -s, 0.0, ax + fix.dx_m - (c * ax - s * ay)],
                         [s, c, 0.0, ay + fix.dy_m - (s * ax + c * ay)],
                         [0.0, 0.0, 1.0, 0.0],
                         [0.0, 0.0, 0.0, 1.0]])
    return believed @ world_from_camera


def believed_shot(shot: Shot, fix: Fix, about_xy: tuple[float, float]) -> Shot:
    """The same picture with the camera pose the role believes it had (the shot itself with no error)."""
    if fix.dx_m == fix.dy_m == fix.dyaw_rad == 0.0:
        return shot
    return dataclasses.replace(shot, world_from_camera=moved(shot.world_from_camera, fix, about_xy))
