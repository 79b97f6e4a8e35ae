"""The rich look's random choices, frozen with the town: façade style and ground floor of every
building, rooftop units, lamp posts, street trees, the sun and the texture seed (data only).

:func:`agos.world.towns.look.decorate.dress` draws them from the town's seed and id (its own random
stream, so the layout's buildings, parking and traffic are exactly those of a town without
dressing) and the asset document stores the result (:mod:`agos.world.towns.asset`), so the asset
hash covers them. What the scene derives from the document alone (markings, kerbs, shadows,
the skyline beyond the town, the textures' pixels) depends on :data:`DRESSING_VERSION`, which is
stored too: change how the dressing is drawn or derived, bump it, and every asset hash changes
with the look.
"""

from __future__ import annotations

import math
import zlib
from dataclasses import dataclass

import numpy as np

from agos.world.towns.placement import Tree

DRESSING_VERSION = 2


@dataclass(frozen=True)
class Facade:
    style: str
    """Upper storeys (textures.FACADES)."""
    ground: str
    """Ground floor (textures.GROUND_FLOORS), or ``""`` for a building too low for one."""


@dataclass(frozen=True)
class RoofUnit:
    building: int
    """Index into the layout's buildings."""
    offset_m: tuple[float, float]
    """Centre in the building's frame (x along its first side)."""
    size_m: tuple[float, float, float]


@dataclass(frozen=True)
class Lamp:
    position_world_m: tuple[float, float]
    arm_yaw_rad: float
    """Direction the arm reaches out over the road."""


@dataclass(frozen=True)
class Dressing:
    version: int
    texture_seed: int
    sun_azimuth_rad: float
    """Direction of the sun, counter-clockwise from +x (east)."""
    sun_elevation_rad: float
    facades: tuple[Facade, ...]
    """One per building, in the layout's order."""
    roof_units: tuple[RoofUnit, ...]
    lamps: tuple[Lamp, ...]
    street_trees: tuple[Tree, ...]

    @property
    def sun_direction(self) -> np.ndarray:
        """Unit vector from the ground towards the sun."""
        ce = math.cos(self.sun_elevation_rad)
        return np.array([ce * math.cos(self.sun_azimuth_rad), ce * math.sin(self.sun_azimuth_rad),
                         math.sin(self.sun_elevation_rad)])


def dressing_seed(seed: int, town_id: str) -> int:
    """A town's texture and dressing seed: its seed and id (imported towns all have seed 0)."""
    return (seed * 1_000_003 + zlib.crc32(town_id.encode())) & 0x7FFFFFFF
