"""Runtime benchmarks (issue 5); every figure is a ratio against a baseline from the same run.

1. Decision round trip (``--only breakdown``: the same with timers inside both processes, to see
   where the time beyond the ping-pong goes): the world's own code (``BusDecisionSource.decide`` on a
   ``WorkerSlot``) encodes an observation with real encoded images, an agent service (a separate
   process, zero-latency stand-in policy, subscribed to the slot once its token appeared) decodes it
   and answers, the world decodes the answer into the ``Action`` it applies — against a raw zenoh
   ping-pong of the same bytes through the same router, on a slot's ``obs``/``act`` keys too. Goal <= 1.3x.
2. Slow observers: world ticks (the decision, then the step event and coordination state on the
   control and visualisation keys, a frame offered to viewers) for a fixed time with and without
   an observer that spends 20 ms on every sample: the agos Observer (ring buffer, visualisation
   stream), a callback sleeping on the visualisation stream (DROP: the world must not notice; goal
   within 10 %), and, for contrast, a callback sleeping on ``agos/**`` (the control stream is
   BLOCK: that observer back-pressures the world). A phase's figure is its mean tick (a median
   would hide the ticks that wait once queues are full); each on-phase is compared with the
   off-phase before it, and the median of those ratios printed. Then the QoS itself: the longest
   single ``put`` of step-sized samples to a subscriber that sleeps 20 ms per sample, with the
   visualisation QoS (DROP, express, low priority) against the same with BLOCK.
3. Agent concurrency: 32 concurrent episodes against one agent service with a fixed 200 ms
   stand-in policy: decisions per second against the ideal 32 / 0.2 s = 160. Goal >= 90 %.
4. Throughput: episodes per minute with 2 world workers against 1 on this machine (``agos eval``
   on the same episodes, heuristic agents). Goal >= 1.8x on 2 cores.

    .venv/bin/python bench/bench_runtime.py [--skip-throughput] [--quick] [--json]

``--quick`` (``make bench``): the round trip and agent concurrency only (about 30 s). ``--json``:
also one machine-readable line per figure (bench/figures.py).
"""

from __future__ import annotations

import argparse
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import msgspec
from figures import Figures

from agos.deploy.run.launcher import free_port, wait_listening
from agos.runtime import keys
from agos.runtime.bus import Inbox, ZenohBus
from agos.runtime.codec import decode, encode
from agos.runtime.process import StopFlag
from agos.runtime.schemas import Observation, StepEvent
from agos.runtime.viz import FrameStream
from agos.world.sim.worker import BusDecisionSource, BusSink, WorkerSlot

