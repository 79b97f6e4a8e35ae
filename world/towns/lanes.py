"""The lane network: the one road representation the world is built from.

Procedural towns and imported OpenDRIVE maps both produce a :class:`LaneNetwork`; the fine and
decision graphs (:mod:`agos.world.towns.roadgraph`), parking slots, the rendered road surface and the
off-road placement of buildings are all derived from it. World frame: x east, y north, metres.

A :class:`Lane` is one drivable lane in its direction of travel: a dense centre line (points
about 1 m apart or closer, first to last in the direction of travel), its width along that line,
and the ids of the lanes a vehicle may continue into at its end.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

TURNAROUND = "turnaround"
"""``road_id`` of a connector that turns a vehicle around at a dead end."""


@dataclass
class Lane:
    lane_id: str
    """Unique, stable id (e.g. ``r12.s0.-1`` for OpenDRIVE road 12, section 0, lane -1)."""
    centre_m: np.ndarray
    """(N, 2) centre line in the direction of travel, N >= 2, spacing <= ~1 m."""
    width_m: np.ndarray
    """(N,) lane width at each centre-line point."""
    successors: list[str] = field(default_factory=list)
    """Lanes a vehicle may continue into from this lane's last point."""
    in_junction: bool = False
    """Connector lanes inside a junction (no cruise anchors, no parking)."""
    road_id: str = ""
    parking_offset_m: float | None = None
    """Lateral offset (to the right of the centre line) of a parking row along this lane, or None."""
    covered: bool = False
    """Under a deck or in a tunnel: drivable, but hidden from the air."""
    lane_changes: list[str] = field(default_factory=list)
    """Neighbouring lanes in the same direction a vehicle may change into (multi-lane roads)."""

    @property
    def length_m(self) -> float:
        return float(np.linalg.norm(np.diff(self.centre_m, axis=0), axis=1).sum())

    def boundary(self) -> tuple[np.ndarray, np.ndarray]:
        """Left and right edges of the lane, (N, 2) each."""
        d = np.gradient(self.centre_m, axis=0)
        d /= np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-9)
        left = np.stack([-d[:, 1], d[:, 0]], axis=1)
        half = (self.width_m / 2)[:, None]
        return self.centre_m + left * half, self.centre_m - left * half


@dataclass
class LaneNetwork:
    lanes: dict[str, Lane]
    warnings: list[str] = field(default_factory=list)
    """What an importer skipped or repaired (file, road id, reason)."""

    def bounds_m(self) -> tuple[float, float, float, float]:
        pts = np.concatenate([lane.centre_m for lane in self.lanes.values()])
        return float(pts[:, 0].min()), float(pts[:, 1].min()), float(pts[:, 0].max()), float(pts[:, 1].max())

    def check(self) -> None:
        """Raise ValueError naming the lane for dangling successors or malformed arrays."""
        for lane in self.lanes.values():
            if lane.centre_m.ndim != 2 or lane.centre_m.shape[1] != 2 or len(lane.centre_m) < 2:
                raise ValueError(f"lane {lane.lane_id}: centre line must be (N>=2, 2), got {lane.centre_m.shape}")
            if lane.width_m.shape != (len(lane.centre_m),):
                raise ValueError(f"lane {lane.lane_id}: width has {lane.width_m.shape}, centre has {len(lane.centre_m)}")
            if not np.all(np.isfinite(lane.centre_m)) or not np.all(np.isfinite(lane.width_m)):
                raise ValueError(f"lane {lane.lane_id}: non-finite coordinates or widths")
            for succ in lane.successors:
                if succ not in self.lanes:
                    raise ValueError(f"lane {lane.lane_id}: successor {succ} does not exist")
