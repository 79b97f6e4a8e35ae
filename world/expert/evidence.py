"""What the expert's planner asks the world about an episode in progress (ground truth, by
rendering, with the checks the benchmark itself applies), cached per episode.

* :meth:`Evidence.uav_cell`: whether a UAV at a grid node finds a vehicle, and in which grid cell
  of its nadir image: the vehicle oracle-visible (at least ``uav_visible_min_px`` instance
  pixels, the threshold of tau_e) and its centre inside the image, within ``max_distance_m``;
* :meth:`Evidence.verifies`: whether STOP_OBSERVE then CONFIRM at a decision anchor, arrived at
  with a heading, passes the CONFIRM checker (world/sim/evidence.py, as the oracle and SPL use);
* :meth:`Evidence.nearest_verifying`: the anchor nearest by road where it would;
* :meth:`Evidence.candidate_centre`: where Ego-to-Allo projection puts a cell's candidate.
"""

from __future__ import annotations

import math

import numpy as np

from agos.runtime.geometry import centroid, point_in_polygon
from agos.world.sim import sensors
from agos.world.sim.confirm import check_confirm
from agos.world.sim.evidence import ground_evidence, line_of_sight, nearest_verifying_anchor, target_points
from agos.world.sim.state import EpisodeState


class Evidence:
    def __init__(self, st: EpisodeState) -> None:
        self.st = st
        self.target_xy = st.target_xy
        t = st.spec.target
        self._points = target_points(t.position_world_m, t.yaw_rad)
        self._confirm = st.cfg.confirm_at_view_size()
        self._nadir: dict[str, sensors.Shot] = {}
        self._verifies: dict[tuple[int, float], bool] = {}

    def nadir(self, node: str) -> sensors.Shot:
        if node not in self._nadir:
            p = self.st.town.uav_grid.nodes[node].position_world_m
            self._nadir[node] = sensors.nadir(self.st.scene, p[:2], p[2], self.st.cfg.cameras)
        return self._nadir[node]

    def uav_cell(self, node: str, uid: int, xy: tuple[float, float], max_distance_m: float) -> str | None:
        """The grid cell holding the vehicle ``uid`` (centre ``xy``) in the nadir view at ``node``;
        None when it is farther than ``max_distance_m``, not oracle-visible or not in the image."""
        here = self.st.town.uav_grid.nodes[node].position_world_m
        if math.dist(here[:2], xy) > max_distance_m:
            return None
        shot = self.nadir(node)
        if sensors.target_pixels(shot, uid) < self.st.cfg.uav_visible_min_px():
            return None
        i = shot.intrinsics
        pixel = sensors.ground_to_pixel(xy, shot.world_from_camera, i)
        if pixel is None or not (0 <= pixel[0] < i.width_px and 0 <= pixel[1] < i.height_px):
            return None
        return sensors.cell_of_pixel(pixel[0], pixel[1], i.width_px, i.height_px)

    def candidate_centre(self, node: str, cell: str) -> tuple[tuple[float, float], bool]:
        """Ego-to-Allo projection of ``cell`` seen from ``node`` (as world/sim/rules.py projects an
        annotation): the candidate's centre, and whether its polygon holds the target."""
        shot = self.nadir(node)
        polygon = sensors.cell_polygon_world(cell, shot.world_from_camera, shot.intrinsics)
        return centroid(polygon), point_in_polygon(self.target_xy, polygon)

    def verifies(self, anchor: int, heading_rad: float) -> bool:
        """STOP_OBSERVE then CONFIRM at ``anchor``, arrived at with ``heading_rad``, would pass."""
        key = (anchor, heading_rad)
        if key not in self._verifies:
            roads = self.st.roads
            xy = (float(roads.positions_world_m[anchor][0]), float(roads.positions_world_m[anchor][1]))
            ok = (math.dist(xy, self.target_xy) <= self._confirm.max_distance_m
                  and line_of_sight(self.st.scene, xy, self.st.target_uid, self._points)
                  and not check_confirm(ground_evidence(self.st.scene, self.st.town, anchor, self.st.target_uid, self._points,
                                                        self.target_xy, self.st.cfg.cameras, heading_rad), self._confirm))
            self._verifies[key] = bool(ok)
        return self._verifies[key]

    def nearest_verifying(self, anchor: int, heading_rad: float) -> int | None:
        t = self.st.spec.target
        found = nearest_verifying_anchor(self.st.scene, self.st.town, anchor, heading_rad, self.st.target_uid,
                                         t.position_world_m, t.yaw_rad, self._confirm, self.st.cfg.cameras)
        return None if found is None else found[0]

    def lookalikes(self) -> list[tuple[int, tuple[float, float]]]:
        """(scene uid, centre) of the episode's look-alikes (the distractors, hard episodes)."""
        uids = self.st.added[1:1 + len(self.st.spec.distractors)]
        return [(uid, (d.position_world_m[0], d.position_world_m[1]))
                for uid, d in zip(uids, self.st.spec.distractors, strict=True)]


def as_xy(p: np.ndarray | tuple[float, ...]) -> tuple[float, float]:
    return (float(p[0]), float(p[1]))
