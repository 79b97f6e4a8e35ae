"""Procedural town layouts: roads between junctions, buildings on blocks, parked traffic.

A :class:`TownLayout` is pure data (no PyBullet): the road network as junctions joined by
straight two-way segments, building boxes on the blocks, background vehicles in the parking
strips and the free parking slots episodes may use for the target and its look-alikes.
The same generator and seed give the same layout on any machine.

Road cross-section, from the centre line outwards on each side: one 3.5 m driving lane,
a 2.5 m parking strip, a 2.5 m sidewalk. Traffic drives on the right.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import networkx as nx
import numpy as np

from agos.world.catalog import BODY_TYPES, NEUTRAL_COLOURS

LANE_WIDTH_M = 3.5
PARKING_WIDTH_M = 2.5
SIDEWALK_WIDTH_M = 2.5
ROAD_HALF_WIDTH_M = LANE_WIDTH_M + PARKING_WIDTH_M
JUNCTION_SETBACK_M = ROAD_HALF_WIDTH_M + 2.0
"""Lanes end this far from a junction centre; the junction box is crossed on connector curves."""

BUILDING_PALETTE: tuple[tuple[float, float, float], ...] = (
    (0.72, 0.70, 0.66), (0.60, 0.60, 0.62), (0.78, 0.74, 0.66), (0.50, 0.50, 0.52),
    (0.66, 0.62, 0.58), (0.83, 0.82, 0.80), (0.55, 0.52, 0.50),
)


@dataclass(frozen=True)
class Building:
    center_world_m: tuple[float, float]
    size_m: tuple[float, float, float]
    colour: tuple[float, float, float]


@dataclass(frozen=True)
class ParkingSlot:
    """A spot in a parking strip: where a vehicle may stand, facing the direction of travel."""

    slot_id: int
    position_world_m: tuple[float, float]
    yaw_rad: float
    segment: int


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
    junctions: list[tuple[float, float]]
    segments: list[tuple[int, int]]
    buildings: list[Building] = field(default_factory=list)
    slots: list[ParkingSlot] = field(default_factory=list)
    parked: list[ParkedVehicle] = field(default_factory=list)

    @property
    def occupied_slots(self) -> set[int]:
        return {p.slot_id for p in self.parked}

    def bounds_world_m(self) -> tuple[float, float, float, float]:
        xy = np.asarray(self.junctions)
        pad = ROAD_HALF_WIDTH_M + SIDEWALK_WIDTH_M
        return (float(xy[:, 0].min() - pad), float(xy[:, 1].min() - pad),
                float(xy[:, 0].max() + pad), float(xy[:, 1].max() + pad))


def grid_town(seed: int, *, lines: int = 6, spacing_m: tuple[float, float] = (75.0, 100.0),
              removal_fraction: float = 0.12, parked_fraction: float = 0.22) -> TownLayout:
    """A regular-grid town: ``lines`` x ``lines`` junctions with jittered spacing, a few road
    segments removed (the network stays connected), 4-6 buildings per block."""
    rng = np.random.default_rng(seed)
    xs = np.concatenate([[0.0], np.cumsum(rng.uniform(*spacing_m, size=lines - 1))])
    ys = np.concatenate([[0.0], np.cumsum(rng.uniform(*spacing_m, size=lines - 1))])
    xs -= xs[-1] / 2
    ys -= ys[-1] / 2
    index = {(i, j): i * lines + j for i in range(lines) for j in range(lines)}
    junctions = [(float(xs[i]), float(ys[j])) for i in range(lines) for j in range(lines)]
    segments = [(index[i, j], index[i + 1, j]) for i in range(lines - 1) for j in range(lines)]
    segments += [(index[i, j], index[i, j + 1]) for i in range(lines) for j in range(lines - 1)]
    segments = _remove_segments(segments, len(junctions), removal_fraction, rng)

    layout = TownLayout(f"grid-s{seed}", "procedural-grid", seed, junctions, segments)
    layout.buildings = _grid_buildings(xs, ys, rng)
    layout.slots = _parking_slots(layout)
    layout.parked = _park_background(layout.slots, parked_fraction, rng)
    return layout


def _remove_segments(segments: list[tuple[int, int]], n_nodes: int, fraction: float,
                     rng: np.random.Generator) -> list[tuple[int, int]]:
    graph = nx.Graph()
    graph.add_nodes_from(range(n_nodes))
    graph.add_edges_from(segments)
    target = round(fraction * len(segments))
    removed = 0
    for k in rng.permutation(len(segments)):
        if removed >= target:
            break
        a, b = segments[k]
        graph.remove_edge(a, b)
        if nx.is_connected(graph) and graph.degree(a) >= 2 and graph.degree(b) >= 2:
            removed += 1
        else:
            graph.add_edge(a, b)
    return sorted((min(a, b), max(a, b)) for a, b in graph.edges())


def _grid_buildings(xs: np.ndarray, ys: np.ndarray, rng: np.random.Generator) -> list[Building]:
    margin = ROAD_HALF_WIDTH_M + SIDEWALK_WIDTH_M + 1.0
    buildings: list[Building] = []
    for i in range(len(xs) - 1):
        for j in range(len(ys) - 1):
            x0, x1 = xs[i] + margin, xs[i + 1] - margin
            y0, y1 = ys[j] + margin, ys[j + 1] - margin
            nx_lots = 2 if (x1 - x0) < 60 else 3
            xcuts = np.sort(rng.uniform(0.35, 0.65, nx_lots - 1)) if nx_lots == 2 else np.array([1 / 3, 2 / 3])
            xb = np.concatenate([[x0], x0 + xcuts * (x1 - x0), [x1]])
            yb = np.array([y0, y0 + rng.uniform(0.4, 0.6) * (y1 - y0), y1])
            for a in range(len(xb) - 1):
                for b in range(len(yb) - 1):
                    if rng.random() < 0.08:
                        continue  # an empty lot
                    inset = rng.uniform(1.0, 3.0)
                    sx, sy = xb[a + 1] - xb[a] - 2 * inset, yb[b + 1] - yb[b] - 2 * inset
                    if sx < 6 or sy < 6:
                        continue
                    height = float(rng.choice([rng.uniform(8, 18), rng.uniform(18, 42)], p=[0.6, 0.4]))
                    colour = BUILDING_PALETTE[int(rng.integers(len(BUILDING_PALETTE)))]
                    buildings.append(Building(
                        (float((xb[a] + xb[a + 1]) / 2), float((yb[b] + yb[b + 1]) / 2)),
                        (float(sx), float(sy), height), colour))
    return buildings


def _parking_slots(layout: TownLayout, pitch_m: float = 7.5) -> list[ParkingSlot]:
    slots: list[ParkingSlot] = []
    offset = LANE_WIDTH_M + PARKING_WIDTH_M / 2
    for seg_index, (a, b) in enumerate(layout.segments):
        pa, pb = np.asarray(layout.junctions[a]), np.asarray(layout.junctions[b])
        for start, end in ((pa, pb), (pb, pa)):
            direction = (end - start) / np.linalg.norm(end - start)
            right = np.array([direction[1], -direction[0]])
            length = float(np.linalg.norm(end - start))
            yaw = math.atan2(direction[1], direction[0])
            s = JUNCTION_SETBACK_M + 6.0
            while s <= length - JUNCTION_SETBACK_M - 6.0:
                p = start + direction * s + right * offset
                slots.append(ParkingSlot(len(slots), (float(p[0]), float(p[1])), yaw, seg_index))
                s += pitch_m
    return slots


def _park_background(slots: list[ParkingSlot], fraction: float,
                     rng: np.random.Generator) -> list[ParkedVehicle]:
    # Background traffic uses neutral paints only (catalog docstring), so look-alikes of a
    # vivid target appear only where an episode places them.
    models = [m for m in BODY_TYPES if m != "box_truck"]
    parked = []
    for slot in slots:
        if rng.random() < fraction:
            model = str(rng.choice(models + ["box_truck"], p=[0.9 / len(models)] * len(models) + [0.1]))
            parked.append(ParkedVehicle(slot.slot_id, model, str(rng.choice(NEUTRAL_COLOURS))))
    return parked


GENERATORS = {"procedural-grid": grid_town}


def build_layout(generator: str, seed: int) -> TownLayout:
    try:
        make = GENERATORS[generator]
    except KeyError:
        raise ValueError(f"unknown town generator {generator!r}; known: {', '.join(GENERATORS)}") from None
    return make(seed)
