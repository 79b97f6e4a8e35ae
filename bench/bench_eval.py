"""Evaluation at model speed: the wall time of a real ``agos eval`` against the floors it cannot beat.

A real evaluation is paced by the model. This bench runs a split through the real ``agos eval``
(router, evaluator, two agent services, world workers: the processes ``agos eval`` starts) with the
``standin-<L>ms`` policy, which sleeps L seconds per decision like a remote model and then takes a
plain legal action (agents/standin_policy.py), and prints the wall time from the command's start to its
final table, start-up included, against two floors measured in the same run:

* model floor = max(longest chain × L, total rounds × L / concurrent episodes). A *round* is one
  time the world asks the agents and waits: the roles due at one sim instant are asked together
  and their answers overlap, so a round costs L however many roles it asks. Rounds are counted
  from the step events (subscribed on the run's router): the events of one round are consecutive,
  UAV then UGV, at one sim time, and arrive within L/2 of each other (rounds are at least L apart).
* CPU floor = CPU seconds of every process of the run (``agos eval`` with its orchestrator,
  router, evaluator, agents, world workers: ``RUSAGE_CHILDREN`` around the command) / cores.
  The world workers' share (their own ``getrusage`` at exit, in their logs) is printed beside it.

ratio = wall / max(floors). Goal: the paper's 210-episode test split (or a stated stratified
sample of it, ``--episodes N``) within 1.25x of the larger floor on 2 cores, with the number of
world workers chosen by ``agos eval --workers auto`` (deploy/run/concurrency.py).

The split is the paper's test split (``agos episodes split --train 0 --val 0 --test 210``, 70
episodes per difficulty on the held-out town), made once and cached in bench/.cache. A sample
takes the first N/3 episodes of each difficulty in file order.

    .venv/bin/python bench/bench_eval.py [--latency-ms 1000] [--episodes 24 | --episodes 210] [--workers auto]

``--quick`` (``make bench``): three episodes sampled on grid-s7 (one per difficulty), all at once
(about 90 s: the floor is one episode's 79 rounds x L, so the start-up weighs on the ratio as it
does for any run with fewer episodes than the rule's workers). ``--json``: also one
machine-readable line per figure (bench/figures.py).

Progress is ``agos eval``'s own bar (episodes, decisions/s); Ctrl-C stops the evaluation cleanly
(``agos eval`` stops every process of the run) and the bench says where the run's files are. The
CPU that other processes on the machine used meanwhile (``/proc/stat``) is printed; above 5 % the
figures are flagged as not clean.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import resource
import signal
import subprocess
import sys
import tempfile
import threading
import time
from collections import defaultdict
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path

from figures import Figures
from rich.console import Console
from rich.table import Table

from agos.deploy.run.launcher import free_port, wait_listening
from agos.runtime import keys
from agos.runtime.bus import Sample, ZenohBus
from agos.runtime.codec import DecodeError, decode
from agos.runtime.schemas import EpisodeRecord, EpisodeStarted, StepEvent

AGOS = [sys.executable, "-m", "agos.deploy.cli"]
CACHE = Path(__file__).resolve().parent / ".cache"
DIFFICULTIES = ("easy", "mid", "hard")
GOAL = 1.25


def paper_test_split(cache: Path = CACHE) -> Path:
    """The paper's test split (210 episodes on the held-out town), made once and cached."""
    out = cache / "test-210"
    path = out / "test.jsonl"
    if not path.exists():
        started = time.monotonic()
        cores = len(os.sched_getaffinity(0))
        subprocess.run([*AGOS, "episodes", "split", "--train", "0", "--val", "0", "--test", "210",
                        "--workers", str(cores), "--out", str(out)], check=True)
        print(f"made the test split in {time.monotonic() - started:.0f} s on {cores} cores -> {path}")
    return path


def quick_split(work: Path) -> Path:
    """One episode per difficulty sampled on grid-s7 (``--quick``)."""
    path = work / "quick-split.jsonl"
    subprocess.run([*AGOS, "episodes", "sample", "--town", "grid-s7", "--per-difficulty", "1", "--seed", "1",
                    "--out", str(path)], check=True, capture_output=True)
    return path


