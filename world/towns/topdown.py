"""Top-down maps drawn with OpenCV from the layout (no PyBullet): the map M agents receive, and
debug views of the road graphs and the UAV grid.

North is up. The map of an episode region shows roads, buildings, parks, decks and the agents'
markers (UAV: cyan triangle, UGV: magenta circle); the debug view adds the fine graph, the
decision anchors and the UAV grid.
"""

from __future__ import annotations

from collections.abc import Sequence

import cv2
import numpy as np

from agos.world.towns.layout import TownLayout

COLOURS_BGR = {
    "ground": (200, 210, 214), "road": (70, 70, 72), "junction": (78, 78, 80), "sidewalk": (170, 172, 175),
    "park": (110, 170, 110), "plaza": (150, 160, 175), "building": (120, 130, 145), "deck": (95, 120, 150),
    "marking_yellow": (40, 180, 220), "marking_white": (225, 225, 225), "tree": (60, 120, 60),
}


class MapCanvas:
    """World metres -> pixels for a square region, north up."""

    def __init__(self, region: tuple[float, float, float, float], size_px: int) -> None:
        self.x0, self.y0, x1, y1 = region
        self.scale = size_px / max(x1 - self.x0, y1 - self.y0)
        self.size = size_px
        self.image = np.full((size_px, size_px, 3), COLOURS_BGR["ground"], np.uint8)

    @property
    def metres_per_px(self) -> float:
        return 1.0 / self.scale

    def px(self, pts: np.ndarray) -> np.ndarray:
        pts = np.asarray(pts, dtype=float).reshape(-1, 2)
        u = (pts[:, 0] - self.x0) * self.scale
        v = self.size - (pts[:, 1] - self.y0) * self.scale
        return np.round(np.stack([u, v], axis=1) * 8).astype(np.int32)  # 3 fractional bits

    def poly(self, pts: np.ndarray, colour: tuple[int, int, int]) -> None:
        cv2.fillPoly(self.image, [self.px(pts)], colour, cv2.LINE_AA, shift=3)

    def line(self, pts: np.ndarray, colour: tuple[int, int, int], width: int = 1) -> None:
        cv2.polylines(self.image, [self.px(pts)], False, colour, width, cv2.LINE_AA, shift=3)

    def dot(self, p: Sequence[float], colour: tuple[int, int, int], radius: int = 2) -> None:
        cv2.circle(self.image, tuple(self.px(np.asarray(p))[0]), radius * 8, colour, -1, cv2.LINE_AA, shift=3)


def draw_layout(canvas: MapCanvas, layout: TownLayout) -> None:
    order = ("park", "plaza", "sidewalk", "road", "junction", "marking_white", "marking_yellow")
    for kind in order:
        for surface in layout.surfaces:
            if surface.kind == kind:
                canvas.poly(surface.polygon_m, COLOURS_BGR[kind])
    if not any(s.kind == "road" for s in layout.surfaces):  # imported maps: draw the lanes
        for lane in layout.network.lanes.values():
            left, right = lane.boundary()
            canvas.poly(np.concatenate([left, right[::-1]]), COLOURS_BGR["road"])
    for b in layout.buildings:
        c, s = np.cos(b.yaw_rad), np.sin(b.yaw_rad)
        hx, hy = b.size_m[0] / 2, b.size_m[1] / 2
        corners = [(b.center_world_m[0] + c * dx - s * dy, b.center_world_m[1] + s * dx + c * dy)
                   for dx, dy in ((-hx, -hy), (hx, -hy), (hx, hy), (-hx, hy))]
        canvas.poly(np.asarray(corners), COLOURS_BGR["building"])
    for t in layout.trees:
        canvas.dot(t.position_world_m, COLOURS_BGR["tree"], max(1, round(t.crown_radius_m * canvas.scale)))
    for deck in layout.decks:
        canvas.poly(deck.polygon_m, COLOURS_BGR["deck"])


