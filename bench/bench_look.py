"""Cost of the rich look (textured city, drawn shadows, vehicle meshes) against the flat look.

Both scenes hold the same town, the same parked traffic and the same hard episode's target and
look-alikes. Rounds alternate between the looks (one process, CPU time of this process, so other
load on the machine counts less) and medians are printed as ratios against flat measured in the
same run:

1. a UAV observation: nadir render, RGB and grid-overlay frames, depth and semantic PNGs, map M;
   a six-view observation: six ground renders and their frames, map M (issue 22 goal: <= 1.6x);
   the bare renders alone as well;
2. scene build time and the city's size (bodies, triangles);
3. a world worker's peak RSS: a fresh process that loads the largest CARLA town's frozen asset and
   builds its scene, per look, median of three processes each (goal: rich <= 1.5x flat).

    .venv/bin/python bench/bench_look.py [--town grid-s7] [--repeats 15] [--carla ../shared/maps/carla/Town04.xodr]

``--quick`` (``make bench``): 3 rounds and one probe process a look. ``--json``: also one
machine-readable line per figure (bench/figures.py).

``--renderer egl`` measures the renderers instead: PyBullet's EGL plugin against TinyRenderer on the
same scenes (each look of ``--look``, default both), the same observations, rounds alternating, CPU
time of this process and wall time (on a GPU the work leaves the CPU, so the wall time is the
latency of an observation and the CPU time what a worker's core pays). EGL renders on whatever
device ``EGL_VISIBLE_DEVICES`` (or the plugin) picks: Mesa's llvmpipe where there is no GPU.

    .venv/bin/python bench/bench_look.py --renderer egl [--look flat] [--repeats 15]
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
from figures import Figures

from agos.runtime.codec import encode_png
from agos.runtime.episode_config import CameraConfig
from agos.world.episodes.sampling import sample_episode
from agos.world.sim import sensors
from agos.world.sim.episode_vehicles import add_episode_vehicles
from agos.world.sim.scene import Scene, pb
from agos.world.towns.asset import Town, open_town
from agos.world.towns.topdown import RegionMap

LOOKS = ("flat", "rich")


def _cpu(fn: Callable[[], object]) -> float:
    start = time.process_time()
    fn()
    return time.process_time() - start


def _clock(fn: Callable[[], object]) -> tuple[float, float]:
    """CPU and wall seconds of one call."""
    cpu, wall = time.process_time(), time.perf_counter()
    fn()
    return time.process_time() - cpu, time.perf_counter() - wall


def renderer_costs(town: Town, repeats: int, looks: tuple[str, ...], figures: Figures) -> None:
    """EGL against TinyRenderer: per look, the same town, traffic, episode vehicles and views."""
    for look in looks:
        _renderers_on(town, look, repeats, figures)



def _episode_in(town, scenes: dict, sample_in: Scene):
    """One hard episode (seed 5) sampled in ``sample_in``, its vehicles added to every scene of ``scenes``:
    the spec, the target's (x, y) and the three road anchors nearest it (position, heading)."""
    spec = sample_episode(town, sample_in, "hard", 0, seed=5)
    for scene in scenes.values():
        add_episode_vehicles(scene, spec)
    tx, ty = spec.target.position_world_m[:2]
    ids, xy = town.roads.anchor_array()
    nearest = np.argsort(np.hypot(xy[:, 0] - tx, xy[:, 1] - ty))[:3]
    anchors = [((float(xy[k, 0]), float(xy[k, 1])), town.roads.heading_at(int(ids[k]))) for k in nearest]
    return spec, (tx, ty), anchors

