"""Solvability of an episode, checked by rendering (never by assumption).

An episode is solvable when

1. the UGV can drive from its start to a decision anchor where the checker would accept a CONFIRM
   (within the CONFIRM distance of the target, a clear line of sight, the target in its six
   views, rendered with the heading the UGV arrives with):
   :func:`~agos.world.sim.evidence.nearest_verifying_anchor`, the goal of the oracle's shortest
   road path; and
2. the UAV can fly from its start, by neighbour moves over the active nodes (which need not be
   one connected piece of the grid), to a node whose nadir view shows the target oracle-visibly,
   its centre inside the image (so the UAV can annotate the cell that holds it).

Without the starts (``ugv_start``, ``uav_start``) the check answers for any start: a verifying
anchor near the target (with the road's heading), any active node.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import networkx as nx
import numpy as np

from agos.world.sim import sensors
from agos.world.sim.confirm import ConfirmConfig, check_confirm
from agos.world.sim.evidence import ground_evidence, line_of_sight, nearest_verifying_anchor, target_points
from agos.world.sim.scene import Scene
from agos.world.towns.asset import Town

UAV_VISIBLE_MIN_PX = 30


@dataclass(frozen=True)
class Solvability:
    verifying_anchors: list[int]
    uav_nodes: list[str]

    @property
    def solvable(self) -> bool:
        return bool(self.verifying_anchors) and bool(self.uav_nodes)


def check(scene: Scene, town: Town, uid: int, position: tuple[float, float, float], yaw_rad: float,
          active_uav: list[str], *, ugv_start: int | None = None, uav_start: str | None = None,
          confirm: ConfirmConfig | None = None, cam: sensors.CameraConfig | None = None,
          max_renders: int = 8) -> Solvability:
    confirm = confirm or ConfirmConfig()
    cam = cam or sensors.CameraConfig()
    target_xy = (position[0], position[1])
    if ugv_start is not None:
        found = nearest_verifying_anchor(scene, town, ugv_start, town.roads.heading_at(ugv_start), uid, position,
                                         yaw_rad, confirm, cam)
        verifying = [found[0]] if found is not None else []
    else:
        verifying = _verifying_near(scene, town, uid, position, yaw_rad, confirm, cam, max_renders)
    flyable = active_uav if uav_start is None else sorted(town.uav_grid.reachable(uav_start, set(active_uav)))
    seeing: list[str] = []
    for node_id in flyable:
        uav_node = town.uav_grid.nodes[node_id]
        if math.dist(uav_node.position_world_m[:2], target_xy) > 50.0:
            continue
        shot = sensors.nadir(scene, uav_node.position_world_m[:2], uav_node.position_world_m[2], cam)
        if sensors.target_pixels(shot, uid) >= UAV_VISIBLE_MIN_PX * (cam.nadir_px / 512) ** 2 and _in_image(shot, target_xy):
            seeing.append(node_id)
            break
    return Solvability(verifying, seeing)


def _verifying_near(scene: Scene, town: Town, uid: int, position: tuple[float, float, float], yaw_rad: float,
                    confirm: ConfirmConfig, cam: sensors.CameraConfig, max_renders: int) -> list[int]:
    """A verifying anchor nearest the target in a straight line (the road's heading), from any start."""
    target_xy = (position[0], position[1])
    points = target_points(position, yaw_rad)
    ids, xy = town.roads.anchor_array()
    dist = np.hypot(xy[:, 0] - target_xy[0], xy[:, 1] - target_xy[1])
    renders = 0
    for k in np.argsort(dist, kind="stable"):
        if dist[k] > confirm.max_distance_m or renders >= max_renders:
            break
        node = int(ids[k])
        if not line_of_sight(scene, (float(xy[k][0]), float(xy[k][1])), uid, points):
            continue
        renders += 1
        if not check_confirm(ground_evidence(scene, town, node, uid, points, target_xy, cam), confirm):
            return [node]  # one verifying anchor makes the episode solvable
    return []


def _in_image(shot: sensors.Shot, xy: tuple[float, float]) -> bool:
    """The ground point ``xy`` is inside the view, so it falls in one of its grid cells."""
    i = shot.intrinsics
    pixel = sensors.ground_to_pixel(xy, shot.world_from_camera, i)
    return pixel is not None and 0 <= pixel[0] < i.width_px and 0 <= pixel[1] < i.height_px


def reachable(town: Town, start: int, goals: list[int]) -> bool:
    if not goals:
        return False
    reach = nx.descendants(town.roads.fine, start) | {start}
    return any(g in reach for g in goals)