AGOS = [sys.executable, "-m", "agos.deploy.cli"]
RUN = "bench"
RAW_SLOT = "raw"
"""The raw ping-pong's keys are a slot's observation and action keys (``agos/bench/slot/raw/obs/uav`` and
``.../act/uav``), of the same shape and depth as the world's: no slot token, so no agent service
subscribes to them."""
ECHO = """
import sys, time, zenoh
from agos.runtime import keys
from agos.runtime.bus import zenoh_config
s = zenoh.open(zenoh_config(connect=[sys.argv[1]]))
run, slot = sys.argv[2], sys.argv[3]
pub = s.declare_publisher(keys.act(run, slot, "uav"), congestion_control=zenoh.CongestionControl.BLOCK,
                          reliability=zenoh.Reliability.RELIABLE)
sub = s.declare_subscriber(keys.obs(run, slot, "uav"), lambda sample: pub.put(sample.payload))
while True:
    time.sleep(1)
"""
OBSERVER = """
import sys, time, zenoh
from agos.runtime import keys
from agos.runtime.bus import zenoh_config
from agos.runtime.observer import Observer
endpoint, kind = sys.argv[1], sys.argv[2]
session = zenoh.open(zenoh_config(connect=[endpoint]))
current = None
for line in sys.stdin:  # "on" / "off", answered with "ok" once done
    if line.strip() == "on":
        if kind == "observer":  # the agos Observer: 20 ms of work per sample, off its ring buffer
            current = Observer(endpoint, lambda key, payload: time.sleep(0.02))
        else:  # blocks its zenoh callback for 20 ms per sample
            current = session.declare_subscriber(keys.viz_all() if kind == "viz" else "agos/**",
                                                 lambda sample: time.sleep(0.02))
    elif current is not None:
        current.close() if kind == "observer" else current.undeclare()
        current = None
    print("ok", flush=True)
"""
TIMED_AGENT = """
# The agent service (standin-0ms) with timers around its stages; medians written to argv[2].
import asyncio, json, statistics, sys
sys.path.insert(0, sys.argv[3])
from bench_runtime import timed
from agos.agents import agent_service
from agos.agents.registry import make_policy
from agos.runtime.bus import ZenohBus, zenoh_config
from agos.runtime.process import StopFlag
spent = {}
policy = make_policy("standin-0ms", "uav")
agent_service._Dispatch.take = timed(agent_service._Dispatch.take, spent, "agent: receive to answer sent")
agent_service.decode = timed(agent_service.decode, spent, "agent: decode")
policy.act = timed(policy.act, spent, "agent: policy")
agent_service._stamped = timed(agent_service._stamped, spent, "agent: encode and check action")
ZenohBus.publish = timed(ZenohBus.publish, spent, "agent: publish action")
async def main():
    bus = ZenohBus(zenoh_config(connect=[sys.argv[1]]))
    serving = asyncio.ensure_future(agent_service.serve_async(bus, policy, "bench", StopFlag(), concurrency=64))
    while True:
        await asyncio.sleep(0.5)
        with open(sys.argv[2], "w") as out:
            json.dump({k: statistics.median(v) for k, v in spent.items() if v}, out)
asyncio.run(main())
"""
SLEEPER = """
import sys, time, zenoh
from agos.runtime.bus import zenoh_config
s = zenoh.open(zenoh_config(connect=[sys.argv[1]]))
sub = s.declare_subscriber(sys.argv[2], lambda sample: time.sleep(0.02))
while True:
    time.sleep(1)
"""


def sample_observation() -> Observation:
    """A real UAV observation (rendered, encoded) from the grid town: an episode's first."""
    from agos.env import Env
    from agos.runtime.episode_config import EpisodeConfig
    from agos.world.episodes.sampling import sample_episode
    from agos.world.sim.scene import Scene
    from agos.world.towns.asset import open_town

    town = open_town("grid-s7")
    with Scene(town.layout, look="flat") as scene:
        spec = sample_episode(town, scene, "mid", 0, seed=1)
        with Env(spec, EpisodeConfig(look="flat"), run_id="bench", worker_id="bench", scene=scene, town=town) as env:
            first = env.reset()["uav"]
    return msgspec.structs.replace(first, run_id="bench", episode_id="e0")


