"""Regenerate the figures of docs/WORLD.md (run from the repository root):

    .venv/bin/python docs/world_figures.py [--carla ../shared/maps/carla/Town10HD.xodr]

The UAV view, the six views and the references are drawn in both looks from the same episode
(sampled on the flat scene): ``<town>_<figure>.png`` (flat) and ``<town>_<figure>_rich.png``.
"""

from __future__ import annotations

import argparse
import math
import tempfile
from pathlib import Path

import cv2
import numpy as np

from agos.runtime.codec import decode_image
from agos.world.episodes.sampling import sample_episode
from agos.world.sim import sensors
from agos.world.sim.episode_vehicles import add_episode_vehicles
from agos.world.sim.scene import Scene
from agos.world.towns.asset import Town, freeze, open_town
from agos.world.towns.topdown import debug_map, region_map

OUT = Path("docs/images")


def save(name: str, rgb: np.ndarray) -> None:
    OUT.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(OUT / name), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
    print(OUT / name)


def label(img: np.ndarray, text: str) -> np.ndarray:
    out = img.copy()
    cv2.putText(out, text, (4, 14), cv2.FONT_HERSHEY_SIMPLEX, 0.42, (0, 0, 0), 3, cv2.LINE_AA)
    cv2.putText(out, text, (4, 14), cv2.FONT_HERSHEY_SIMPLEX, 0.42, (255, 255, 255), 1, cv2.LINE_AA)
    return out


def figures(town: Town, tag: str) -> None:
    cam = sensors.CameraConfig()
    flat = Scene(town.layout, look="flat")
    spec = sample_episode(town, flat, "hard", 0, seed=5)
    t = spec.target
    # UAV: the active node nearest the target; UGV: the nearest decision anchor
    node = min(spec.active_uav_waypoints, key=lambda k: math.dist(town.uav_grid.nodes[k].position_world_m[:2],
                                                                  t.position_world_m[:2]))
    pos = town.uav_grid.nodes[node].position_world_m
    ids, xy = town.roads.anchor_array()
    anchor = int(ids[np.argmin(np.hypot(xy[:, 0] - t.position_world_m[0], xy[:, 1] - t.position_world_m[1]))])
    p = town.roads.positions_world_m[anchor]
    for look, scene in (("flat", flat), ("rich", None)):
        scene = scene or Scene(town.layout, look=look)
        suffix = "" if look == "flat" else f"_{look}"
        uid, *_ = add_episode_vehicles(scene, spec)
        shot = sensors.nadir(scene, pos[:2], pos[2], cam)
        save(f"{tag}_uav_grid{suffix}.png", sensors.grid_overlay(shot.render.rgb))
        six = sensors.six_views(scene, (float(p[0]), float(p[1])), town.roads.heading_at(anchor), cam)
        top = np.concatenate([label(s.render.rgb, s.name) for s in six[:3]], axis=1)
        bottom = np.concatenate([label(s.render.rgb, s.name) for s in six[3:]], axis=1)
        save(f"{tag}_six_views{suffix}.png", np.concatenate([top, bottom], axis=0))
        refs = sensors.reference_views(scene, uid, t.position_world_m, t.yaw_rad, cam)
        tiles = []
        for f in refs:
            rgba = decode_image(f.data)
            bg = np.full(rgba.shape[:2] + (3,), 235, np.uint8)
            alpha = rgba[:, :, 3:4] / 255.0
            tiles.append(label((rgba[:, :, :3] * alpha + bg * (1 - alpha)).astype(np.uint8), f.name))
        save(f"{tag}_references{suffix}.png", np.concatenate(tiles, axis=1))
        scene.close()
    rmap, _ = region_map(town.layout, spec.region_world_m, size_px=384, uav_xy=pos[:2], ugv_xy=(p[0], p[1]),
                         ugv_yaw_rad=town.roads.heading_at(anchor))
    save(f"{tag}_episode_map.png", rmap)
    nodes = [n.position_world_m for n in town.uav_grid.nodes.values()]
    save(f"{tag}_graphs.png", debug_map(town.layout, town.roads, nodes, size_px=1400))
    cx, cy = t.position_world_m[:2]
    save(f"{tag}_graphs_zoom.png", debug_map(town.layout, town.roads, nodes, size_px=900,
                                             region=(cx - 70, cy - 70, cx + 70, cy + 70)))


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--carla", type=Path, default=Path("../shared/maps/carla/Town10HD.xodr"))
    args = parser.parse_args()
    figures(open_town("parks-s23"), "procedural")
    if args.carla.exists():
        from agos.world.towns.imported import imported_layout

        with tempfile.TemporaryDirectory():
            figures(freeze(imported_layout(args.carla)), "carla")


if __name__ == "__main__":
    main()