def stratified_sample(lines: list[str], n: int) -> list[str]:
    """The first n/3 episodes of each difficulty in file order (the remainder to the easier ones)."""
    by: dict[str, list[str]] = defaultdict(list)
    for line in lines:
        by[json.loads(line)["difficulty"]].append(line)
    out: list[str] = []
    for k, level in enumerate(DIFFICULTIES):
        out += by[level][:n // 3 + (1 if k < n % 3 else 0)]
    return out


def decision_rounds(steps: list[tuple[float, StepEvent]], latency_s: float) -> int:
    """Sequential decision rounds of one episode, from its step events with their arrival times.

    The world asks every role due at one sim instant at once and applies the answers UAV then UGV,
    so a round's events are consecutive (``episode_step``), UAV then UGV, at one sim time. A UGV
    decision woken at the same sim time by the UAV's sync is a round of its own: it arrives at least
    a model latency later, hence the ``latency_s / 2`` gap test (skipped when the latency is 0)."""
    rounds = 0
    prev: tuple[float, StepEvent] | None = None
    for arrived, event in sorted(steps, key=lambda s: s[1].episode_step):
        same_round = (prev is not None and prev[1].role == "uav" and event.role == "ugv"
                      and event.episode_step == prev[1].episode_step + 1 and event.sim_time_s == prev[1].sim_time_s
                      and (latency_s <= 0 or arrived - prev[0] < latency_s / 2))
        rounds += not same_round
        prev = (arrived, event)
    return rounds


def model_floor(rounds: list[int], latency_s: float, concurrent: int) -> tuple[float, float]:
    """(longest chain × L, total rounds × L / concurrent episodes); the floor is the larger."""
    return max(rounds, default=0) * latency_s, sum(rounds) * latency_s / max(1, concurrent)


class EventLog:
    """Every sample on the run's ``slot/*/events`` with its arrival time (zenoh's thread appends)."""

    def __init__(self, t0: float) -> None:
        self.t0 = t0
        self.samples: list[tuple[float, bytes]] = []

    def put(self, sample: Sample) -> None:
        self.samples.append((time.monotonic() - self.t0, sample.payload))

    def decoded(self) -> tuple[dict[str, list[tuple[float, StepEvent]]], list[tuple[float, EpisodeStarted]]]:
        steps: dict[str, list[tuple[float, StepEvent]]] = defaultdict(list)
        starts: list[tuple[float, EpisodeStarted]] = []
        for arrived, payload in list(self.samples):
            try:
                message = decode(payload)
            except DecodeError:
                continue
            if isinstance(message, StepEvent):
                steps[message.episode_id].append((arrived, message))
            elif isinstance(message, EpisodeStarted):
                starts.append((arrived, message))
        return steps, starts


@dataclass
class WorldLogs:
    cpu_s: float
    peak_rss_mb: list[float]
    setup_cpu_s: list[float]
    resends: int
    timeouts: int
    resubmits: int
    workers: int


def read_world_logs(log_dir: Path) -> WorldLogs:
    cpu, rss, setup = 0.0, [], []
    resends = timeouts = resubmits = 0
    files = sorted(log_dir.glob("world-*.log"))
    for path in files:
        text = path.read_text(errors="replace")
        for m in re.finditer(r"exits: CPU ([0-9.]+) s, peak RSS ([0-9.]+) MB", text):
            cpu += float(m.group(1))
            rss.append(float(m.group(2)))
        setup += [float(m.group(1)) for m in re.finditer(r"s CPU for town and scene, ([0-9.]+) s CPU since", text)]
        resends += text.count("re-requesting")
        timeouts += len(re.findall(r"no (uav|ugv) action for decision", text))
        resubmits += text.count("resubmitting")
    return WorldLogs(cpu, rss, setup, resends, timeouts, resubmits, len(files))


def machine_cpu_s() -> dict[str, float]:
    """CPU seconds this machine has spent so far (/proc/stat): ``busy`` in processes and the kernel on
    their behalf, ``irq`` (interrupts, softirqs: the loopback network among them), ``steal`` (the host
    ran something else while this VM wanted to run)."""
    fields = [int(x) for x in Path("/proc/stat").read_text().split("\n", 1)[0].split()[1:]]
    user, nice, system, _idle, _iowait, irq, softirq, steal = (fields + [0] * 8)[:8]
    tick = os.sysconf("SC_CLK_TCK")
    return {"busy": (user + nice + system) / tick, "irq": (irq + softirq) / tick, "steal": steal / tick}


def stored_records(run_dir: Path) -> list[EpisodeRecord]:
    from agos.evaluator.store import ResultStore

    path = run_dir / "results.sqlite"
    if not path.exists():
        return []
    with ResultStore(path, create=False) as store:
        return store.records()


def watch_events(proc: subprocess.Popen, port: int, run_id: str, log: EventLog) -> ZenohBus | None:
    """Subscribe to the run's step events once its router listens (before any world can start)."""
    while proc.poll() is None:
        if wait_listening("127.0.0.1", port, 0.2):
            bus = ZenohBus.connect(f"tcp/127.0.0.1:{port}")
            bus.subscribe(keys.events(run_id, "*"), log)  # EventLog is an inbox (put): a SampleSink
            return bus
    return None


def run(args: argparse.Namespace) -> int:
    console = Console()
    cores = len(os.sched_getaffinity(0))
    latency_s = args.latency_ms / 1000.0
    work = Path(tempfile.mkdtemp(prefix="agos-bench-eval-")) if args.work is None else args.work
    work.mkdir(parents=True, exist_ok=True)
    split = args.split or (quick_split(work) if args.quick else paper_test_split())
    lines = [x for x in split.read_text().splitlines() if x.strip()]
    episodes = lines if args.episodes >= len(lines) else stratified_sample(lines, args.episodes)
    sample = work / "episodes.jsonl"
    sample.write_text("\n".join(episodes) + "\n")
    run_dir = work / f"bench-eval-{datetime.now(UTC).strftime('%Y%m%d-%H%M%S')}"
    port = free_port(0)  # any free port: 7447 may be wanted by a router started by hand (the README's)
    policy = f"standin-{args.latency_ms}ms"
    cmd = [*AGOS, "eval", "--split", str(sample), "--policy", policy, "--workers", str(args.workers),
           "--run-dir", str(run_dir), "--port", str(port)]
    what = "all" if len(episodes) == len(lines) else "stratified sample"
    console.print(f"[bold]bench_eval[/]: {len(episodes)} episodes of {split} ({what}), policy {policy}, "
                  f"workers {args.workers}, {cores} cores", highlight=False)
    console.print("$ agos " + " ".join(cmd[3:]), highlight=False, soft_wrap=True)

    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    machine_before, self_before = machine_cpu_s(), time.process_time()
    t0 = time.monotonic()
    proc = subprocess.Popen(cmd)
    log = EventLog(t0)
    bus: ZenohBus | None = None
    try:
        holder: list[ZenohBus | None] = []
        watcher = threading.Thread(target=lambda: holder.append(watch_events(proc, port, run_dir.name, log)), daemon=True)
        watcher.start()
        rc = proc.wait()
        wall = time.monotonic() - t0
        watcher.join(timeout=5)
        bus = holder[0] if holder else None
    except KeyboardInterrupt:
        # A terminal's Ctrl-C reached agos eval too (same process group); it stops its processes in order.
        if proc.poll() is None:
            proc.send_signal(signal.SIGINT)
        try:
            proc.wait(timeout=30.0)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
        console.print(f"[yellow]interrupted; the run's files are in {run_dir}")
        return 130
    finally:
        if bus is not None:
            bus.close()
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    machine = {k: v - machine_before[k] for k, v in machine_cpu_s().items()}
    machine["busy"] -= time.process_time() - self_before  # the bench's own CPU is not load
    if rc != 0:
        console.print(f"[red]agos eval exited with {rc}; logs in {run_dir / 'logs'}")
        return rc

    cpu_all = (after.ru_utime + after.ru_stime) - (before.ru_utime + before.ru_stime)
    world = read_world_logs(run_dir / "logs")
    workers = world.workers
    records = stored_records(run_dir)
    steps, starts = log.decoded()
    rounds: list[int] = []
    estimated = 0
    for record in records:
        events = steps.get(record.episode_id, [])
        if len(events) == record.decisions_uav + record.decisions_ugv:
            rounds.append(decision_rounds(events, latency_s))
        else:  # events missed (should not happen): the fewest rounds those decisions can take
            estimated += 1
            rounds.append(max(record.decisions_uav, record.decisions_ugv))
    chain, throughput = model_floor(rounds, latency_s, workers)
    floor_model = max(chain, throughput)
    floor_cpu = cpu_all / cores
    floor = max(floor_model, floor_cpu)
    ratio = wall / floor if floor > 0 else float("inf")
    decisions = sum(r.decisions_uav + r.decisions_ugv for r in records)

    first_start = min((t for t, _ in starts), default=float("nan"))
    worker_ready = sorted(min(t for t, s in starts if s.worker_id == w) for w in {s.worker_id for _, s in starts})
    last_start = max((t for t, _ in starts), default=float("nan"))
    last_step = max((t for ev in steps.values() for t, _ in ev), default=float("nan"))
    per_round = [r.wall_time_s / n - latency_s for r, n in zip(records, rounds, strict=True) if n]

    table = Table(title=f"Evaluation at model speed: {len(records)} episodes, L = {latency_s:g} s, {workers} workers, "
                        f"{cores} cores")
    table.add_column("quantity")
    table.add_column("value", justify="right")
    table.add_column("how", style="dim")
    table.add_row("wall (agos eval start -> final table)", f"{wall:.1f} s", "start-up and shutdown included")
    table.add_row("model floor", f"{floor_model:.1f} s", "max(chain x L, rounds x L / workers)")
    table.add_row("  longest chain x L", f"{chain:.1f} s", f"{max(rounds, default=0)} rounds")
    table.add_row("  rounds x L / workers", f"{throughput:.1f} s", f"{sum(rounds)} rounds ({decisions} decisions) / {workers}")
    table.add_row("CPU floor", f"{floor_cpu:.1f} s", f"{cpu_all:.0f} CPU s of all processes / {cores} cores")
    table.add_row("  world workers' share", f"{world.cpu_s / cores:.1f} s", f"{world.cpu_s:.0f} CPU s / {cores} cores")
    table.add_row("[bold]ratio wall / max(floors)", f"[bold]{ratio:.2f}x", f"goal <= {GOAL}x")
    others = max(0.0, machine["busy"] - cpu_all)
    table.add_row("other load on the machine", f"{100 * others / (wall * cores):.0f} %",
                  f"{others:.0f} CPU s in processes outside the run; interrupts {machine['irq']:.0f} s, "
                  f"stolen by the host {machine['steal']:.0f} s")
    table.add_row("first episode started", f"{first_start:.1f} s", "processes up, town and scene built")
    if worker_ready:
        table.add_row("workers ready (first episode)", f"{worker_ready[0]:.1f}-{worker_ready[-1]:.1f} s",
                      f"median {worker_ready[len(worker_ready) // 2]:.1f} s")
    table.add_row("last episode started", f"{last_start:.1f} s", "after this, workers run out of work")
    table.add_row("last decision", f"{last_step:.1f} s", f"then {wall - last_step:.1f} s to the final table")
    if per_round:
        per_round.sort()
        table.add_row("world time per round beyond L", f"{1000 * per_round[len(per_round) // 2]:.0f} ms",
                      "median over episodes: (episode wall / rounds) - L")
    if world.setup_cpu_s:
        table.add_row("worker start-up CPU", f"{sum(world.setup_cpu_s) / len(world.setup_cpu_s):.1f} s",
                      "per worker, imports + town + scene (mean)")
    if world.peak_rss_mb:
        mean_rss = sum(world.peak_rss_mb) / len(world.peak_rss_mb)
        table.add_row("world worker peak RSS", f"{max(world.peak_rss_mb):.0f} MB", f"mean {mean_rss:.0f} MB")
    table.add_row("resends / timeouts / record resubmits", f"{world.resends} / {world.timeouts} / {world.resubmits}",
                  "from the world logs")
    if estimated:
        table.add_row("[yellow]episodes with missed events", str(estimated), "rounds estimated as max(decisions per role)")
    console.print(table)
    Figures(args.json).add(f"agos eval at model speed, {len(records)} episodes, L = {latency_s:g} s: wall vs max(floors)",
                           ratio, f"{ratio:.2f}x ({wall:.1f} vs {floor:.1f} s)", f"<= {GOAL}x",
                           ratio <= GOAL and len(records) == len(episodes))
    console.print(f"inputs: L = {latency_s:g} s, episodes = {len(records)}, workers = {workers} ({args.workers}), "
                  f"cores = {cores}; run: {run_dir}", highlight=False)
    if others > 0.05 * wall * cores:
        console.print("[yellow]other processes used more than 5 % of the machine during the run: the figures are not clean")
    if len(records) != len(episodes):
        console.print(f"[red]{len(episodes) - len(records)} episodes have no stored record")
        return 1
    return 0


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--latency-ms", type=int, default=1000, help="the stand-in model's latency per decision (default 1000)")
    parser.add_argument("--episodes", type=int, help="stratified sample of the split (default 24, 3 with --quick; 210: all)")
    parser.add_argument("--workers", default="auto", help="agos eval --workers: auto (default) or a number")
    parser.add_argument("--split", type=Path, help="episode file instead of the paper's test split")
    parser.add_argument("--work", type=Path, help="directory for the sample and the run (default: a new temp dir)")
    parser.add_argument("--quick", action="store_true", help="three grid-s7 episodes (one per difficulty)")
    parser.add_argument("--json", action="store_true", help="also print each figure as a BENCH-FIGURE line")
    args = parser.parse_args()
    if args.episodes is None:
        args.episodes = 3 if args.quick else 24
    if args.latency_ms < 0 or args.episodes < 1:
        parser.error("--latency-ms >= 0 and --episodes >= 1")
    try:
        return run(args)
    except KeyboardInterrupt:  # while the split is made (agos eval's own Ctrl-C is handled in run)
        return 130


if __name__ == "__main__":
    sys.exit(main())
