"""The UAV waypoint grid (paper Appendix A.1): 40 m spacing at 80 m altitude.

Built over the bounding box of the road nodes (the spawn bounding box) expanded by 50 m on each
side, and kept only where a node lies within 40 m (horizontally) of a UGV decision anchor. Node
ids are ``U<i>_<j>`` with i along x and j along y, so neighbours are found by index arithmetic.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

SPACING_M = 40.0
ALTITUDE_M = 80.0
EXPAND_M = 50.0
ROAD_PROXIMITY_M = 40.0


@dataclass(frozen=True)
class UavNode:
    node_id: str
    i: int
    j: int
    position_world_m: tuple[float, float, float]


@dataclass
class UavGrid:
    nodes: dict[str, UavNode]
    spacing_m: float = SPACING_M
    altitude_m: float = ALTITUDE_M

    def inside(self, region: tuple[float, float, float, float]) -> list[str]:
        """Ids of the nodes inside a region (the episode's active flags)."""
        x0, y0, x1, y1 = region
        return sorted(n.node_id for n in self.nodes.values()
                      if x0 <= n.position_world_m[0] <= x1 and y0 <= n.position_world_m[1] <= y1)

    def nearest(self, xy: tuple[float, float], among: list[str]) -> str:
        p = np.asarray(xy)
        return min(among, key=lambda k: (float(np.hypot(*(np.asarray(self.nodes[k].position_world_m[:2]) - p))), k))

    def neighbours(self, centre: str, active: set[str]) -> list[str]:
        """Active nodes of the 3x3 neighbourhood of ``centre``, excluding it (at most 8)."""
        c = self.nodes[centre]
        out = []
        for di in (-1, 0, 1):
            for dj in (-1, 0, 1):
                key = f"U{c.i + di}_{c.j + dj}"
                if (di or dj) and key in active:
                    out.append(key)
        return out

    def reachable(self, start: str, active: set[str]) -> set[str]:
        """The active nodes a UAV at ``start`` can fly to by neighbour moves (``start`` included):
        the active flags of a region need not be one connected piece of the grid."""
        seen, frontier = {start}, [start]
        while frontier:
            for n in self.neighbours(frontier.pop(), active):
                if n not in seen:
                    seen.add(n)
                    frontier.append(n)
        return seen


def build_uav_grid(road_positions_m: np.ndarray, anchor_positions_m: np.ndarray) -> UavGrid:
    x_min, y_min = road_positions_m.min(axis=0) - EXPAND_M
    x_max, y_max = road_positions_m.max(axis=0) + EXPAND_M
    ni = int(np.floor((x_max - x_min) / SPACING_M)) + 1
    nj = int(np.floor((y_max - y_min) / SPACING_M)) + 1
    xs = x_min + SPACING_M * np.arange(ni)
    ys = y_min + SPACING_M * np.arange(nj)
    gx, gy = np.meshgrid(xs, ys, indexing="ij")
    near = np.zeros(gx.shape, dtype=bool)
    for chunk in np.array_split(anchor_positions_m, max(1, len(anchor_positions_m) // 2000)):
        d = np.hypot(gx[..., None] - chunk[:, 0], gy[..., None] - chunk[:, 1]).min(axis=-1)
        near |= d <= ROAD_PROXIMITY_M
    nodes = {}
    for i, j in zip(*np.nonzero(near), strict=True):
        key = f"U{i}_{j}"
        nodes[key] = UavNode(key, int(i), int(j), (round(float(xs[i]), 3), round(float(ys[j]), 3), ALTITUDE_M))
    return UavGrid(nodes)
