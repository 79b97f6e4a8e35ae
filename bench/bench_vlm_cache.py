"""Record and replay of model calls (``--vlm-cache``, agents/vlm/cache.py): what they cost.

Plays one split (``--episodes`` mid episodes on grid-s7, one world worker) through the real ``agos
eval`` with AGOS-Agent against the offline stand-in endpoint (in this process, 0 ms latency: its
perception is the model's whole cost), four ways, ``--repeats`` times each in turn:

* ``plain``: no cache;
* ``record``: ``--vlm-cache DIR`` on an empty cache (every call asked and stored);
* ``replay``: ``--vlm-cache DIR --vlm-cache-mode replay``, no endpoint;
* ``floor``: the same decisions with no model at all: a 0 ms scripted policy (``ScriptedReplay``
  below, run as ``--policy bench_vlm_cache:ScriptedReplay``) that answers each observation with the
  recorded run's reply for it, parsed as the agent parses it; so it walks the same trajectory, and
  the world's rendering and the processes are all that is left (the CPU floor of this split).

Figures (the median over the repeats of the ratio of the repeat's two runs, which ran one after
the other, and the ratio of the best runs beside it; wall = the command's start to its exit,
start-up included; episode wall = the records' ``wall_time_s``, the episode loop alone; CPU = the
CPU seconds of every process of the run, ``RUSAGE_CHILDREN``, which another process's load moves
least):

* replay vs floor, wall, episode wall and CPU seconds of all the run's processes: goal <= 1.2x;
* record vs plain, the same three: goal <= 1.05x;
* the cache's lookup per call in replay (request canonicalised, images hashed, the row read, the
  hit counted), measured in-process over every recorded call: the CPU it takes on average (goal
  <= 2 ms; the wall median and p95 beside it, which another process's load moves), and the record
  mode's store per call beside it (no goal: the model's latency hides it).

Checks, not timings: the replayed records equal the recorded ones (but for ``run_id``,
``wall_time_s`` and ``provenance``) and the stand-in got no request during the replays; a failed check exits 1.

    .venv/bin/python bench/bench_vlm_cache.py [--episodes 2] [--repeats 2] [--quick] [--json]

``--quick``: one episode, one repeat (about 2 min on the 2-core VM).
"""

from __future__ import annotations

import argparse
import asyncio
import base64
import json
import os
import resource
import sqlite3
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from figures import Figures

from agos.agents.contract import Policy
from agos.agents.vlm.parse import to_action
from agos.runtime.schemas import Action, Observation

AGOS = [sys.executable, "-m", "agos.deploy.cli"]
HERE = Path(__file__).resolve().parent
SCRIPT_ENV = "BENCH_VLM_CACHE_SCRIPT"
"""The JSON file of recorded replies ScriptedReplay answers with (an environment variable: agos eval
passes its own environment to the agent processes)."""
WALL_CLOCK = ("run_id", "wall_time_s", "provenance")
"""What a replayed record may differ in: the run's name, the episode's wall time, and the agos commit
that wrote it (others may commit between this bench's runs)."""


class ScriptedReplay(Policy):
    """The floor's policy: the recorded reply of each decision, parsed against the observation (the
    VLM agent's parse), in microseconds; a decision the recording lacks is a WAIT."""

    name = "scripted-replay"
    inline = True

    def __init__(self, role) -> None:
        super().__init__(role)
        self.replies: dict[str, str | None] = json.loads(Path(os.environ[SCRIPT_ENV]).read_text())[role]

    def act(self, obs: Observation) -> Action:
        return to_action(self.replies.get(f"{obs.episode_id}#{obs.decision_index}"), obs).action


def _records(run_dir: Path) -> list[dict]:
    with sqlite3.connect(run_dir / "results.sqlite") as db:
        return sorted((json.loads(r) for (r,) in db.execute("SELECT record_json FROM episodes")),
                      key=lambda r: r["episode_id"])


