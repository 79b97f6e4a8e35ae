"""A town layout from an OpenDRIVE map: the imported lanes, then the same furnishing as
procedural towns (buildings and trees off the road, a park, parked traffic at the kerb).

Where the map has no parking or shoulder lane next to the outermost driving lane, vehicles park
at the lane's right edge (partly in the lane), as the paper's targets stand on drivable road.
"""

from __future__ import annotations

from collections import defaultdict
from pathlib import Path

import numpy as np

from agos.world.towns.layout import TownLayout
from agos.world.towns.procedural import furnish
from agos.world.towns.streets import Surface

KERB_PARKING_INSET_M = 0.9
"""Lateral offset of a kerb-side parked car's centre inside the lane edge."""


def imported_layout(path: Path, *, seed: int = 0) -> TownLayout:
    from agos.world.towns.opendrive import load_lane_network

    network = load_lane_network(path)
    _kerb_parking(network)
    surfaces = []
    for lane_id in sorted(network.lanes):
        lane = network.lanes[lane_id]
        left, right = lane.boundary()
        step = 2 if len(left) > 6 else 1
        left, right = left[::step], right[::step]
        if len(left) >= 2:
            surfaces.append(Surface("road", np.concatenate([left, right[::-1]]), "strip"))
    layout = TownLayout(path.stem, "opendrive", seed, network, surfaces)
    furnish(layout, np.random.default_rng(seed), parks=1, plazas=0)
    return layout


def _kerb_parking(network) -> None:
    """Give the outermost right-hand driving lane of each road section a kerb parking row when
    the importer found no parking lane beside it."""
    outermost: dict[tuple[str, str, int], tuple[int, str]] = {}
    groups: dict[tuple[str, str, int], list[tuple[int, str]]] = defaultdict(list)
    for lane_id, lane in network.lanes.items():
        parts = lane_id.split(".")
        if lane.in_junction or len(parts) < 3 or not parts[2].lstrip("-").isdigit():
            continue
        num = int(parts[2])
        groups[(parts[0], parts[1], 1 if num > 0 else -1)].append((abs(num), lane_id))
    for key, members in groups.items():
        outermost[key] = max(members)
    for _, lane_id in outermost.values():
        lane = network.lanes[lane_id]
        if lane.parking_offset_m is None and lane.length_m > 20.0:
            lane.parking_offset_m = float(np.median(lane.width_m)) / 2 - KERB_PARKING_INSET_M
