"""agos as a library (issue 32): what stepping the world from Python costs.

* ``env``: decisions per second of ``agos.Env`` (a fresh Env per play, its ``step`` loop) against the
  engine driven directly (``EpisodeRunner.run`` with in-process agents), the same episodes, images at
  their default sizes, interleaved; the policy is examples/my_policy.py's Explorer (it never confirms,
  so every episode is its whole budget, and takes microseconds: the world's cost is what is timed).
  Goal: >= 0.95x.
* ``process``: the same episodes through ``agos eval`` (processes on a bus): the world's decisions per
  second of episode wall time (from the records) and of the whole command, against ``agos.Env``.
  Reported, no goal (the bus, the agent processes and the run's start-up are what it measures).
* ``vector``: steps per second of 2 environments in subprocesses against 1 (the UGV learning beside
  the Explorer flying the UAV, random masked actions, images on), each counted as environment steps
  over the same wall time, two ways: ``agos.vector.AsyncEnvPool`` (each environment sent its next
  action as soon as it answers; goal: >= 1.7x on 2 cores) and ``make_vector_env`` (Gymnasium's
  ``AsyncVectorEnv``, lockstep: each step waits for the slower environment; reported).

    .venv/bin/python bench/bench_env.py [--quick] [--only env --only vector] [--json]

``--quick`` (``make bench``): 2 episodes, 2 rounds, 20 s per vector size and way, no ``process``. ``--json``:
also one machine-readable line per figure (bench/figures.py).
"""

from __future__ import annotations

import argparse
import json
import os
import sqlite3
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np
from figures import Figures

from agos import Env, episode_config
from agos.agents.inprocess import InProcessAgents
from agos.agents.registry import make_policy
from agos.runtime.episode_config import EpisodeConfig
from agos.runtime.schemas import EpisodeSpec
from agos.world.episodes.files import write_episodes
from agos.world.episodes.sampling import sample_episode
from agos.world.sim.engine import EpisodeRunner
from agos.world.sim.scene import Scene
from agos.world.towns.asset import Town, open_town

ROLES = ("uav", "ugv")
POLICY = "examples.my_policy:Explorer"
"""Found from the repository root, where this runs (agents/registry.py looks in the current folder)."""