def _eval(split: Path, run_dir: Path, policy: str, *flags: str,
          env: dict[str, str] | None = None) -> tuple[float, float, float]:
    """(command wall s, sum of the episodes' wall_time_s, CPU s of every process of the run) of one ``agos eval``."""
    from agos.deploy.run.launcher import free_port

    cpu = resource.getrusage(resource.RUSAGE_CHILDREN)
    started = time.monotonic()
    proc = subprocess.run([*AGOS, "eval", "--split", str(split), "--policy", policy, "--workers", "1",
                           "--run-dir", str(run_dir), "--port", str(free_port(23000 + os.getpid() % 500)), *flags],
                          cwd=HERE, capture_output=True, text=True, env=env, timeout=1800)
    wall = time.monotonic() - started
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    if proc.returncode != 0:
        sys.exit(f"agos eval ({policy} {' '.join(flags)}) exited {proc.returncode}:\n{proc.stdout[-2000:]}{proc.stderr[-2000:]}")
    used = after.ru_utime + after.ru_stime - cpu.ru_utime - cpu.ru_stime
    return wall, sum(r["wall_time_s"] for r in _records(run_dir)), used


def _script(records: list[dict], out: Path) -> Path:
    replies: dict[str, dict[str, str | None]] = {"uav": {}, "ugv": {}}
    for record in records:
        for t in record["decision_traces"]:
            replies[t["role"]][f"{record['episode_id']}#{t['decision_index']}"] = t["raw_reply"]
    out.write_text(json.dumps(replies))
    return out