def _renderers_on(town: Town, look: str, repeats: int, figures: Figures) -> None:
    cam = CameraConfig()
    renderers = ("tiny", "egl")
    scenes = {}
    for renderer in renderers:
        start = time.perf_counter()
        scenes[renderer] = Scene(town.layout, look=look, renderer=renderer)
        print(f"{look} look, {renderer}: scene built in {time.perf_counter() - start:.2f} s", flush=True)
    _, (tx, ty), anchors = _episode_in(town, scenes, scenes["tiny"])

    def uav_obs(scene: Scene) -> None:
        sensors.frames_of(sensors.nadir(scene, (tx, ty), 80.0, cam), scene, cam, with_grid=True)

    def six_obs(scene: Scene, xy: tuple[float, float], heading: float) -> None:
        for shot in sensors.six_views(scene, xy, heading, cam):
            sensors.frames_of(shot, scene, cam)

    for scene in scenes.values():  # warm-up (the EGL context, textures on the device)
        uav_obs(scene)
        six_obs(scene, *anchors[0])
    times: dict[tuple[str, str], list[tuple[float, float]]] = {}
    for _ in range(repeats):
        for renderer, scene in scenes.items():
            for a_xy, heading in anchors:
                times.setdefault((renderer, "six_obs"), []).append(
                    _clock(lambda s=scene, p=a_xy, h=heading: six_obs(s, p, h)))
                times.setdefault((renderer, "six"), []).append(
                    _clock(lambda s=scene, p=a_xy, h=heading: sensors.six_views(s, p, h, cam)))
            times.setdefault((renderer, "uav_obs"), []).append(_clock(lambda s=scene: uav_obs(s)))
            times.setdefault((renderer, "uav"), []).append(_clock(lambda s=scene: sensors.nadir(s, (tx, ty), 80.0, cam)))
    print(f"{look} look, town {town.town_id}: medians of {repeats} rounds x {len(anchors)} anchors; "
          "CPU time of this process | wall time")
    rows = (("uav_obs", f"UAV observation {cam.nadir_px}px"), ("six_obs", f"six-view observation {cam.ground_px}px"),
            ("uav", "  UAV render alone"), ("six", "  six renders alone"))
    for key, what in rows:
        cpu = {r: statistics.median(c for c, _ in times[(r, key)]) * 1000 for r in renderers}
        wall = {r: statistics.median(w for _, w in times[(r, key)]) * 1000 for r in renderers}
        print(f"{what:34s} CPU tiny {cpu['tiny']:7.1f} ms  egl {cpu['egl']:7.1f} ms  {cpu['egl'] / cpu['tiny']:.2f}x"
              f"   | wall tiny {wall['tiny']:7.1f} ms  egl {wall['egl']:7.1f} ms  {wall['egl'] / wall['tiny']:.2f}x")
        if key in ("uav_obs", "six_obs"):
            figures.add(f"{what.strip()}, {look} look: EGL vs TinyRenderer (CPU)", cpu["egl"] / cpu["tiny"],
                        f"{cpu['egl'] / cpu['tiny']:.2f}x ({cpu['egl']:.0f} vs {cpu['tiny']:.0f} ms CPU; wall "
                        f"{wall['egl']:.0f} vs {wall['tiny']:.0f} ms)")
    for scene in scenes.values():
        scene.close()


def observation_costs(town: Town, repeats: int, figures: Figures) -> None:
    cam = CameraConfig()
    scenes, build_s = {}, {}
    for look in LOOKS:
        start = time.perf_counter()
        scenes[look] = Scene(town.layout, look=look)
        build_s[look] = time.perf_counter() - start
    spec, (tx, ty), anchors = _episode_in(town, scenes, scenes["flat"])
    region_map = RegionMap(town.layout, spec.region_world_m, size_px=cam.map_px)

    def uav_obs(scene: Scene) -> None:
        shot = sensors.nadir(scene, (tx, ty), 80.0, cam)
        sensors.frames_of(shot, scene, cam, with_grid=True)
        encode_png(region_map.render(uav_xy=(tx, ty), ugv_xy=anchors[0][0], ugv_yaw_rad=anchors[0][1]))

    def six_obs(scene: Scene, xy: tuple[float, float], heading: float) -> None:
        for shot in sensors.six_views(scene, xy, heading, cam):
            sensors.frames_of(shot, scene, cam)
        encode_png(region_map.render(uav_xy=(tx, ty), ugv_xy=xy, ugv_yaw_rad=heading))

    times: dict[tuple[str, str], list[float]] = {}
    for scene in scenes.values():  # warm-up
        uav_obs(scene)
        six_obs(scene, *anchors[0])
    for _ in range(repeats):
        for look, scene in scenes.items():
            for a_xy, heading in anchors:
                times.setdefault((look, "six_obs"), []).append(_cpu(lambda s=scene, p=a_xy, h=heading: six_obs(s, p, h)))
                times.setdefault((look, "six"), []).append(
                    _cpu(lambda s=scene, p=a_xy, h=heading: sensors.six_views(s, p, h, cam)))
            times.setdefault((look, "uav_obs"), []).append(_cpu(lambda s=scene: uav_obs(s)))
            times.setdefault((look, "uav"), []).append(_cpu(lambda s=scene: sensors.nadir(s, (tx, ty), 80.0, cam)))
    print(f"town {town.town_id}: {len(town.layout.parked)} parked vehicles + target and {len(spec.distractors)} "
          f"look-alikes; medians of {repeats} rounds x {len(anchors)} anchors, CPU time of this process")
    rows = (("uav_obs", f"UAV observation {cam.nadir_px}px", 1.6), ("six_obs", f"six-view observation {cam.ground_px}px", 1.6),
            ("uav", "  UAV render alone", None), ("six", "  six renders alone", None))
    for key, what, goal in rows:
        flat, rich = (statistics.median(times[(look, key)]) * 1000 for look in LOOKS)
        verdict = "" if goal is None else f"  (goal <= {goal}: {'met' if rich / flat <= goal else 'NOT met'})"
        print(f"{what:34s} flat {flat:7.1f} ms   rich {rich:7.1f} ms   {rich / flat:.2f}x{verdict}")
        if goal is not None:
            figures.add(f"{what.strip()}: rich vs flat look", rich / flat, f"{rich / flat:.2f}x ({rich:.0f} vs {flat:.0f} ms CPU)",
                        f"<= {goal}x", rich / flat <= goal)
    bodies = {look: pb.getNumBodies(physicsClientId=s.client) for look, s in scenes.items()}
    city = scenes["rich"]._city
    print(f"{'scene build':34s} flat {build_s['flat'] * 1000:7.0f} ms   rich {build_s['rich'] * 1000:7.0f} ms   "
          f"{build_s['rich'] / build_s['flat']:.2f}x")
    print(f"{'bodies (incl. parked vehicles)':34s} flat {bodies['flat']:7d}      rich {bodies['rich']:7d}"
          f"      rich static city: {city.triangles if city else 0} triangles")
    for scene in scenes.values():
        scene.close()