class World:
    """One episode's decisions made by the world worker's own code (world/sim/worker.py): the worker's
    slot (declared once, as for a worker's session), the episode's decision source on it, its sink."""

    def __init__(self, bus: ZenohBus, obs: Observation, episode: str = "e0", worker: str = "w0") -> None:
        self.obs = msgspec.structs.replace(obs, episode_id=episode)
        self.frames = FrameStream(bus)
        self.slot = WorkerSlot(bus, RUN, worker)
        self.source = BusDecisionSource(self.slot, episode, timeout_s=5.0, stop=StopFlag(), frames=self.frames)
        self.sink = BusSink(bus, RUN, worker)
        self.index = 0

    def _next(self) -> Observation:
        # As in world/sim/engine.py: a new Observation each decision, its searchable area a new list
        # of the episode's same Waypoint objects (built once per episode).
        self.index += 1
        return msgspec.structs.replace(self.obs, decision_index=self.index,
                                       active_uav_waypoints=list(self.obs.active_uav_waypoints))

    def round_trips(self, n: int) -> list[float]:
        """The whole decision as the world lives it: encode, publish, wait for the answer and decode
        it into the ``Action`` struct that ``EpisodeRunner._apply`` takes as it is (no conversion)."""
        times = []
        for _ in range(n):
            obs = self._next()
            start = time.perf_counter()
            action = self.source.decide({"uav": obs})["uav"]
            times.append(time.perf_counter() - start)
            assert action is not None, "no action from the agent service"
        return times

    def ticks(self, seconds: float) -> tuple[float, float]:
        """Decision ticks for ``seconds``: the decision, then the step event and coordination state
        (control and visualisation keys) as after every decision. Returns the mean wall time of a
        tick and of its decision (a median would hide the ticks that wait once queues are full)."""
        count, decisions, start = 0, 0.0, time.perf_counter()
        while time.perf_counter() - start < seconds:
            obs = self._next()
            t0 = time.perf_counter()
            action = self.source.decide({"uav": obs})["uav"]
            decisions += time.perf_counter() - t0
            self.sink.step(StepEvent(run_id=RUN, episode_id=obs.episode_id, role="uav",
                                     decision_index=obs.decision_index, episode_step=obs.decision_index,
                                     sim_time_s=obs.sim_time_s, requested=action, applied="WAIT", pose_after=obs.pose))
            self.sink.coordination(obs.coordination, {"uav": obs.coordination, "ugv": obs.coordination})
            count += 1
        return (time.perf_counter() - start) / count, decisions / count

    def close(self) -> None:
        self.source.close()
        self.slot.close()
        self.frames.close()


class PingPong:
    """The raw zenoh ping-pong: ``payload`` to the echo process and its copy back, on keys of the
    world's shape (``RAW_SLOT``). Subscribed once for the whole measurement, so no (un)declaration's
    route update runs into a timed batch."""

    def __init__(self, bus: ZenohBus, payload: bytes) -> None:
        self.bus, self.payload, self.inbox = bus, payload, Inbox()
        self.ping = keys.obs(RUN, RAW_SLOT, "uav")
        self.handle = bus.subscribe(keys.act(RUN, RAW_SLOT, "uav"), self.inbox)
        bus.wait_for_subscriber(self.ping, 10.0)

    def round_trips(self, n: int) -> list[float]:
        times = []
        for _ in range(n):
            start = time.perf_counter()
            self.bus.publish(self.ping, self.payload)
            assert self.inbox.get(5.0) is not None
            times.append(time.perf_counter() - start)
        return times

    def close(self) -> None:
        self.bus.unsubscribe(self.handle)


def paired_ratios(a, b, rounds: int = 40, n: int = 20) -> tuple[float, float, list[float]]:
    """Medians of two measurements taken in alternating batches (drift hits both alike; 800 of each,
    over a few seconds, so that one noisy second on a shared machine does not decide), and the
    ratio b/a of each round's medians (a round is 2 x ``n`` calls, tens of milliseconds): a slow
    spell of the machine moves a round's pair together, so the ratios' median and quartiles say
    more than the ratio of the overall medians. Every other round runs ``b`` first, so neither side
    always pays for following the other (caches, zenoh's own work left from the batch before).
    One unmeasured batch of each first: the first samples on a new route are slower."""
    a(n), b(n)
    ta, tb, ratios = [], [], []
    for i in range(rounds):
        if i % 2:
            rb, ra = b(n), a(n)
        else:
            ra, rb = a(n), b(n)
        ta += ra
        tb += rb
        ratios.append(statistics.median(rb) / statistics.median(ra))
    return statistics.median(ta), statistics.median(tb), ratios


STUCK_N, STUCK_BYTES = 8000, 1300