def lookup_costs(cache_dir: Path) -> tuple[list[tuple[float, float]], list[tuple[float, float]]]:
    """(wall ms, CPU ms) of each replay lookup and each record store, for every call stored in ``cache_dir``: each
    request rebuilt as the client sends it (images as base64 data URLs) and asked of a replay
    handle, then recorded into a fresh cache with an endpoint that answers at once."""
    from agos.agents.vlm.cache import CACHE_FILE, ReplyCache
    from agos.agents.vlm.client import CallTag, Reply

    with sqlite3.connect(cache_dir / CACHE_FILE) as db:
        images = {d: f"data:{m};base64,{base64.b64encode(b).decode()}" for d, m, b in
                  db.execute("SELECT sha256, mime, data FROM images")}
        calls = db.execute("SELECT q.body, r.stream FROM replies r JOIN requests q USING (key) "
                           "ORDER BY r.stream, r.occurrence").fetchall()

    def rebuilt(stored: str) -> dict:
        body = json.loads(stored)
        for message in body["messages"]:
            for part in message["content"] if isinstance(message.get("content"), list) else []:
                url = part.get("image_url", {}).get("url", "") if isinstance(part, dict) else ""
                if url.startswith("sha256:"):
                    part["image_url"]["url"] = images[url[len("sha256:"):]]
        return body

    bodies = [(rebuilt(b), CallTag(*s.split("/"), 0)) for b, s in calls]
    replay, fresh = ReplyCache(cache_dir, "replay"), Path(tempfile.mkdtemp(prefix="vlm-cache-store-"))
    record = ReplyCache(fresh, "record")
    answer = Reply(text='{"action": "WAIT"}', finish_reason="stop", prompt_tokens=1, completion_tokens=1,
                   latency_s=0.0, attempts=1)

    async def at_once(body: dict) -> Reply:
        return answer

    async def timed(cache: ReplyCache) -> list[tuple[float, float]]:
        out = []
        for body, call in bodies:
            wall, cpu = time.perf_counter(), time.thread_time()
            await cache.complete(body, call, at_once)
            out.append(((time.perf_counter() - wall) * 1000, (time.thread_time() - cpu) * 1000))
        return out

    async def run() -> tuple[list[tuple[float, float]], list[tuple[float, float]]]:
        return await timed(replay), await timed(record)

    try:
        return asyncio.run(run())
    finally:
        replay.close()
        record.close()


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--episodes", type=int, default=2)
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--quick", action="store_true", help="one episode, one repeat")
    ap.add_argument("--json", action="store_true", help="also one BENCH-FIGURE line per figure")
    args = ap.parse_args()
    if args.quick:
        args.episodes, args.repeats = 1, 1
    figures = Figures(args.json)
    from agos.agents.vlm.standin.server import StandinServer

    work = Path(tempfile.mkdtemp(prefix="bench-vlm-cache-"))
    split = work / "split.jsonl"
    subprocess.run([*AGOS, "episodes", "sample", "--town", "grid-s7", "--difficulty", "mid", "-n", str(args.episodes),
                    "--seed", "3", "--out", str(split)], check=True, capture_output=True)
    print(f"split: {args.episodes} mid episode(s) on grid-s7 (seed 3), {args.repeats} repeat(s); files in {work}; "
          f"load average {os.getloadavg()[0]:.2f}", flush=True)
    walls: dict[str, list[tuple[float, float, float]]] = {"plain": [], "record": [], "replay": [], "floor": []}
    env = dict(os.environ)
    failures: list[str] = []
    with StandinServer(models=("agos-standin",)) as server:
        model = ["--vlm-base-url", server.url, "--model", "agos-standin"]
        for k in range(args.repeats):
            cache = work / f"cache-{k}"
            walls["plain"].append(_eval(split, work / f"plain-{k}", "agos-agent", *model))
            walls["record"].append(_eval(split, work / f"record-{k}", "agos-agent", *model, "--vlm-cache", str(cache)))
            before = server.stats()["requests"]
            walls["replay"].append(_eval(split, work / f"replay-{k}", "agos-agent", "--model", "agos-standin",
                                         "--vlm-cache", str(cache), "--vlm-cache-mode", "replay"))
            if server.stats()["requests"] != before:
                failures.append(f"the replay asked the endpoint {server.stats()['requests'] - before} time(s)")
            recorded, replayed = _records(work / f"record-{k}"), _records(work / f"replay-{k}")
            strip = [[{f: v for f, v in r.items() if f not in WALL_CLOCK} for r in rs] for rs in (recorded, replayed)]
            if strip[0] != strip[1]:
                failures.append(f"repeat {k}: the replayed records differ from the recorded ones")
            env[SCRIPT_ENV] = str(_script(recorded, work / f"script-{k}.json"))
            walls["floor"].append(_eval(split, work / f"floor-{k}", "bench_vlm_cache:ScriptedReplay", env=env))
            floor_records = _records(work / f"floor-{k}")
            if [r["decisions_uav"] + r["decisions_ugv"] for r in floor_records] != [
                    r["decisions_uav"] + r["decisions_ugv"] for r in recorded]:
                failures.append(f"repeat {k}: the scripted floor took other decisions than the recorded run")
            print("  " + ", ".join(f"{name} {w[-1][0]:.1f} s ({w[-1][1]:.1f} s in episodes, {w[-1][2]:.1f} CPU s)"
                                   for name, w in walls.items()), flush=True)
    decisions = sum(r["decisions_uav"] + r["decisions_ugv"] for r in _records(work / "record-0"))
    lookups, stores = lookup_costs(work / "cache-0")
    best = {name: tuple(min(run[i] for run in runs) for i in range(3)) for name, runs in walls.items()}
    rows = [("replay vs floor", "replay", "floor", 1.2), ("record vs plain", "record", "plain", 1.05)]
    print(f"\n{decisions} decisions, {len(lookups)} model calls a run; the median of the {args.repeats} repeats' "
          "ratios (each repeat's runs one after the other), and the best runs':")
    for label, a, b, goal in rows:
        for i, what in enumerate(("wall", "episode wall", "CPU")):
            ratio = statistics.median(x[i] / y[i] for x, y in zip(walls[a], walls[b], strict=True))
            shown = f"{ratio:.3f}x (best runs: {best[a][i]:.1f} s vs {best[b][i]:.1f} s, {best[a][i] / best[b][i]:.3f}x)"
            print(f"  {label}, {what}: {shown}  goal <= {goal}x {'met' if ratio <= goal else 'MISSED'}")
            figures.add(f"vlm-cache {label} ({what})", round(ratio, 3), shown, f"<= {goal}x", ratio <= goal)
    for label, costs, goal in (("replay lookup", lookups, 2.0), ("record store", stores, None)):
        walls_ms, cpus_ms = [w for w, _ in costs], [c for _, c in costs]
        mean_cpu = statistics.fmean(cpus_ms)
        shown = (f"{mean_cpu:.2f} ms CPU on average (wall: median {statistics.median(walls_ms):.2f} ms, "
                 f"p95 {statistics.quantiles(walls_ms, n=20)[-1]:.2f} ms)")
        verdict = "(no goal)" if goal is None else f"goal <= {goal:g} ms {'met' if mean_cpu <= goal else 'MISSED'}"
        print(f"  {label} per call: {shown}  {verdict}")
        figures.add(f"vlm-cache {label} per call (CPU)", round(mean_cpu, 3), shown,
                    "" if goal is None else f"<= {goal:g} ms", None if goal is None else mean_cpu <= goal)
    print(f"load average at the end {os.getloadavg()[0]:.2f}")
    for failure in failures:
        print(f"CHECK FAILED: {failure}")
    return 1 if failures else 0


if __name__ == "__main__":
    sys.exit(main())
