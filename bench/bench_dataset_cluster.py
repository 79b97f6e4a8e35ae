"""The full AGOS-Dataset build on a cluster: per-episode CPU of each process of a build, measured, and
the wall time of the paper's 7,700 episodes projected for nodes x cores (issue 33, item 5).

One ``agos dataset build`` (the build's own settings: rich look, views every 10 m) of a sampled split,
its processes' CPU read from ``/proc`` every 0.2 s: world workers, the two agent services (they write
the dataset), the evaluator, the router and the build command itself (the orchestrator, which also
assembles each episode). Start-up is left out: each process's CPU is counted from the moment the first
episode starts (town building, once per worker and town, stays in).

The projection (docs/DATASET.md, "On a cluster"): a world worker on every core of every node renders
episodes in parallel (a world is single-threaded: one core each), the first node's cores shared with
the build's other processes; those are one per build, at most one core each (a Python process: one
interpreter lock), so the build goes no faster than its busiest one allows, whatever the cores::

    episodes/s = min(cores / CPU s per episode of all processes, 1 / CPU s per episode of each single process)

A single process's CPU per episode is an upper bound: it includes what the process spends while idle
(polling, liveliness, progress) over the measured build's wall time, which a faster build spreads over
more episodes; where one of them bounds the projection, the table gives the range between that
ceiling and the cores' rate. Bytes per episode give the rate the shared filesystem must absorb.

    .venv/bin/python bench/bench_dataset_cluster.py                       # grid-s7, 1 per difficulty
    .venv/bin/python bench/bench_dataset_cluster.py --towns Town01 --per-difficulty 1
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from bench_dataset import AGOS, FULL_EPISODES, sample_split
from rich.console import Console
from rich.table import Table

KINDS = ("world", "agent uav", "agent ugv", "evaluator", "router", "build (orchestrator)")
CLUSTERS = ((1, 2), (1, 16), (2, 32), (4, 16), (4, 32), (8, 32), (16, 32))
"""(nodes, cores per node) of the projection table; (1, 2) is this VM."""


def kind_of(cmdline: str, build_pid: int, pid: int) -> str | None:
    if pid == build_pid:
        return "build (orchestrator)"
    for words, kind in ((" world", "world"), (" agent --role uav", "agent uav"), (" agent --role ugv", "agent ugv"),
                        (" evaluator", "evaluator"), (" router", "router")):
        if words in cmdline:
            return kind
    return None


def cpu_s(pid: int) -> float | None:
    """User + system CPU seconds of ``pid`` so far; None once it is gone."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except OSError:
        return None
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def descendants(root: int) -> dict[int, str]:
    """pid -> command line of every live descendant of ``root`` (and ``root``)."""
    parent: dict[int, int] = {}
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            parent[int(stat.parent.name)] = int(stat.read_text().rsplit(")", 1)[1].split()[1])
        except (OSError, ValueError, IndexError):
            continue
    found, grew = {root}, True
    while grew:
        more = {p for p, pp in parent.items() if pp in found} - found
        found |= more
        grew = bool(more)
    out = {}
    for pid in found:
        try:
            out[pid] = Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
        except OSError:
            continue
    return out


def measure(split: Path, out: Path, workers: int, console: Console) -> tuple[dict[str, float], int, float, int]:
    """Build ``split`` into ``out``; CPU seconds per process kind from the first episode's start to the
    end, episodes, the build's wall seconds and the dataset's bytes."""
    argv = [*AGOS, "dataset", "build", "--split", str(split), "--out", str(out), "--workers", str(workers)]
    console.print(f"$ agos {' '.join(argv[3:])}", highlight=False, soft_wrap=True)
    t0 = time.monotonic()
    proc = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    first: dict[int, float] | None = None  # CPU of each process when the first episode started
    last: dict[int, float] = {}
    kinds: dict[int, str] = {}
    while proc.poll() is None:
        for pid, cmdline in descendants(proc.pid).items():
            kind = kind_of(cmdline, proc.pid, pid)
            used = cpu_s(pid)
            if kind is None or used is None:
                continue
            kinds[pid], last[pid] = kind, used
        if first is None and any("starts, attempt" in p.read_text(errors="replace") for p in out.glob("*/logs/world-*.log")):
            first = dict(last)
        time.sleep(0.2)
    wall = time.monotonic() - t0
    output = proc.stdout.read() if proc.stdout else ""
    if proc.returncode != 0:
        raise SystemExit(f"agos dataset build exited with {proc.returncode}:\n{output[-3000:]}")
    manifest = json.loads((out / "manifest.json").read_text())
    by_kind = dict.fromkeys(KINDS, 0.0)
    for pid, kind in kinds.items():
        by_kind[kind] += last[pid] - (first or {}).get(pid, 0.0)
    return by_kind, manifest["counts"]["episodes"], wall, manifest["counts"]["bytes"]


