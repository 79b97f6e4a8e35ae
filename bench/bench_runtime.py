"""Runtime benchmarks (issue 5); every figure is a ratio against a baseline from the same run.

1. Decision round trip: the world encodes an observation with real encoded images, an agent
   service (a separate process, zero-latency stand-in policy) decodes it and answers, the world
   decodes the action — against a raw zenoh ping-pong of the same bytes through the same router.
   Goal <= 1.3x.
2. A slow observer: the same round trip while a client subscribed to ``agos/**`` spends 20 ms in
   every sample callback. Goal: within 10 % of the round trip without it.
3. Agent concurrency: 32 concurrent episodes against one agent service with a fixed 200 ms
   stand-in policy: decisions per second against the ideal 32 / 0.2 s = 160. Goal >= 90 %.
4. Throughput: episodes per minute with 2 world workers against 1 on this machine (``agos eval``
   on the same episodes, heuristic agents). Goal >= 1.8x on 2 cores.

    .venv/bin/python bench/bench_runtime.py [--skip-throughput]
"""

from __future__ import annotations

import argparse
import contextlib
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

from agos.runtime import keys
from agos.runtime.bus import Inbox, ZenohBus
from agos.runtime.codec import decode, encode
from agos.runtime.launcher import free_port, wait_listening
from agos.runtime.schemas import Action, Observation

AGOS = [sys.executable, "-m", "agos.runtime.cli"]
ECHO = """
import sys, time, zenoh
from agos.runtime.bus import zenoh_config
s = zenoh.open(zenoh_config(connect=[sys.argv[1]]))
pub = s.declare_publisher("bench/pong", congestion_control=zenoh.CongestionControl.BLOCK, reliability=zenoh.Reliability.RELIABLE)
sub = s.declare_subscriber("bench/ping", lambda sample: pub.put(sample.payload))
while True:
    time.sleep(1)
"""
SLOW_OBSERVER = """
import sys, time
from agos.runtime.observer import Observer
Observer(sys.argv[1], lambda key, payload: time.sleep(0.02))  # 20 ms of work per sample
while True:
    time.sleep(1)
"""
CALLBACK_OBSERVER = """
import sys, time, zenoh
from agos.runtime.bus import zenoh_config
s = zenoh.open(zenoh_config(connect=[sys.argv[1]]))
sub = s.declare_subscriber("agos/**", lambda sample: time.sleep(0.02))  # the anti-pattern
while True:
    time.sleep(1)
"""


def sample_observation() -> Observation:
    """A real UAV observation (rendered, encoded) from the grid town."""
    from agos.agents.inprocess import InProcessAgents
    from agos.world.asset import open_town
    from agos.world.episode import EpisodeRunner
    from agos.world.episodes import sample_episode
    from agos.world.scene import Scene

    town = open_town("grid-s7")
    scene = Scene(town.layout)
    spec = sample_episode(town, scene, "mid", 0, seed=1)
    captured: list[Observation] = []

    class Capture(InProcessAgents):
        def decide(self, observations):
            captured.extend(o for o in observations.values() if o.role == "uav")
            raise StopIteration

    with contextlib.suppress(StopIteration):
        EpisodeRunner(scene, town, spec, run_id="bench", worker_id="bench").run(Capture({}))
    scene.close()
    return captured[0].model_copy(update={"run_id": "bench", "episode_id": "e0"})


def round_trips(bus: ZenohBus, obs: Observation, n: int) -> list[float]:
    inbox = Inbox()
    handle = bus.subscribe(keys.act("bench", "e0", "uav"), inbox)
    key = keys.obs("bench", "e0", "uav")
    bus.wait_for_subscriber(key, 10.0)
    times = []
    for k in range(n):
        start = time.perf_counter()
        bus.publish(key, encode(obs.model_copy(update={"decision_index": k + 1})))
        while True:
            sample = inbox.get(5.0)
            assert sample is not None, "no action from the agent service"
            action = decode(sample.payload)
            if isinstance(action, Action) and action.decision_index == k + 1:
                break
        times.append(time.perf_counter() - start)
    bus.unsubscribe(handle)
    return times


def ping_pongs(bus: ZenohBus, payload: bytes, n: int) -> list[float]:
    inbox = Inbox()
    handle = bus.subscribe("bench/pong", inbox)
    bus.wait_for_subscriber("bench/ping", 10.0)
    times = []
    for _ in range(n):
        start = time.perf_counter()
        bus.publish("bench/ping", payload)
        assert inbox.get(5.0) is not None
        times.append(time.perf_counter() - start)
    bus.unsubscribe(handle)
    return times


def interleaved(a, b, rounds: int = 10, n: int = 20) -> tuple[float, float]:
    """Medians of two measurements taken in alternating batches (drift hits both alike)."""
    ta, tb = [], []
    for _ in range(rounds):
        ta += a(n)
        tb += b(n)
    return statistics.median(ta), statistics.median(tb)


