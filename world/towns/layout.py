"""A town layout: the lane network plus everything the scene draws and episodes use.

Pure data (no PyBullet). Built by a procedural generator (:mod:`agos.world.towns.procedural`) or by the
OpenDRIVE importer; the same generator and seed (or the same file) give the same layout.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from agos.world.towns.catalog import BODY_TYPES, PAINT_SHARES, paint_weights
from agos.world.towns.dressing import Dressing
from agos.world.towns.lanes import LaneNetwork
from agos.world.towns.placement import Building, ParkingSlot, Tree
from agos.world.towns.streets import Surface


@dataclass(frozen=True)
class Deck:
    """A slab over a road (an overpass or a tunnel roof): the UAV sees its top, not the road."""

    polygon_m: np.ndarray
    """(K, 2) outline built as a strip: first half one edge, second half the other edge reversed."""
    bottom_m: float
    top_m: float


@dataclass(frozen=True)
class ParkedVehicle:
    slot_id: int
    model: str
    colour: str


@dataclass
class TownLayout:
    town_id: str
    generator: str
    seed: int
    network: LaneNetwork
    surfaces: list[Surface] = field(default_factory=list)
    buildings: list[Building] = field(default_factory=list)
    trees: list[Tree] = field(default_factory=list)
    decks: list[Deck] = field(default_factory=list)
    slots: list[ParkingSlot] = field(default_factory=list)
    parked: list[ParkedVehicle] = field(default_factory=list)
    dressing: Dressing | None = None
    """The rich look's frozen choices (façades, lamps, street trees, sun); None for a hand-made layout."""

    @property
    def occupied_slots(self) -> set[int]:
        return {p.slot_id for p in self.parked}

    def bounds_world_m(self, pad_m: float = 10.0) -> tuple[float, float, float, float]:
        x0, y0, x1, y1 = self.network.bounds_m()
        return (x0 - pad_m, y0 - pad_m, x1 + pad_m, y1 + pad_m)


def park_background(slots: list[ParkingSlot], fraction: float, rng: np.random.Generator) -> list[ParkedVehicle]:
    """Background traffic in a fraction of the slots, painted with the survey's shares (see
    catalog): a target's paint or body type recurs in its region as often as chance gives."""
    models = sorted(m for m in BODY_TYPES if m != "box_truck")
    weights = [0.9 / len(models)] * len(models) + [0.1]
    paints = tuple(PAINT_SHARES)
    paint_p = paint_weights(paints)
    parked = []
    for slot in slots:
        if rng.random() < fraction:
            model = str(rng.choice([*models, "box_truck"], p=weights))
            parked.append(ParkedVehicle(slot.slot_id, model, str(rng.choice(paints, p=paint_p))))
    return parked