def projection(per_episode: dict[str, float], mb_per_episode: float) -> Table:
    """The 7,700 episodes' wall for each of :data:`CLUSTERS`: the cores' rate (every CPU second of an
    episode, the world's and the others', over all cores), or, where a single process's ceiling is
    lower, the range between the two (that ceiling comes from an upper bound of its CPU: module
    docstring)."""
    total = sum(per_episode.values())
    singles = {k: v for k, v in per_episode.items() if k != "world" and v > 0}
    busiest, busiest_s = max(singles.items(), key=lambda kv: kv[1])
    ceiling = 1.0 / busiest_s
    table = Table(title=f"{FULL_EPISODES:,} episodes projected ({total:.1f} CPU s an episode, all processes; the "
                        f"busiest single process, {busiest}, {busiest_s:.2f} CPU s an episode at most: "
                        f"{ceiling * 3600:,.0f} episodes/h or more)")
    for col in ("nodes x cores", "episodes/h", "wall", "bound by", "MB/s to the shared FS"):
        table.add_column(col, justify="right")

    def wall(rate: float) -> str:
        hours = FULL_EPISODES / rate / 3600
        return f"{hours:.1f} h" if hours >= 1 else f"{hours * 60:.0f} min"

    for nodes, cores in CLUSTERS:
        rate = nodes * cores / total
        if rate <= ceiling:
            table.add_row(f"{nodes} x {cores}", f"{rate * 3600:,.0f}", wall(rate), "cores", f"{rate * mb_per_episode:.0f}")
        else:
            table.add_row(f"{nodes} x {cores}", f"{ceiling * 3600:,.0f}-{rate * 3600:,.0f}", f"{wall(rate)} to {wall(ceiling)}",
                          busiest, f"{ceiling * mb_per_episode:.0f}-{rate * mb_per_episode:.0f}")
    return table


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--towns", nargs="+", default=["grid-s7"], help="towns of the sample (default grid-s7)")
    ap.add_argument("--per-difficulty", type=int, default=1)
    ap.add_argument("--seed", type=int, default=3)
    ap.add_argument("--look", default="rich")
    ap.add_argument("--workers", type=int, default=1, help="world workers of the measured build (default 1)")
    ap.add_argument("--out", type=Path, help="work folder (default: a temporary one, removed)")
    args = ap.parse_args()
    console = Console(width=160)
    work = args.out or Path(tempfile.mkdtemp(prefix="bench-dataset-cluster-"))
    work.mkdir(parents=True, exist_ok=True)
    split = sample_split(args.towns, args.per_difficulty, args.seed, args.look, work, console)
    by_kind, episodes, wall, size = measure(split, work / "dataset", args.workers, console)
    per_episode = {k: v / episodes for k, v in by_kind.items()}
    table = Table(title=f"CPU per episode by process ({episodes} episodes, {', '.join(args.towns)}, "
                        f"look {args.look}; build wall {wall:.0f} s)")
    table.add_column("process")
    table.add_column("CPU s per episode", justify="right")
    table.add_column("share", justify="right")
    total = sum(per_episode.values())
    for kind in KINDS:
        table.add_row(kind, f"{per_episode[kind]:.2f}", f"{100 * per_episode[kind] / total:.0f} %")
    table.add_row("all", f"{total:.2f}", "100 %")
    console.print(table)
    mb = size / episodes / 1e6
    console.print(f"dataset: {mb:.1f} MB per episode")
    console.print(projection(per_episode, mb))
    print(json.dumps({"episodes": episodes, "cpu_s_per_episode": per_episode, "mb_per_episode": mb}))
    if args.out is None:
        import shutil

        shutil.rmtree(work, ignore_errors=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
