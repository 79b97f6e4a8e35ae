"""Solvability of an episode, checked by rendering (never by assumption).

An episode is solvable when (1) some decision anchor lies within the CONFIRM distance of the
target, has a clear line of sight to it and shows it in its six views (the checker would accept
a CONFIRM there), (2) the UGV can drive from its start to such an anchor, and (3) some active
UAV node sees the target in its nadir view.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import networkx as nx
import numpy as np

from agos.world.sim import sensors
from agos.world.sim.confirm import ConfirmConfig, check_confirm
from agos.world.sim.evidence import ground_evidence, line_of_sight, target_points
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
          active_uav: list[str], *, confirm: ConfirmConfig | None = None,
          cam: sensors.CameraConfig | None = None, max_renders: int = 8) -> Solvability:
    confirm = confirm or ConfirmConfig()
    cam = cam or sensors.CameraConfig()
    target_xy = (position[0], position[1])
    points = target_points(position, yaw_rad)
    ids, xy = town.roads.anchor_array()
    dist = np.hypot(xy[:, 0] - target_xy[0], xy[:, 1] - target_xy[1])
    verifying: list[int] = []
    renders = 0
    for k in np.argsort(dist, kind="stable"):
        if dist[k] > confirm.max_distance_m or renders >= max_renders:
            break
        node = int(ids[k])
        if not line_of_sight(scene, (float(xy[k][0]), float(xy[k][1])), uid, points):
            continue
        renders += 1
        if not check_confirm(ground_evidence(scene, town, node, uid, points, target_xy, cam), confirm):
            verifying.append(node)
            break  # one verifying anchor makes the episode solvable
    seeing: list[str] = []
    for node_id in active_uav:
        uav_node = town.uav_grid.nodes[node_id]
        if math.dist(uav_node.position_world_m[:2], target_xy) > 50.0:
            continue
        shot = sensors.nadir(scene, uav_node.position_world_m[:2], uav_node.position_world_m[2], cam)
        if sensors.target_pixels(shot, uid) >= UAV_VISIBLE_MIN_PX * (cam.nadir_px / 512) ** 2:
            seeing.append(node_id)
            break
    return Solvability(verifying, seeing)


def reachable(town: Town, start: int, goals: list[int]) -> bool:
    if not goals:
        return False
    reach = nx.descendants(town.roads.fine, start) | {start}
    return any(g in reach for g in goals)
