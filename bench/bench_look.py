"""Render cost of the rich look (vehicle meshes by body type) against the flat look, on one town.

Both scenes hold the same town, the same parked traffic and the same hard episode's target and
look-alikes; rounds alternate between the looks (one process, one core) and the median is printed:
a UAV nadir render and a six-view set at the default camera settings, from the decision anchors
nearest the target, and the scene build time.

    .venv/bin/python bench/bench_look.py [--town grid-s7] [--repeats 15]
"""

from __future__ import annotations

import argparse
import statistics
import time

import numpy as np

from agos.runtime.episode_config import CameraConfig
from agos.world.episodes.sampling import sample_episode
from agos.world.sim import sensors
from agos.world.sim.scene import Scene
from agos.world.towns.asset import open_town


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--town", default="grid-s7")
    parser.add_argument("--repeats", type=int, default=15)
    args = parser.parse_args()
    town = open_town(args.town)
    cam = CameraConfig()
    scenes, build_s = {}, {}
    for look in ("flat", "rich"):
        start = time.perf_counter()
        scenes[look] = Scene(town.layout, look=look)
        build_s[look] = time.perf_counter() - start
    spec = sample_episode(town, scenes["flat"], "hard", 0, seed=5)
    for scene in scenes.values():
        for v in (spec.target, *spec.distractors):
            scene.add_vehicle(v.model, v.colour, v.position_world_m, v.yaw_rad)
    tx, ty = spec.target.position_world_m[:2]
    ids, xy = town.roads.anchor_array()
    nearest = np.argsort(np.hypot(xy[:, 0] - tx, xy[:, 1] - ty))[:3]
    anchors = [(float(xy[k, 0]), float(xy[k, 1]), town.roads.heading_at(int(ids[k]))) for k in nearest]
    times: dict[tuple[str, str], list[float]] = {}
    for _ in range(args.repeats):
        for look, scene in scenes.items():
            for ax, ay, heading in anchors:
                start = time.perf_counter()
                sensors.six_views(scene, (ax, ay), heading, cam)
                times.setdefault((look, "six"), []).append(time.perf_counter() - start)
            start = time.perf_counter()
            sensors.nadir(scene, (tx, ty), 80.0, cam)
            times.setdefault((look, "uav"), []).append(time.perf_counter() - start)
    print(f"town {args.town}: {len(town.layout.parked)} parked vehicles + target and {len(spec.distractors)} look-alikes")
    for view, what in (("uav", f"UAV nadir {cam.nadir_px}px"), ("six", f"six views {cam.ground_px}px")):
        flat, rich = (statistics.median(times[(look, view)]) * 1000 for look in ("flat", "rich"))
        print(f"{what:22s} flat {flat:7.1f} ms   rich {rich:7.1f} ms   ratio {rich / flat:.2f}x")
    print(f"scene build            flat {build_s['flat'] * 1000:7.1f} ms   rich {build_s['rich'] * 1000:7.1f} ms")
    for scene in scenes.values():
        scene.close()


if __name__ == "__main__":
    main()
