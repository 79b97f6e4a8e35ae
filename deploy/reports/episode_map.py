"""The top-down map of one episode, for recordings and figures (``agos record``, ``agos plot``).

Contract: :func:`episode_map` rebuilds the episode's town as the world did (procedural towns from
generator and seed, imported ones from the local asset cache; the asset hash must match) and draws
the region around the episode's region from above, north up, with the town's own colours
(world/towns/topdown.py). It also gives where both roles started and the UAV's searchable area.
A town that cannot be had here gives a map without the town (``rgb`` None), never an error: a
recording or a figure without the streets is still worth having.
"""

from __future__ import annotations

import functools
import logging
from dataclasses import dataclass
from typing import Any

import numpy as np

from agos.runtime.schemas import EpisodeSpec, Role

log = logging.getLogger("agos.map")
MARGIN = 0.15
"""The map shows the region and this fraction of its side around it."""


@dataclass(frozen=True)
class MapFrame:
    """World metres (x east, y north) -> pixels of a square map image (u right, v down)."""

    x0_m: float
    y0_m: float
    px_per_m: float
    size_px: int

    @classmethod
    def around(cls, region_world_m: tuple[float, float, float, float], size_px: int) -> MapFrame:
        x0, y0, x1, y1 = region_world_m
        side_m = max(x1 - x0, y1 - y0) * (1 + 2 * MARGIN)
        cx, cy = (x0 + x1) / 2, (y0 + y1) / 2
        return cls(cx - side_m / 2, cy - side_m / 2, size_px / side_m, size_px)

    @property
    def extent_world_m(self) -> tuple[float, float, float, float]:
        """The world rectangle the image shows: (x_min, y_min, x_max, y_max)."""
        side_m = self.size_px / self.px_per_m
        return (self.x0_m, self.y0_m, self.x0_m + side_m, self.y0_m + side_m)

    def px(self, points_world_m: Any) -> np.ndarray:
        """(N, 2) pixel coordinates of world points (any shape ending in 2, or one point)."""
        pts = np.asarray(points_world_m, dtype=float).reshape(-1, 2)
        return np.stack([(pts[:, 0] - self.x0_m) * self.px_per_m,
                         self.size_px - (pts[:, 1] - self.y0_m) * self.px_per_m], axis=1)


@dataclass(frozen=True)
class EpisodeMap:
    frame: MapFrame
    rgb: np.ndarray | None
    """The town from above (size_px x size_px x 3, uint8), or None when the town could not be had."""
    starts_world_m: dict[Role, tuple[float, float]]
    """Where each role started (empty without the town)."""
    search_area_world_m: list[tuple[float, float]]
    """The UAV's active waypoints (empty without the town)."""
    missing: str | None = None
    """Why there is no town (``rgb`` None), else None."""


def episode_map(spec: EpisodeSpec, size_px: int = 768,
                around_world_m: tuple[float, float, float, float] | None = None) -> EpisodeMap:
    """The map of ``spec``'s region, or of ``around_world_m`` (x_min, y_min, x_max, y_max) and a margin
    (see the module's contract)."""
    frame = MapFrame.around(around_world_m or spec.region_world_m, size_px)
    town, missing = _town(spec.town.generator, spec.town.seed, spec.asset_sha256, spec.town.town_id)
    if town is None:
        return EpisodeMap(frame, None, {}, [], missing)
    from agos.world.towns.roadgraph import RoadGraphs
    from agos.world.towns.topdown import region_map

    rgb, _ = region_map(town.layout, frame.extent_world_m, size_px=size_px)
    nodes = town.uav_grid.nodes
    starts: dict[Role, tuple[float, float]] = {}
    if spec.uav_start_waypoint in nodes:
        p = nodes[spec.uav_start_waypoint].position_world_m
        starts["uav"] = (float(p[0]), float(p[1]))
    try:
        q = town.roads.positions_world_m[RoadGraphs.parse_anchor_id(spec.ugv_start_waypoint)]
        starts["ugv"] = (float(q[0]), float(q[1]))
    except (ValueError, IndexError, KeyError):
        pass
    area = [(float(nodes[n].position_world_m[0]), float(nodes[n].position_world_m[1]))
            for n in spec.active_uav_waypoints if n in nodes]
    return EpisodeMap(frame, rgb, starts, area)


@functools.lru_cache(maxsize=4)
def _town(generator: str, seed: int, sha256: str, town_id: str) -> tuple[Any, str | None]:
    """The episode's town, or None and why (logged) when it cannot be rebuilt or found here."""
    from agos.world.towns.asset import town_for

    try:
        return town_for(generator, seed, sha256, town_id=town_id), None
    except (ValueError, OSError) as exc:  # AssetError and AssetMismatch are ValueErrors
        log.warning("no map of town %s: %s", town_id, exc)
        return None, str(exc)
