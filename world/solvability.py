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

from agos.world import sensors
from agos.world.asset import Town
from agos.world.confirm import ConfirmEvidence, ConfirmSettings, check_confirm
from agos.world.scene import Scene

UAV_VISIBLE_MIN_PX = 30


@dataclass(frozen=True)
class Solvability:
    verifying_anchors: list[int]
    uav_nodes: list[str]

    @property
    def solvable(self) -> bool:
        return bool(self.verifying_anchors) and bool(self.uav_nodes)


def target_points(position: tuple[float, float, float], yaw_rad: float) -> np.ndarray:
    """Points on a parked vehicle's body used by line-of-sight rays."""
    c, s = math.cos(yaw_rad), math.sin(yaw_rad)
    local = ((0, 0, 0.8), (0, 0, 1.3), (1.5, 0, 0.9), (-1.5, 0, 0.9), (0, 0.7, 0.9), (0, -0.7, 0.9))
    return np.array([(position[0] + c * dx - s * dy, position[1] + s * dx + c * dy, z) for dx, dy, z in local])


def line_of_sight(scene: Scene, xy: tuple[float, float], uid: int, points: np.ndarray) -> bool:
    return scene.line_of_sight(np.array([xy[0], xy[1], sensors.UGV_CAMERA_HEIGHT_M]), uid, points)


def facing_views(heading_rad: float, bearing_rad: float, fov_deg: float) -> list[tuple[str, float]]:
    """The STOP_OBSERVE views whose field of view can contain a point at ``bearing_rad`` (with a
    margin for the target's extent): the only views that can show it."""
    out = []
    for name, offset in sensors.SIX_VIEWS:
        diff = (bearing_rad - heading_rad - math.radians(offset) + math.pi) % (2 * math.pi) - math.pi
        if abs(diff) <= math.radians(fov_deg / 2 + 15.0):
            out.append((name, offset))
    return out


def ground_evidence(scene: Scene, town: Town, node: int, uid: int, points: np.ndarray,
                    target_xy: tuple[float, float], cam: sensors.CameraSettings) -> ConfirmEvidence:
    """Checker evidence at a node as if the UGV stopped there. Only the views facing the target
    are rendered; the others cannot show it, so the maximum pixel count is the same."""
    xy = (float(town.roads.positions_world_m[node][0]), float(town.roads.positions_world_m[node][1]))
    heading = town.roads.heading_at(node)
    bearing = math.atan2(target_xy[1] - xy[1], target_xy[0] - xy[0])
    shots = [sensors.ground_view(scene, name, xy, heading + math.radians(offset), cam)
             for name, offset in facing_views(heading, bearing, cam.ground_fov_deg)]
    return ConfirmEvidence(True, max((sensors.target_pixels(s, uid) for s in shots), default=0),
                           math.dist(xy, target_xy), line_of_sight(scene, xy, uid, points))


def check(scene: Scene, town: Town, uid: int, position: tuple[float, float, float], yaw_rad: float,
          active_uav: list[str], *, confirm: ConfirmSettings | None = None,
          cam: sensors.CameraSettings | None = None, max_renders: int = 8) -> Solvability:
    confirm = confirm or ConfirmSettings()
    cam = cam or sensors.CameraSettings()
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
    seeing = []
    for node_id in active_uav:
        node = town.uav_grid.nodes[node_id]
        if math.dist(node.position_world_m[:2], target_xy) > 50.0:
            continue
        shot = sensors.nadir(scene, node.position_world_m[:2], node.position_world_m[2], cam)
        if sensors.target_pixels(shot, uid) >= UAV_VISIBLE_MIN_PX * (cam.nadir_px / 512) ** 2:
            seeing.append(node_id)
            break
    return Solvability(verifying, seeing)


def reachable(town: Town, start: int, goals: list[int]) -> bool:
    if not goals:
        return False
    reach = nx.descendants(town.roads.fine, start) | {start}
    return any(g in reach for g in goals)