def concurrency_rate(endpoint: str, obs: Observation, episodes: int = 32, seconds: float = 8.0) -> float:
    bus = ZenohBus.connect(endpoint)
    stop = time.monotonic() + seconds
    counts = [0] * episodes
    small = obs.model_copy(update={"images": obs.images[:1], "references": obs.references[:1]})

    def loop(k: int) -> None:
        inbox = Inbox()
        bus.subscribe(keys.act("bench", f"c{k}", "uav"), inbox)
        key = keys.obs("bench", f"c{k}", "uav")
        bus.wait_for_subscriber(key, 10.0)
        index = 0
        while time.monotonic() < stop:
            index += 1
            bus.publish(key, encode(small.model_copy(update={"episode_id": f"c{k}", "decision_index": index})))
            while time.monotonic() < stop + 2:
                sample = inbox.get(1.0)
                if sample is not None and decode(sample.payload).decision_index == index:
                    counts[k] += 1
                    break

    threads = [threading.Thread(target=loop, args=(k,)) for k in range(episodes)]
    start = time.monotonic()
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    elapsed = time.monotonic() - start
    bus.close()
    return sum(counts) / elapsed


def throughput(workers: int, episodes: Path, tmp: Path) -> float:
    """Episodes per minute reported by `agos eval` (first lease to last stored episode)."""
    run_dir = tmp / f"w{workers}"
    out = subprocess.run([*AGOS, "eval", "--split", str(episodes), "--workers", str(workers), "--run-dir", str(run_dir)],
                         check=True, capture_output=True, text=True, timeout=900, env={**__import__("os").environ,
                                                                                         "COLUMNS": "200"}).stdout
    line = next(x for x in out.splitlines() if x.startswith("throughput:"))
    return float(line.split()[1])


class Cluster:
    """A fresh router plus the given agos processes, torn down on exit (one per phase, so one
    measurement's leftovers cannot skew the next)."""

    def __init__(self, *commands: list[str]) -> None:
        port = free_port(17900)
        self.endpoint = f"tcp/127.0.0.1:{port}"
        self.procs = [subprocess.Popen([*AGOS, "router", "--listen", self.endpoint], stderr=subprocess.DEVNULL)]
        assert wait_listening("127.0.0.1", port, 15)
        for cmd in commands:
            self.procs.append(subprocess.Popen([arg.replace("{EP}", self.endpoint) for arg in cmd], stderr=subprocess.DEVNULL))
        time.sleep(1.5)

    def __enter__(self) -> Cluster:
        return self

    def __exit__(self, *exc) -> None:
        for p in self.procs:
            p.terminate()
        for p in self.procs:
            p.wait()


def agent(policy: str, concurrency: int) -> list[str]:
    return [*AGOS, "agent", "--role", "uav", "--policy", policy, "--connect", "{EP}", "--run", "bench",
            "--concurrency", str(concurrency)]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--skip-throughput", action="store_true")
    parser.add_argument("--episodes", type=int, default=6, help="episodes per difficulty for the throughput run")
    args = parser.parse_args()
    obs = sample_observation()
    payload = encode(obs)

    with Cluster([sys.executable, "-c", ECHO, "{EP}"], agent("standin-0ms", 64)) as cluster:
        bus = ZenohBus.connect(cluster.endpoint)
        t_ping, t_rt = interleaved(lambda n: ping_pongs(bus, payload, n), lambda n: round_trips(bus, obs, n))
        print(f"decision round trip      {1000 * t_rt:7.2f} ms vs raw zenoh ping-pong of the same {len(payload) / 1024:.0f} KB "
              f"{1000 * t_ping:.2f} ms: {t_rt / t_ping:.2f}x (goal <= 1.3: {'met' if t_rt / t_ping <= 1.3 else 'NOT met'})")
        bus.close()

    for label, script in (("agos Observer, 20 ms/sample", SLOW_OBSERVER), ("callback sleeping 20 ms", CALLBACK_OBSERVER)):
        with Cluster(agent("standin-0ms", 64)) as cluster:
            bus = ZenohBus.connect(cluster.endpoint)
            without, with_ = [], []
            for _ in range(4):  # observer off and on in alternation
                without += round_trips(bus, obs, 40)
                observer = subprocess.Popen([sys.executable, "-c", script, cluster.endpoint])
                time.sleep(1.0)
                with_ += round_trips(bus, obs, 40)
                observer.terminate()
                observer.wait()
                time.sleep(0.5)
            bus.close()
        t_off, t_on = statistics.median(without), statistics.median(with_)
        change = t_on / t_off - 1
        goal = f"(goal within 10 %: {'met' if abs(change) <= 0.10 else 'NOT met'})" if "agos" in label else "(for contrast)"
        print(f"observer: {label:28s} {1000 * t_on:5.2f} ms vs {1000 * t_off:.2f} ms without: {100 * change:+.1f} % {goal}")

    with Cluster(agent("standin-200ms", 32)) as cluster:
        rate = concurrency_rate(cluster.endpoint, obs)
    print(f"32 episodes, 200 ms agent {rate:7.1f} decisions/s vs ideal 160.0: {100 * rate / 160:.0f} % "
          f"(goal >= 90 %: {'met' if rate >= 144 else 'NOT met'})")

    if not args.skip_throughput:
        with tempfile.TemporaryDirectory() as tmp:
            eps = Path(tmp) / "eps.jsonl"
            subprocess.run([*AGOS, "episodes", "sample", "--town", "grid-s7", "--per-difficulty", str(args.episodes),
                            "--out", str(eps)], check=True, capture_output=True)
            r1 = throughput(1, eps, Path(tmp))
            r2 = throughput(2, eps, Path(tmp))
            print(f"episodes per minute      {r2:7.1f} with 2 workers vs {r1:.1f} with 1: {r2 / r1:.2f}x "
                  f"(goal >= 1.8: {'met' if r2 / r1 >= 1.8 else 'NOT met'}; first lease to last stored episode)")


if __name__ == "__main__":
    main()
