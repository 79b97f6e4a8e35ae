"""What full-resolution recording (``agos record --full``, docs/VIEWING.md) costs the world's decision thread.

Per observation of a real heuristic episode on grid-s7 (UAV nadir view, UGV forward view, UGV six
views): the ``watched()`` check alone when nobody asks, and ``full_frames()`` + ``publish_viz`` (what
``BusDecisionSource.decide`` does) while a subscriber on ``viz/<worker>/full/<role>`` asks, through a
real router on loopback. 200 observations of each kind, back to back (DROP may lose some of those
bursts at the subscriber: the count received is printed).

    .venv/bin/python bench/bench_record.py [--quick] [--json]

No baseline here: the figure ``make bench`` guards is the cost when nobody asks (a flag read,
0.1-0.2 us in docs/VIEWING.md), against 1 us. ``--quick``: 50 observations of each kind.
``--json``: also one machine-readable line per figure (bench/figures.py).
"""

from __future__ import annotations

import argparse
import statistics
import subprocess
import sys
import time

from figures import Figures

from agos.deploy.run.launcher import free_port, wait_listening
from agos.runtime import keys
from agos.runtime.bus import Inbox, ZenohBus
from agos.runtime.codec import encode
from agos.runtime.schemas import Observation
from agos.runtime.viz import full_frames


def observations() -> list[Observation]:
    """Every observation of one heuristic mid episode on grid-s7."""
    from agos import Env
    from agos.agents.registry import make_policy
    from agos.runtime.episode_config import EpisodeConfig
    from agos.world.episodes.sampling import sample_episode
    from agos.world.sim.scene import Scene
    from agos.world.towns.asset import open_town

    town = open_town("grid-s7")
    with Scene(town.layout, look="flat") as scene:
        spec = sample_episode(town, scene, "mid", 0, seed=1)
        seen: list[Observation] = []
        policies = {r: make_policy("heuristic", r) for r in ("uav", "ugv")}
        with Env(spec, EpisodeConfig(look="flat"), run_id="bench", scene=scene, town=town) as env:
            env.play(policies, seen=seen)
    return seen


def cost_us(world: ZenohBus, key: str, sample: list[Observation], n: int = 200) -> tuple[float, float]:
    """(median, mean) microseconds of what the world does per observation."""
    times = []
    for k in range(n):
        obs = sample[k % len(sample)]
        start = time.perf_counter()
        if world.watched(key):
            for frame in full_frames(obs):
                world.publish_viz(key, frame)
        times.append(time.perf_counter() - start)
    return statistics.median(times) * 1e6, statistics.mean(times) * 1e6


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true", help="50 observations of each kind (200)")
    parser.add_argument("--json", action="store_true", help="also print each figure as a BENCH-FIGURE line")
    args = parser.parse_args()
    figures, n = Figures(args.json), 50 if args.quick else 200
    off: dict[str, float] = {}
    obs = observations()
    kinds = {"UAV nadir": [o for o in obs if o.role == "uav"],
             "UGV six views": [o for o in obs if o.mode == "stop_6view"],
             "UGV forward": [o for o in obs if o.role == "ugv" and o.mode != "stop_6view"]}
    port = free_port(17900)
    router = subprocess.Popen([sys.executable, "-m", "agos.deploy.cli", "router", "--listen", f"tcp/127.0.0.1:{port}"],
                              stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        assert wait_listening("127.0.0.1", port, 15)
        with ZenohBus.connect(f"tcp/127.0.0.1:{port}") as world:
            key = keys.viz_full("bench", "w0", "uav")
            world.watched(key)
            time.sleep(0.5)
            for name, sample in kinds.items():
                median = cost_us(world, key, sample, n)[0]
                print(f"nobody asks, {name}: median {median:.1f} us per observation")
                off[name] = median
            worst = max(off, key=off.__getitem__)
            figures.add("recording off (nobody asks): per observation, worst kind", off[worst],
                        f"{off[worst]:.2f} us ({worst})", "<= 1 us", off[worst] <= 1.0)
            with ZenohBus.connect(f"tcp/127.0.0.1:{port}") as recorder:
                got = Inbox()
                recorder.subscribe(key, got)
                time.sleep(1.0)
                for name, sample in kinds.items():
                    size = sum(len(encode(f)) for f in full_frames(sample[0]))
                    median, mean = cost_us(world, key, sample, n)
                    print(f"a recorder asks, {name} ({size / 1024:.0f} KiB per observation): median {median:.0f} us, "
                          f"mean {mean:.0f} us per observation")
                time.sleep(1.0)
                print(f"frames received by the subscriber: {len(got.drain())}")
    finally:
        router.terminate()
        router.wait(timeout=10)


if __name__ == "__main__":
    main()