def worst_put(bus: ZenohBus, key: str, *, drop: bool) -> float:
    """The longest single put of ``STUCK_N`` step-sized samples, 0.5 ms apart, to a subscriber
    that sleeps 20 ms per sample (it takes 50 a second): through ``publish_viz`` (DROP), or with
    the same QoS but congestion control BLOCK."""
    import zenoh

    put = (lambda payload: bus.publish_viz(key, payload)) if drop else bus.session.declare_publisher(
        key, congestion_control=zenoh.CongestionControl.BLOCK, express=True, priority=zenoh.Priority.DATA_LOW).put
    deadline = time.monotonic() + 10.0
    while not bus.watched(key) and time.monotonic() < deadline:
        time.sleep(0.05)
    payload, worst = b"x" * STUCK_BYTES, 0.0
    for _ in range(STUCK_N):
        start = time.perf_counter()
        put(payload)
        worst = max(worst, time.perf_counter() - start)
        time.sleep(0.0005)
    bus.close()
    return worst


def concurrency_rate(endpoint: str, obs: Observation, episodes: int = 32, seconds: float = 8.0) -> float:
    with ZenohBus.connect(endpoint) as bus:
        stop = time.monotonic() + seconds
        counts = [0] * episodes
        small = msgspec.structs.replace(obs, images=obs.images[:1], references=obs.references[:1])

        def loop(k: int) -> None:
            slot = WorkerSlot(bus, RUN, f"c{k}")  # as world worker c<k>: its slot, declared for its session
            if slot.agents.wait_for(["uav"], 10.0, StopFlag()):
                raise RuntimeError(f"no agent service subscribed to slot c{k}")
            key = slot.obs_keys["uav"]
            index = 0
            while time.monotonic() < stop:
                index += 1
                bus.publish(key, encode(msgspec.structs.replace(small, episode_id=f"e{k}", decision_index=index)))
                while time.monotonic() < stop + 2:
                    sample = slot.actions.get(1.0)
                    if sample is not None and decode(sample.payload).decision_index == index:
                        counts[k] += 1
                        break
            slot.close()

        threads = [threading.Thread(target=loop, args=(k,)) for k in range(episodes)]
        start = time.monotonic()
        for t in threads:
            t.start()
        for t in threads:
            t.join()
        elapsed = time.monotonic() - start
    unanswered = [f"c{k}" for k, count in enumerate(counts) if count == 0]
    if unanswered:  # an assert in a loop thread would only be printed
        raise RuntimeError(f"episodes never answered: {', '.join(unanswered)}")
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


def toggle(observer: subprocess.Popen, world: World, state: str) -> None:
    """Subscribe or unsubscribe the observer process, keeping the world busy meanwhile."""
    observer.stdin.write(state + "\n")
    observer.stdin.flush()
    observer.stdout.readline()
    world.ticks(0.3)  # while the (un)subscription reaches the world; not measured


PARTS = ("roundtrip", "breakdown", "observer", "qos", "concurrency", "throughput")


def echo() -> list[str]:
    return [sys.executable, "-c", ECHO, "{EP}", RUN, RAW_SLOT]


