"""How many episodes an evaluation runs at once: ``agos eval --workers auto``.

A world worker runs one episode at a time, so concurrency is the number of world workers. Each
decision round of an episode (the world asks the roles due at one sim instant and waits for their
answers) costs about ``c`` CPU seconds on the host, all processes together (the world renders the
observations and applies the actions; the agents decode them; the router forwards them), and then
``L`` seconds of model time during which that episode needs no CPU. One worker therefore keeps the
cores busy a fraction c / (c + L) of the time, and ``cores × (c + L) / c`` workers would fill them
if their CPU bursts never collided; they do (at that count the cores were about a quarter idle),
so the rule asks ``HEADROOM`` times as many. Capped by memory (each worker holds a PyBullet scene of
the town), by how many requests the model endpoint may get at once (VLM policies: ``[vlm]
concurrency``), and by the episodes; then spread evenly over the waves the episodes need, so the
last wave is not a handful of episodes beside idle workers.

``L`` comes from the policy names where they say it (``standin-<N>ms``; scripted policies: 0), else
from ``--model-latency`` (VLM policies: the model's, which agos cannot know before it runs; unknown,
it counts as 0: one worker per core).
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass
from pathlib import Path

from agos.agents.names import known_latency_s

CPU_PER_ROUND_S = 0.09
"""``c``: CPU seconds of all of a run's processes per decision round, measured with
bench/bench_eval.py on the 2-core VM (parks-s23, tiny renderer, 512 px nadir and six 256 px ground
views, standin-1000ms): 0.09-0.10 s per round in runs of 3 to 210 episodes with 3 to 35 workers,
the workers' start-up left out (more workers share the caches: the higher figures).
Rendering dominates it, so another renderer or other image sizes give another ``c``."""
HEADROOM = 1.5
"""Workers per "just enough" worker. With 24 workers (the balance point for L = 1 s on 2 cores) a
round took 1.44 s instead of about 1.1, the cores were about a quarter idle and 48 episodes took 1.30x
their CPU floor; with 48 workers, 1.04x (bench/README.md, "Evaluation at model speed")."""
WORKER_RSS_MB = 300.0
"""A world worker's resident memory with one procedural town (262 MB peak measured), rounded up."""
MEMORY_SHARE = 0.5
"""At most this share of the available memory goes to world workers."""


@dataclass(frozen=True)
class Choice:
    workers: int
    why: str


def auto_workers(*, latency_s: float | None, cores: int, episodes: int, available_mb: float | None = None,
                 model_concurrency: int | None = None, cpu_per_round_s: float = CPU_PER_ROUND_S,
                 headroom: float = HEADROOM, worker_rss_mb: float = WORKER_RSS_MB) -> Choice:
    """World workers for ``episodes`` episodes of a model taking ``latency_s`` per decision on
    ``cores`` cores: ``ceil(headroom × cores × (c + L) / c)``, capped by ``MEMORY_SHARE`` of
    ``available_mb`` (None: no cap), by ``model_concurrency`` (None: no cap) and by ``episodes``,
    then evened out over the waves. An unknown latency (None) counts as 0, and no latency needs no
    headroom: one worker per core. Always at least 1."""
    c = max(cpu_per_round_s, 1e-6)
    latency = max(0.0, latency_s or 0.0)
    h = headroom if latency > 0 else 1.0
    ideal = math.ceil(h * max(1, cores) * (c + latency) / c - 1e-9)
    caps = {"episodes": max(1, episodes)}
    if model_concurrency is not None:
        caps["model concurrency"] = max(1, model_concurrency)
    if available_mb is not None:
        caps["memory"] = max(1, int(MEMORY_SHARE * available_mb // worker_rss_mb))
    capped = max(1, min([ideal, *caps.values()]))
    waves = math.ceil(max(1, episodes) / capped)
    workers = math.ceil(max(1, episodes) / waves)
    limit = min(caps, key=lambda k: caps[k])
    why = (f"auto: {h:g} x {cores} cores x (c + L) / c with c = {c:g} s, L = "
           + ("unknown, give --model-latency" if latency_s is None else f"{latency:g} s")
           + f" -> {ideal}" + (f"; capped by {limit} -> {capped}" if capped < ideal else "")
           + (f"; {waves} waves of {episodes} episodes -> {workers}" if workers < capped else ""))
    return Choice(workers, why)


def run_latency_s(policies: dict[str, str], model_latency_s: float | None = None) -> float | None:
    """Model time per decision round: ``model_latency_s`` if given, else the slowest known latency of
    the roles' policies (roles asked together overlap); None if some policy's latency is unknown."""
    if model_latency_s is not None:
        return model_latency_s
    latencies = [known_latency_s(name) for name in policies.values()]
    return None if any(x is None for x in latencies) else max((x for x in latencies if x is not None), default=0.0)


def host_resources() -> tuple[int, float | None]:
    """(cores this process may run on, available memory in MB or None where /proc/meminfo is missing)."""
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    try:
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemAvailable:"):
                return cores, int(line.split()[1]) / 1024
    except OSError:
        pass
    return cores, None


def choose_workers(policies: dict[str, str], episodes: int, *, model_latency_s: float | None = None,
                   model_concurrency: int | None = None) -> Choice:
    """``--workers auto`` on this host."""
    cores, available = host_resources()
    return auto_workers(latency_s=run_latency_s(policies, model_latency_s), cores=cores, episodes=episodes,
                        available_mb=available, model_concurrency=model_concurrency)