class RegionMap:
    """The map M of an episode region: the static layout drawn once, agent markers per call."""

    def __init__(self, layout: TownLayout, region: tuple[float, float, float, float], *, size_px: int = 384) -> None:
        self.canvas = MapCanvas(region, size_px)
        draw_layout(self.canvas, layout)
        cv2.rectangle(self.canvas.image, (0, 0), (size_px - 1, size_px - 1), (0, 0, 0), 1)
        self.base = self.canvas.image.copy()

    @property
    def metres_per_px(self) -> float:
        return self.canvas.metres_per_px

    def render(self, *, uav_xy: Sequence[float] | None, ugv_xy: Sequence[float] | None,
               ugv_yaw_rad: float = 0.0) -> np.ndarray:
        """RGB map with the UAV (cyan triangle) and the UGV (magenta dot with heading)."""
        self.canvas.image = self.base.copy()
        _markers(self.canvas, uav_xy, ugv_xy, ugv_yaw_rad)
        return cv2.cvtColor(self.canvas.image, cv2.COLOR_BGR2RGB)


def _markers(canvas: MapCanvas, uav_xy, ugv_xy, ugv_yaw_rad: float) -> None:
    if ugv_xy is not None:
        canvas.dot(ugv_xy, (200, 40, 200), 5)
        tip = np.asarray(ugv_xy) + 9.0 * np.array([np.cos(ugv_yaw_rad), np.sin(ugv_yaw_rad)])
        canvas.line(np.stack([ugv_xy, tip]), (200, 40, 200), 2)
    if uav_xy is not None:
        x, y = uav_xy
        canvas.poly(np.array([(x, y + 8), (x - 6, y - 6), (x + 6, y - 6)]), (220, 200, 0))


def region_map(layout: TownLayout, region: tuple[float, float, float, float], *, size_px: int = 384,
               uav_xy: Sequence[float] | None = None, ugv_xy: Sequence[float] | None = None,
               ugv_yaw_rad: float = 0.0) -> tuple[np.ndarray, float]:
    """RGB map of ``region`` with agent markers, and its metres per pixel."""
    region_map_ = RegionMap(layout, region, size_px=size_px)
    return region_map_.render(uav_xy=uav_xy, ugv_xy=ugv_xy, ugv_yaw_rad=ugv_yaw_rad), region_map_.metres_per_px


def debug_map(layout: TownLayout, roads, uav_nodes: Sequence[Sequence[float]] = (), *, size_px: int = 1600,
              region: tuple[float, float, float, float] | None = None, graph: bool = True) -> np.ndarray:
    """The whole town (or a region) with the fine graph (thin), decision anchors and UAV grid."""
    x0, y0, x1, y1 = region or layout.bounds_world_m(pad_m=60.0)
    side = max(x1 - x0, y1 - y0)
    canvas = MapCanvas((x0, y0, x0 + side, y0 + side), size_px)
    draw_layout(canvas, layout)
    if graph:
        pos = roads.positions_world_m
        for u, v in roads.fine.edges():
            canvas.line(pos[[u, v]], (255, 200, 120), 1)
        colours = {"cruise": (0, 200, 255), "junction_entry": (0, 0, 255), "junction_exit": (0, 160, 0),
                   "dead_end": (255, 0, 255), "fork": (255, 0, 0), "merge": (255, 128, 0)}
        for node, kind in roads.anchors.items():
            canvas.dot(pos[node], colours.get(kind, (0, 0, 0)), 2)
    for p in uav_nodes:
        x, y = p[0], p[1]
        canvas.line(np.array([(x - 3, y), (x + 3, y)]), (30, 30, 30), 1)
        canvas.line(np.array([(x, y - 3), (x, y + 3)]), (30, 30, 30), 1)
    return cv2.cvtColor(canvas.image, cv2.COLOR_BGR2RGB)