def agent(policy: str, concurrency: int) -> list[str]:
    return [*AGOS, "agent", "--role", "uav", "--policy", policy, "--connect", "{EP}", "--run", RUN,
            "--concurrency", str(concurrency)]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--skip-throughput", action="store_true")
    parser.add_argument("--only", choices=PARTS, action="append", help="run only these parts (repeatable)")
    parser.add_argument("--episodes", type=int, default=6, help="episodes per difficulty for the throughput run")
    parser.add_argument("--quick", action="store_true", help="the round trip and agent concurrency only")
    parser.add_argument("--json", action="store_true", help="also print each figure as a BENCH-FIGURE line")
    args = parser.parse_args()
    parts = set(args.only or (("roundtrip", "concurrency") if args.quick else PARTS))
    parts -= {"throughput"} if args.skip_throughput else set()
    figures = Figures(args.json)
    obs = sample_observation()
    payload = encode(obs)

    if "roundtrip" in parts:
        round_trip(obs, payload, figures)
    if "breakdown" in parts:
        round_trip_breakdown(obs, payload)
    if "observer" in parts:
        observers(obs, figures)
    if "qos" in parts:
        stuck_subscriber()
    if "concurrency" in parts:
        with Cluster(agent("standin-200ms", 32)) as cluster:
            rate = concurrency_rate(cluster.endpoint, obs)
        print(f"32 episodes, 200 ms agent {rate:7.1f} decisions/s vs ideal 160.0: {100 * rate / 160:.0f} % "
              f"(goal >= 90 %: {'met' if rate >= 144 else 'NOT met'})")
        figures.add("agent concurrency: 32 episodes x 200 ms vs ideal", rate / 160,
                    f"{100 * rate / 160:.0f} % ({rate:.1f} of 160 decisions/s)", ">= 90 %", rate >= 144)
    if "throughput" in parts:
        with tempfile.TemporaryDirectory() as tmp:
            eps = Path(tmp) / "eps.jsonl"
            subprocess.run([*AGOS, "episodes", "sample", "--town", "grid-s7", "--per-difficulty", str(args.episodes),
                            "--out", str(eps)], check=True, capture_output=True)
            r1 = throughput(1, eps, Path(tmp))
            r2 = throughput(2, eps, Path(tmp))
            print(f"episodes per minute      {r2:7.1f} with 2 workers vs {r1:.1f} with 1: {r2 / r1:.2f}x "
                  f"(goal >= 1.8: {'met' if r2 / r1 >= 1.8 else 'NOT met'}; first lease to last stored episode)")
            figures.add("episodes per minute, 2 workers vs 1", r2 / r1, f"{r2 / r1:.2f}x ({r2:.1f} vs {r1:.1f})", ">= 1.8x",
                        r2 / r1 >= 1.8)


def round_trip(obs: Observation, payload: bytes, figures: Figures) -> None:
    with (Cluster(echo(), agent("standin-0ms", 64)) as cluster,
          ZenohBus.connect(cluster.endpoint) as bus):
        world, ping = World(bus, obs), PingPong(bus, payload)
        t_ping, t_rt, ratios = paired_ratios(ping.round_trips, world.round_trips)
        ratio, (q1, _, q3) = statistics.median(ratios), statistics.quantiles(ratios, n=4)
        print(f"decision round trip      {1000 * t_rt:7.2f} ms vs raw zenoh ping-pong of the same {len(payload) / 1024:.0f} KB "
              f"{1000 * t_ping:.2f} ms: {ratio:.2f}x (median of {len(ratios)} paired rounds, middle half {q1:.2f}-{q3:.2f}; "
              f"goal <= 1.3: {'met' if ratio <= 1.3 else 'NOT met'})")
        figures.add("decision round trip vs raw zenoh ping-pong", ratio,
                    f"{ratio:.2f}x ({1000 * t_rt:.2f} vs {1000 * t_ping:.2f} ms; middle half {q1:.2f}-{q3:.2f})", "<= 1.3x",
                    ratio <= 1.3)
        ping.close()
        world.close()


def timed(function, spent: dict[str, list[float]], label: str):
    """``function`` that also appends each call's duration to ``spent[label]``."""
    durations = spent.setdefault(label, [])

    def wrapper(*args, **kw):
        start = time.perf_counter()
        try:
            return function(*args, **kw)
        finally:
            durations.append(time.perf_counter() - start)

    return wrapper


