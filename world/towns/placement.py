"""Off-road placement of buildings, trees, plazas and parking, from a road occupancy raster.

Works for any town (procedural or imported): the drivable surfaces and sidewalks are drawn
into a 1 m raster, widened by a margin, and buildings are packed into the free space; parks and
plazas take whole free areas instead. Parking slots follow the lanes that have a parking row.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from agos.world.towns.lanes import LaneNetwork
from agos.world.towns.streets import Surface

CELL_M = 1.0
BUILDING_PALETTE: tuple[tuple[float, float, float], ...] = (
    (0.72, 0.70, 0.66), (0.60, 0.60, 0.62), (0.78, 0.74, 0.66), (0.50, 0.50, 0.52),
    (0.66, 0.62, 0.58), (0.83, 0.82, 0.80), (0.55, 0.52, 0.50),
)


@dataclass(frozen=True)
class Building:
    center_world_m: tuple[float, float]
    size_m: tuple[float, float, float]
    colour: tuple[float, float, float]
    yaw_rad: float = 0.0


@dataclass(frozen=True)
class Tree:
    position_world_m: tuple[float, float]
    height_m: float
    crown_radius_m: float


@dataclass(frozen=True)
class ParkingSlot:
    slot_id: int
    position_world_m: tuple[float, float]
    yaw_rad: float
    lane_id: str
    covered: bool = False
    plaza: bool = False
    """On a plaza: visible from the air, not reachable by the UGV (never used for targets)."""


class Raster:
    """A boolean occupancy grid over the town in world metres."""

    def __init__(self, bounds: tuple[float, float, float, float], pad_m: float = 60.0) -> None:
        self.x0, self.y0 = bounds[0] - pad_m, bounds[1] - pad_m
        self.w = math.ceil((bounds[2] - bounds[0] + 2 * pad_m) / CELL_M)
        self.h = math.ceil((bounds[3] - bounds[1] + 2 * pad_m) / CELL_M)
        self.grid = np.zeros((self.h, self.w), np.uint8)

    def to_px(self, pts: np.ndarray) -> np.ndarray:
        return np.round((pts - [self.x0, self.y0]) / CELL_M).astype(np.int32)

    def fill(self, polygon: np.ndarray) -> None:
        cv2.fillPoly(self.grid, [self.to_px(polygon)], 1)

    def dilate(self, margin_m: float) -> np.ndarray:
        k = max(1, round(2 * margin_m / CELL_M) + 1)
        return cv2.dilate(self.grid, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (k, k)))

    def bounds_world(self) -> tuple[float, float, float, float]:
        return self.x0, self.y0, self.x0 + self.w * CELL_M, self.y0 + self.h * CELL_M


def road_raster(network: LaneNetwork, surfaces: list[Surface]) -> Raster:
    raster = Raster(network.bounds_m())
    for lane in network.lanes.values():
        left, right = lane.boundary()
        raster.fill(np.concatenate([left, right[::-1]]))
    for surface in surfaces:
        if surface.kind in ("road", "junction", "sidewalk"):
            raster.fill(surface.polygon_m)
    return raster


def free_areas(occupied: np.ndarray, raster: Raster, *, min_area_m2: float) -> list[np.ndarray]:
    """Outlines (world metres) of connected free regions at least ``min_area_m2`` big, largest
    first, skipping the region touching the raster border (outside the town)."""
    free = (occupied == 0).astype(np.uint8)
    _, labels, stats, _ = cv2.connectedComponentsWithStats(free, connectivity=4)
    out = []
    for k in np.argsort(-stats[:, cv2.CC_STAT_AREA]):
        x, y, w, h, area = stats[k]
        if k == 0 or area * CELL_M * CELL_M < min_area_m2 or x == 0 or y == 0 or x + w >= raster.w or y + h >= raster.h:
            continue
        contours, _ = cv2.findContours((labels == k).astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
        pts = contours[0].reshape(-1, 2).astype(float) * CELL_M + [raster.x0, raster.y0]
        out.append(pts)
    return out


def pack_buildings(occupied: np.ndarray, raster: Raster, rng: np.random.Generator, *,
                   pitch_m: float = 16.0) -> list[Building]:
    """Greedy packing of axis-aligned buildings into free cells on a jittered lattice."""
    taken = occupied.copy()
    buildings: list[Building] = []
    x0, y0, x1, y1 = raster.bounds_world()
    for y in np.arange(y0 + 8, y1 - 8, pitch_m):
        for x in np.arange(x0 + 8, x1 - 8, pitch_m):
            sx, sy = rng.uniform(10, 28), rng.uniform(10, 28)
            cx, cy = x + rng.uniform(-3, 3), y + rng.uniform(-3, 3)
            for _ in range(3):
                c0, r0 = raster.to_px(np.array([cx - sx / 2, cy - sy / 2]))
                c1, r1 = raster.to_px(np.array([cx + sx / 2, cy + sy / 2]))
                if c0 < 0 or r0 < 0 or c1 >= raster.w or r1 >= raster.h:
                    break
                if not taken[r0:r1 + 1, c0:c1 + 1].any():
                    taken[max(0, r0 - 2):r1 + 3, max(0, c0 - 2):c1 + 3] = 1
                    height = float(rng.choice([rng.uniform(8, 18), rng.uniform(18, 45)], p=[0.6, 0.4]))
                    colour = BUILDING_PALETTE[int(rng.integers(len(BUILDING_PALETTE)))]
                    buildings.append(Building((round(float(cx), 3), round(float(cy), 3)),
                                              (round(sx, 3), round(sy, 3), round(height, 3)), colour))
                    break
                sx, sy = sx * 0.7, sy * 0.7
                if sx < 6 or sy < 6:
                    break
    return buildings


def scatter_trees(area: np.ndarray, rng: np.random.Generator, *, spacing_m: float = 9.0) -> list[Tree]:
    x0, y0 = area.min(axis=0)
    x1, y1 = area.max(axis=0)
    contour = area.astype(np.float32).reshape(-1, 1, 2)
    trees = []
    for y in np.arange(y0 + 3, y1 - 3, spacing_m):
        for x in np.arange(x0 + 3, x1 - 3, spacing_m):
            px, py = x + rng.uniform(-2.5, 2.5), y + rng.uniform(-2.5, 2.5)
            if cv2.pointPolygonTest(contour, (float(px), float(py)), True) > 3.0:
                trees.append(Tree((round(float(px), 3), round(float(py), 3)), round(float(rng.uniform(5, 10)), 3),
                                  round(float(rng.uniform(1.8, 3.2)), 3)))
    return trees


def lane_parking_slots(network: LaneNetwork, *, pitch_m: float = 7.5, clear_ends_m: float = 6.0) -> list[ParkingSlot]:
    """Slots along every lane with a parking row, away from the lane ends (junctions)."""
    slots: list[ParkingSlot] = []
    for lane_id in sorted(network.lanes):
        lane = network.lanes[lane_id]
        if lane.parking_offset_m is None or lane.in_junction:
            continue
        pts = lane.centre_m
        seg = np.linalg.norm(np.diff(pts, axis=0), axis=1)
        arc = np.concatenate([[0.0], np.cumsum(seg)])
        s = clear_ends_m
        while s <= arc[-1] - clear_ends_m:
            i = int(np.clip(np.searchsorted(arc, s) - 1, 0, len(pts) - 2))
            t = (s - arc[i]) / max(seg[i], 1e-9)
            p = pts[i] + (pts[i + 1] - pts[i]) * t
            d = (pts[i + 1] - pts[i]) / max(seg[i], 1e-9)
            right = np.array([d[1], -d[0]])
            q = p + right * lane.parking_offset_m
            slots.append(ParkingSlot(len(slots), (round(float(q[0]), 3), round(float(q[1]), 3)),
                                     round(math.atan2(d[1], d[0]), 6), lane_id, lane.covered))
            s += pitch_m
    return slots
