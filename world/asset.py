"""A town asset: layout, road graphs and UAV grid, identified by a sha256 over canonical bytes.

The hash covers every number an episode's outcome can depend on (rounded to the millimetre,
serialized as sorted-key JSON), so the same generator and seed give the same hash on any
machine, and an episode that names a hash refuses to run on a different town.
"""

from __future__ import annotations

import functools
import hashlib
import json
from dataclasses import dataclass

from agos.world.roadgraph import RoadGraphs, build_road_graphs
from agos.world.town import TownLayout, build_layout
from agos.world.uavgrid import UavGrid, build_uav_grid


@dataclass
class Town:
    layout: TownLayout
    roads: RoadGraphs
    uav_grid: UavGrid
    sha256: str

    @property
    def town_id(self) -> str:
        return self.layout.town_id


class AssetMismatch(ValueError):
    """An episode names a town hash that differs from the town built here."""


def _mm(v: float) -> int:
    return round(v * 1000)


def canonical_bytes(layout: TownLayout, roads: RoadGraphs, grid: UavGrid) -> bytes:
    doc = {
        "town_id": layout.town_id,
        "junctions": [[_mm(x), _mm(y)] for x, y in layout.junctions],
        "segments": [list(s) for s in layout.segments],
        "buildings": [[_mm(b.center_world_m[0]), _mm(b.center_world_m[1]), *map(_mm, b.size_m),
                       *map(_mm, b.colour)] for b in layout.buildings],
        "slots": [[s.slot_id, _mm(s.position_world_m[0]), _mm(s.position_world_m[1]), _mm(s.yaw_rad)]
                  for s in layout.slots],
        "parked": [[p.slot_id, p.model, p.colour] for p in layout.parked],
        "fine_nodes": [[_mm(x), _mm(y)] for x, y in roads.positions_world_m.tolist()],
        "fine_edges": sorted([u, v] for u, v in roads.fine.edges()),
        "anchors": sorted([n, k] for n, k in roads.anchors.items()),
        "decision_edges": sorted(e.fine_nodes for e in roads.decision_edges.values()),
        "uav_nodes": sorted([n.node_id, *map(_mm, n.position_world_m)] for n in grid.nodes.values()),
    }
    return json.dumps(doc, sort_keys=True, separators=(",", ":")).encode()


@functools.lru_cache(maxsize=8)
def build_town(generator: str, seed: int) -> Town:
    layout = build_layout(generator, seed)
    roads = build_road_graphs(layout)
    _, anchor_xy = roads.anchor_array()
    grid = build_uav_grid(roads.positions_world_m, anchor_xy)
    digest = hashlib.sha256(canonical_bytes(layout, roads, grid)).hexdigest()
    return Town(layout, roads, grid, digest)


def town_for(generator: str, seed: int, expected_sha256: str | None = None) -> Town:
    """Build (or reuse) a town and check it against the hash an episode recorded."""
    town = build_town(generator, seed)
    if expected_sha256 is not None and town.sha256 != expected_sha256:
        raise AssetMismatch(
            f"town {town.town_id}: episode expects asset sha256 {expected_sha256[:12]}..., "
            f"this build gives {town.sha256[:12]}... (different agos version or generator)"
        )
    return town