def round_trip_breakdown(obs: Observation, payload: bytes) -> None:
    """The same round trip with timers inside both processes (they slow it a little): where the
    time beyond the raw ping-pong goes, measured in situ, not in a micro-benchmark."""
    import json

    from agos.world.sim import worker

    spent: dict[str, list[float]] = {}
    original_encode, original_decode = worker.encode_into, worker.decode_as
    worker.encode_into = timed(original_encode, spent, "world: encode observation")
    worker.decode_as = timed(original_decode, spent, "world: decode action")
    try:
        with tempfile.TemporaryDirectory() as tmp:
            report = Path(tmp) / "agent.json"
            timed_agent = [sys.executable, "-c", TIMED_AGENT, "{EP}", str(report), str(Path(__file__).parent)]
            with Cluster(echo(), timed_agent) as cluster, ZenohBus.connect(cluster.endpoint) as bus:
                world, ping = World(bus, obs), PingPong(bus, payload)
                t_ping, t_rt, _ = paired_ratios(ping.round_trips, world.round_trips)
                time.sleep(1.0)  # the agent writes its medians every 0.5 s
                ping.close()
                world.close()
            agent_spent = json.loads(report.read_text())
    finally:
        worker.encode_into, worker.decode_as = original_encode, original_decode
    print(f"round trip with timers {1000 * t_rt:.2f} ms vs raw ping-pong {1000 * t_ping:.2f} ms: "
          f"{1e6 * (t_rt - t_ping):.0f} us more; medians per decision, in situ:")
    for label, value in [*((k, statistics.median(v)) for k, v in spent.items()), *agent_spent.items()]:
        print(f"  {label:34s} {1e6 * value:6.0f} us")


def observers(obs: Observation, figures: Figures) -> None:
    for kind, label in (("observer", "agos Observer, 20 ms/sample"), ("viz", "viz callback sleeping 20 ms"),
                        ("all", "agos/** callback sleeping 20 ms")):
        with Cluster(agent("standin-0ms", 64)) as cluster, ZenohBus.connect(cluster.endpoint) as bus:
            world = World(bus, obs)
            world.round_trips(20)  # warm-up
            observer = subprocess.Popen([sys.executable, "-c", OBSERVER, cluster.endpoint, kind], text=True,
                                        stdin=subprocess.PIPE, stdout=subprocess.PIPE)

            without, with_ = [], []
            # Observer off and on in alternation. Blocking on agos/** wedges the control stream
            # (BLOCK) for long after, so that contrast gets one round, last.
            for _ in range(10 if kind != "all" else 1):
                without.append(world.ticks(0.5))
                toggle(observer, world, "on")
                with_.append(world.ticks(0.5))
                toggle(observer, world, "off")
            observer.kill()
            observer.wait()
            world.close()
        # Each on-phase against the off-phase just before it (drift hits both alike); the median
        # of those ratios, for the decision and for the whole tick.
        decision = statistics.median(on[1] / off[1] for off, on in zip(without, with_, strict=True))
        tick = statistics.median(on[0] / off[0] for off, on in zip(without, with_, strict=True))
        dec_on, dec_off = statistics.median(x[1] for x in with_), statistics.median(x[1] for x in without)
        goal = (f"(goal within 10 %: {'met' if abs(decision - 1) <= 0.10 else 'NOT met'})" if kind != "all"
                else "(for contrast: control traffic is BLOCK)")
        print(f"observer: {label:32s} decision {1000 * dec_on:6.2f} ms vs {1000 * dec_off:.2f} ms without: "
              f"{decision:.2f}x; whole tick {tick:.2f}x {goal}")
        if kind != "all":
            figures.add(f"decision with {label} vs without", decision, f"{decision:.2f}x", "within 10 %",
                        abs(decision - 1) <= 0.10)


def stuck_subscriber() -> None:
    worst = {}
    for drop in (True, False):
        key = keys.viz_events("bench", "q")
        with Cluster([sys.executable, "-c", SLEEPER, "{EP}", key]) as cluster:
            worst[drop] = worst_put(ZenohBus.connect(cluster.endpoint), key, drop=drop)
    print(f"stuck viz subscriber, {STUCK_N} puts of {STUCK_BYTES} B: longest put {1000 * worst[True]:.1f} ms with DROP "
          f"(the viz QoS) vs {1000 * worst[False]:.0f} ms with BLOCK")


if __name__ == "__main__":
    main()
