"""Rendering-based evidence about a target vehicle: the points line-of-sight rays aim at, which
of the six ground views can show it, what the CONFIRM checker would see at a road node, and the
anchor nearest by road where it would accept. Used online by the episode engine (SPL's shortest
path, the oracle's approach) and offline by the solvability check of sampled episodes.
"""

from __future__ import annotations

import math

import networkx as nx
import numpy as np

from agos.runtime.episode_config import ConfirmConfig
from agos.world.sim import sensors
from agos.world.sim.confirm import ConfirmEvidence, check_confirm
from agos.world.sim.options import heading_after, shortest_path
from agos.world.sim.scene import Scene
from agos.world.towns.asset import Town


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
                    target_xy: tuple[float, float], cam: sensors.CameraConfig,
                    heading_rad: float | None = None) -> ConfirmEvidence:
    """Checker evidence at a node as if the UGV stopped there with ``heading_rad`` (default: the
    road's direction at the node). Only the views facing the target are rendered; the others
    cannot show it, so the maximum pixel count is the same."""
    xy = (float(town.roads.positions_world_m[node][0]), float(town.roads.positions_world_m[node][1]))
    heading = town.roads.heading_at(node) if heading_rad is None else heading_rad
    bearing = math.atan2(target_xy[1] - xy[1], target_xy[0] - xy[0])
    shots = [sensors.ground_view(scene, name, xy, heading + math.radians(offset), cam)
             for name, offset in facing_views(heading, bearing, cam.ground_fov_deg)]
    return ConfirmEvidence(True, max((sensors.target_pixels(s, uid) for s in shots), default=0),
                           math.dist(xy, target_xy), line_of_sight(scene, xy, uid, points))


def nearest_verifying_anchor(scene: Scene, town: Town, start: int, start_heading_rad: float, uid: int,
                             target_position: tuple[float, float, float], target_yaw_rad: float,
                             confirm: ConfirmConfig, cam: sensors.CameraConfig) -> tuple[int, float] | None:
    """The decision anchor nearest by road from ``start`` where a STOP_OBSERVE then CONFIRM would
    be accepted, and its road distance; None when no reachable anchor verifies.

    The UGV can stop only at decision anchors, and it arrives by its shortest path
    (:func:`~agos.world.sim.options.shortest_path`, as every drive does), so each anchor is judged
    with the heading it would arrive with. Anchors are tried in road order (ties by node id);
    distance and line of sight are checked before rendering. This is the oracle's goal (the pose
    its shortest road path leads to) and what makes a sampled episode solvable."""
    roads = town.roads
    target_xy = (target_position[0], target_position[1])
    points = target_points(target_position, target_yaw_rad)
    lengths = nx.single_source_dijkstra_path_length(roads.fine, start, weight="length_m")
    ids, xy = roads.anchor_array()
    near = np.hypot(xy[:, 0] - target_xy[0], xy[:, 1] - target_xy[1]) <= confirm.max_distance_m
    for length, node in sorted((lengths[int(n)], int(n)) for n in ids[near] if int(n) in lengths):
        node_xy = (float(roads.positions_world_m[node][0]), float(roads.positions_world_m[node][1]))
        if not line_of_sight(scene, node_xy, uid, points):
            continue
        heading = heading_after(roads, shortest_path(roads, start, node), start_heading_rad)
        if not check_confirm(ground_evidence(scene, town, node, uid, points, target_xy, cam, heading), confirm):
            return node, float(length)
    return None