def episodes(town: Town, scene: Scene, n: int) -> list[EpisodeSpec]:
    return [sample_episode(town, scene, ("easy", "mid", "hard")[k % 3], k // 3, seed=7, stream=k % 3) for k in range(n)]


def env_vs_engine(town: Town, scene: Scene, specs: list[EpisodeSpec], config: EpisodeConfig, rounds: int,
                  figures: Figures) -> float:
    """Decisions per second of each way, median over rounds of the total over ``specs``."""
    rates: dict[str, list[float]] = {"engine": [], "env": []}
    for _ in range(rounds):
        for way in ("engine", "env") if _ % 2 == 0 else ("env", "engine"):
            decisions, seconds = 0, 0.0
            for spec in specs:
                policies = {r: make_policy(POLICY, r) for r in ROLES}
                started = time.perf_counter()
                if way == "engine":
                    record = EpisodeRunner(scene, town, spec, run_id="bench", worker_id="bench",
                                           config=config).run(InProcessAgents(policies))
                else:
                    with Env(spec, config, scene=scene, town=town) as env:
                        record = env.play(policies)
                seconds += time.perf_counter() - started
                decisions += record.decisions_uav + record.decisions_ugv
            rates[way].append(decisions / seconds)
    engine, env_rate = statistics.median(rates["engine"]), statistics.median(rates["env"])
    ratio = env_rate / engine
    print(f"env ({POLICY}): agos.Env {env_rate:.1f} decisions/s, EpisodeRunner.run {engine:.1f} decisions/s: {ratio:.3f}x "
          f"(goal >= 0.95x; rounds {[round(r, 1) for r in rates['env']]} vs {[round(r, 1) for r in rates['engine']]})")
    figures.add("agos.Env vs the engine driven directly (decisions/s)", ratio, f"{ratio:.3f}x", ">= 0.95x", ratio >= 0.95)
    return env_rate


def process_path(specs: list[EpisodeSpec], env_rate: float, figures: Figures) -> None:
    with tempfile.TemporaryDirectory(prefix="bench-env-") as tmp:
        split = Path(tmp) / "split.jsonl"
        write_episodes(split, specs)
        started = time.perf_counter()
        out = subprocess.run([sys.executable, "-m", "agos.deploy.cli", "eval", "--split", str(split), "--policy",
                              POLICY, "--run-dir", str(Path(tmp) / "run")], capture_output=True,
                             text=True, env={**os.environ, "AGOS_WORLD__LOOK": "flat"}, timeout=900)
        command_s = time.perf_counter() - started
        if out.returncode != 0:
            print(out.stdout[-2000:] + out.stderr[-2000:])
            raise SystemExit(f"agos eval exited {out.returncode}")
        with sqlite3.connect(Path(tmp) / "run" / "results.sqlite") as db:
            records = [json.loads(r) for (r,) in db.execute("SELECT record_json FROM episodes")]
    decisions = sum(r["decisions_uav"] + r["decisions_ugv"] for r in records)
    world = decisions / sum(r["wall_time_s"] for r in records)
    whole = decisions / command_s
    print(f"process: agos eval {world:.1f} decisions/s of episode wall time, {whole:.1f} of the whole command "
          f"({command_s:.1f} s); agos.Env / process: {env_rate / world:.2f}x, {env_rate / whole:.2f}x")
    figures.add("agos.Env vs agos eval (decisions/s of episode wall time)", env_rate / world, f"{env_rate / world:.2f}x")
    figures.add("agos.Env vs agos eval (decisions/s of the whole command)", env_rate / whole, f"{env_rate / whole:.2f}x")


def vector(specs: list[EpisodeSpec], config: EpisodeConfig, seconds: float, figures: Figures) -> None:
    """Steps per second of 1 and 2 subprocess environments, in lockstep (``make_vector_env``) and as a
    pool (``AsyncEnvPool``); beside each, the CPU each subprocess spent per step, this process's CPU
    per step (actions, shared memory or the pipe's observations) and the share of a core each
    subprocess got (a loaded machine gives less than one each, and then no more steps per second:
    the CPU per step says whether the work itself stays the same)."""
    kwargs: dict[str, Any] = {"role": "ugv", "partner": POLICY, "episodes": specs, "config": config, "text": False}
    rates: dict[tuple[str, int], float] = {}
    cpu_per_step: dict[tuple[str, int], float] = {}
    for mode in ("pool", "lockstep"):
        for n in (1, 2):
            play = _lockstep if mode == "lockstep" else _pool
            steps, wall, used, parent_s = play(n, seconds, kwargs)
            rates[mode, n], cpu_per_step[mode, n] = steps / wall, sum(used) / steps
            print(f"vector {mode}, {n} env{'s' if n > 1 else ''}: {rates[mode, n]:.2f} steps/s; each step "
                  f"{cpu_per_step[mode, n]:.3f} s of CPU in its subprocess, {1000 * parent_s / steps:.2f} ms in this "
                  f"one; the subprocesses got {', '.join(f'{u / wall:.2f}' for u in used)} of a core "
                  f"(load average {os.getloadavg()[0]:.1f})")
    lockstep, pool = rates["lockstep", 2] / rates["lockstep", 1], rates["pool", 2] / rates["pool", 1]
    cpu = {mode: cpu_per_step[mode, 2] / cpu_per_step[mode, 1] for mode in ("lockstep", "pool")}
    print(f"vector: 2 subprocess envs vs 1: pool {pool:.2f}x steps/s (goal >= 1.7x on 2 cores; {os.cpu_count()} "
          f"cores), lockstep {lockstep:.2f}x; CPU per step 2 vs 1: pool {cpu['pool']:.2f}x, lockstep "
          f"{cpu['lockstep']:.2f}x")
    figures.add("2 subprocess envs vs 1, AsyncEnvPool (steps/s, images on)", pool, f"{pool:.2f}x", ">= 1.7x",
                pool >= 1.7)
    figures.add("2 subprocess envs vs 1, lockstep make_vector_env (steps/s, images on)", lockstep, f"{lockstep:.2f}x")
    figures.add("2 subprocess envs vs 1, AsyncEnvPool (CPU per step)", cpu["pool"], f"{cpu['pool']:.2f}x")
    figures.add("2 subprocess envs vs 1, lockstep (CPU per step)", cpu["lockstep"], f"{cpu['lockstep']:.2f}x")


def _lockstep(n: int, seconds: float, kwargs: dict[str, Any]) -> tuple[int, float, list[float], float]:
    """``make_vector_env(n)`` stepped for ``seconds``: environment steps, wall seconds, each
    subprocess's CPU seconds and this process's."""
    from agos.vector import make_vector_env

    envs = make_vector_env(n, **kwargs)
    try:
        obs, _ = envs.reset(seed=0)
        space = envs.single_action_space
        space.seed(0)
        for _ in range(3):  # warm-up: first renders, first resets
            obs, *_ = envs.step(np.array([space.sample(mask=obs["action_mask"][i]) for i in range(n)]))
        pids = [p.pid for p in envs.processes if p.pid is not None]
        cpu_before, parent_before = [_cpu_s(pid) for pid in pids], time.process_time()
        steps, started = 0, time.perf_counter()
        while time.perf_counter() - started < seconds:
            obs, *_ = envs.step(np.array([space.sample(mask=obs["action_mask"][i]) for i in range(n)]))
            steps += n
        wall = time.perf_counter() - started
        used = [_cpu_s(pid) - before for pid, before in zip(pids, cpu_before, strict=True)]
        return steps, wall, used, time.process_time() - parent_before
    finally:
        envs.close()


def _pool(n: int, seconds: float, kwargs: dict[str, Any]) -> tuple[int, float, list[float], float]:
    """``AsyncEnvPool(n)`` for ``seconds``, each environment sent its next action as soon as it
    answers: as :func:`_lockstep` returns, steps counting the answers received in the time."""
    from agos.vector import AsyncEnvPool, PoolResult

    with AsyncEnvPool(n, **kwargs) as pool:
        pool.reset(seed=0)
        ready = pool.recv(min_envs=n)
        space = pool.single_action_space
        space.seed(0)

        def step(ready: PoolResult) -> PoolResult:
            pool.send([space.sample(mask=m) for m in ready.observations["action_mask"]], ready.env_ids)
            return pool.recv()

        for _ in range(3 * n):  # warm-up: first renders, first resets
            ready = step(ready)
        pids = [p.pid for p in pool.processes if p.pid is not None]
        cpu_before, parent_before = [_cpu_s(pid) for pid in pids], time.process_time()
        steps, started = 0, time.perf_counter()
        while time.perf_counter() - started < seconds:
            ready = step(ready)
            steps += len(ready.env_ids)
        wall = time.perf_counter() - started
        used = [_cpu_s(pid) - before for pid, before in zip(pids, cpu_before, strict=True)]
        return steps, wall, used, time.process_time() - parent_before


def _cpu_s(pid: int) -> float:
    """User and system CPU seconds of process ``pid`` so far (Linux: /proc/PID/stat)."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--only", action="append", choices=["env", "process", "vector"])
    ap.add_argument("--episodes", type=int, help="episodes (default 6; quick 2)")
    ap.add_argument("--rounds", type=int, help="rounds of env vs engine (default 4; quick 2)")
    ap.add_argument("--vector-seconds", type=float, help="seconds per vector size and way (default 60; quick 20)")
    ap.add_argument("--json", action="store_true", help="also print each figure as a BENCH-FIGURE line")
    args = ap.parse_args(argv)
    os.chdir(Path(__file__).resolve().parents[1])  # the repository root: where the policy's module is found
    parts = args.only or (["env", "vector"] if args.quick else ["env", "process", "vector"])
    figures = Figures(args.json)
    config = episode_config(look="flat")  # images at their default sizes: 512 px nadir, 256 px ground, 384 px map
    town = open_town("grid-s7")
    with Scene(town.layout, look="flat") as scene:
        specs = episodes(town, scene, args.episodes or (2 if args.quick else 6))
        print(f"{len(specs)} grid-s7 episodes (flat look, default images); {os.cpu_count()} cores")
        env_rate = env_vs_engine(town, scene, specs, config, args.rounds or (2 if args.quick else 4), figures) \
            if "env" in parts or "process" in parts else 0.0
    if "process" in parts:
        process_path(specs, env_rate, figures)
    if "vector" in parts:
        vector(specs, config, args.vector_seconds or (20.0 if args.quick else 60.0), figures)
    return 0


if __name__ == "__main__":
    sys.exit(main())