PROBE = """
import json, resource, sys, time
from pathlib import Path
from agos.world.sim.scene import Scene
from agos.world.towns.asset import load_town
town = load_town(Path(sys.argv[1]))
start = time.perf_counter()
scene = Scene(town.layout, look=sys.argv[2])
build_s = time.perf_counter() - start
print(json.dumps([resource.getrusage(resource.RUSAGE_SELF).ru_maxrss, build_s]))
"""


def memory(path: Path, figures: Figures, runs: int = 3) -> None:
    """A world worker's peak RSS: a fresh process that loads the frozen asset (as a worker does from
    its cache) and builds the scene; median over ``runs`` processes a look, alternating (peak RSS
    varies by tens of MB from one process to the next)."""
    import tempfile

    from agos.world.towns.asset import freeze, save_town
    from agos.world.towns.imported import imported_layout

    samples: dict[str, list[tuple[int, float]]] = {look: [] for look in LOOKS}
    with tempfile.TemporaryDirectory() as tmp:
        asset = save_town(freeze(imported_layout(path)), Path(tmp) / path.stem)
        for _ in range(runs):
            for look in LOOKS:
                out = subprocess.run([sys.executable, "-c", PROBE, str(asset), look], capture_output=True, text=True,
                                     check=True)
                samples[look].append(tuple(json.loads(out.stdout.strip().splitlines()[-1])))  # type: ignore[arg-type]
    peak = {look: statistics.median(s[0] for s in samples[look]) for look in LOOKS}
    build = {look: statistics.median(s[1] for s in samples[look]) for look in LOOKS}
    print(f"{path.stem} world process: peak RSS flat {peak['flat'] / 1024:6.0f} MB   rich {peak['rich'] / 1024:6.0f} MB   "
          f"{peak['rich'] / peak['flat']:.2f}x (goal <= 1.5: {'met' if peak['rich'] / peak['flat'] <= 1.5 else 'NOT met'});"
          f" scene build flat {build['flat']:.2f} s, rich {build['rich']:.2f} s")
    ratio = peak["rich"] / peak["flat"]
    figures.add(f"{path.stem} world process peak RSS: rich vs flat", ratio,
                f"{ratio:.2f}x ({peak['rich'] / 1024:.0f} vs {peak['flat'] / 1024:.0f} MB)", "<= 1.5x", ratio <= 1.5)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--town", default="grid-s7")
    parser.add_argument("--repeats", type=int, default=15)
    parser.add_argument("--carla", type=Path, default=Path(__file__).resolve().parents[2] / "shared/maps/carla/Town04.xodr")
    parser.add_argument("--quick", action="store_true", help="3 rounds, one probe process a look")
    parser.add_argument("--json", action="store_true", help="also print each figure as a BENCH-FIGURE line")
    parser.add_argument("--renderer", choices=["tiny", "egl"], default="tiny",
                        help="egl: EGL against TinyRenderer on the same scenes, instead of rich against flat")
    parser.add_argument("--look", choices=LOOKS, action="append",
                        help="with --renderer egl: the look(s) to measure (default both)")
    args = parser.parse_args()
    figures = Figures(args.json)
    if args.renderer == "egl":
        renderer_costs(open_town(args.town), 3 if args.quick else args.repeats, tuple(args.look or LOOKS), figures)
        return
    observation_costs(open_town(args.town), 3 if args.quick else args.repeats, figures)
    if args.carla.exists():
        memory(args.carla, figures, runs=1 if args.quick else 3)
    else:
        print(f"skipped the memory probe: {args.carla} not found")


if __name__ == "__main__":
    main()
