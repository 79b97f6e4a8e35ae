"""AGOS-Dataset build throughput and the image step's cost (issue 19, performance goals).

One sampled split (``agos episodes sample`` per town, the build's look), then, on that split:

1. **Baseline**: ``agos eval --policy expert`` with the world configured exactly as a build configures
   it (``capture_every_m``, look; the bench checks that the configuration hashes are equal). The
   world renders every view the dataset holds, decisions and every 10 m between them, and delivers
   them to the agents, which write nothing.
2. **Builds**: ``agos dataset build`` with 1 and with 2 world workers, each into a fresh directory.
   Episodes per hour (the command's wall, start-up included, and the orchestrator's rate from the
   first lease to the last stored episode), CPU of all processes, bytes; the projection for the
   paper's 7,700 episodes (5,500 train + 2,200 val) from the measured per-episode time and bytes.
   The 1-worker build against the baseline is the image step as a user lives it: the same command
   shape, the same views, plus writing them (wall and CPU ratios).
3. **Breakdown** (in this process, the same episodes): seconds spent rendering the views the
   dataset stores (observations, the six views, views between decisions, references: rendered and
   encoded as the world does), planning the expert, writing (agents/dataset/writer.py: images,
   decisions.jsonl, AGOS-Agent's prompt and the export line) and assembling (deploy/dataset/build.py:
   hashes, episode.json, the rename). Image step = (render + write + assemble) / render.

Goal: the image step within 1.2x of rendering the same views bare. Every ratio is against a
baseline measured in the same run; the CPU other processes used meanwhile (``/proc/stat``) is
printed per command, since walls on a shared machine move with it.

    .venv/bin/python bench/bench_dataset.py                        # grid-s7, 1 episode per difficulty (2-4 min)
    .venv/bin/python bench/bench_dataset.py --quick                # one easy episode: a smoke test

``make bench`` runs ``--quick --workers 1 --no-breakdown --json``: the CPU ratio of one build
against its baseline, one line per figure (bench/figures.py).
    .venv/bin/python bench/bench_dataset.py --towns Town01 --out /tmp/bench-dataset   # a CARLA train/val town
"""

from __future__ import annotations

import argparse
import json
import os
import re
import resource
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from figures import Figures
from rich.console import Console
from rich.table import Table

ROOT = Path(__file__).resolve().parents[1]
CARLA = ROOT.parent / "shared" / "maps" / "carla"
AGOS = [sys.executable, "-m", "agos.deploy.cli"]
FULL_EPISODES = 5_500 + 2_200
GOAL = 1.2


@dataclass
class Command:
    """One timed ``agos`` command."""

    label: str
    wall_s: float
    cpu_s: float
    """User + system CPU of every process the command started (RUSAGE_CHILDREN around it)."""
    other_load: float
    """Share of the machine other processes used meanwhile (0-1)."""
    rate_per_min: float | None
    """The orchestrator's episodes/min, first lease to last stored episode (start-up excluded)."""
    world_cpu_s: float
    run_dir: Path
    out_dir: Path | None = None
    extra: dict[str, Any] = field(default_factory=dict)


def machine_busy_s() -> float:
    """CPU seconds this machine has spent in processes so far (/proc/stat: user, nice, system)."""
    fields = [int(x) for x in Path("/proc/stat").read_text().split("\n", 1)[0].split()[1:]]
    return (fields[0] + fields[1] + fields[2]) / os.sysconf("SC_CLK_TCK")


def timed(label: str, argv: list[str], run_dir: Path, out_dir: Path | None, console: Console) -> Command:
    """Run ``agos argv``; its wall, its processes' CPU, the machine's other load and the run's rate."""
    console.print(f"$ agos {' '.join(argv)}", highlight=False, soft_wrap=True)
    env = {**os.environ, "COLUMNS": "200"}  # rich writes the summary lines unwrapped
    before, busy0, self0 = resource.getrusage(resource.RUSAGE_CHILDREN), machine_busy_s(), time.process_time()
    t0 = time.monotonic()
    done = subprocess.run([*AGOS, *argv], capture_output=True, text=True, env=env)
    wall = time.monotonic() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (after.ru_utime + after.ru_stime) - (before.ru_utime + before.ru_stime)
    others = max(0.0, machine_busy_s() - busy0 - cpu - (time.process_time() - self0))
    if done.returncode != 0:
        raise SystemExit(f"agos {argv[0]} exited with {done.returncode}:\n{done.stdout[-3000:]}\n{done.stderr[-3000:]}")
    rate = re.search(r"throughput: ([0-9.]+) episodes/min", done.stdout)
    world_cpu = sum(float(m.group(1)) for log in (run_dir / "logs").glob("world-*.log")
                    for m in re.finditer(r"exits: CPU ([0-9.]+) s", log.read_text(errors="replace")))
    cores = len(os.sched_getaffinity(0))
    return Command(label, wall, cpu, others / (wall * cores), float(rate.group(1)) if rate else None, world_cpu,
                   run_dir, out_dir)


def sample_split(towns: list[str], per_difficulty: int, seed: int, look: str, work: Path, console: Console, *,
                 easy_only: bool = False) -> Path:
    """One split file: ``per_difficulty`` episodes of each difficulty on each town (``easy_only``: that
    many easy episodes)."""
    lines: list[str] = []
    for name in towns:
        town = str(CARLA / f"{name}.xodr") if (CARLA / f"{name}.xodr").exists() else name
        part = work / f"sample-{name}.jsonl"
        count = ["--difficulty", "easy", "-n", str(per_difficulty)] if easy_only else ["--per-difficulty", str(per_difficulty)]
        argv = ["episodes", "sample", "--town", town, *count, "--seed", str(seed), "--look", look, "--out", str(part)]
        console.print(f"$ agos {' '.join(argv)}", highlight=False, soft_wrap=True)
        subprocess.run([*AGOS, *argv], check=True, capture_output=True, text=True)
        lines += [x for x in part.read_text().splitlines() if x.strip()]
    split = work / "split.jsonl"
    split.write_text("\n".join(lines) + "\n")
    return split


def config_hash(run_dir: Path) -> str:
    return json.loads((run_dir / "run.json").read_text())["config_hash"]


def decisions_by_episode(run_dir: Path) -> dict[str, tuple[int, int]]:
    from agos.evaluator.store import ResultStore

    with ResultStore(run_dir / "results.sqlite", create=False) as store:
        return {r.episode_id: (r.decisions_uav, r.decisions_ugv) for r in store.records()}


def tree_bytes(root: Path) -> int:
    return sum(p.stat().st_size for p in root.rglob("*") if p.is_file())


# ----- the in-process breakdown -----------------------------------------------------------------
class Stopwatch:
    """Seconds spent inside wrapped functions, per name (wall clock, this process only)."""

    def __init__(self) -> None:
        self.s: dict[str, float] = {}

    def wrap(self, name: str, fn: Callable[..., Any]) -> Callable[..., Any]:
        def timed_call(*args: Any, **kwargs: Any) -> Any:
            t0 = time.perf_counter()
            try:
                return fn(*args, **kwargs)
            finally:
                self.s[name] = self.s.get(name, 0.0) + time.perf_counter() - t0

        return timed_call


def breakdown(split: Path, look: str, capture_every_m: float, work: Path) -> dict[str, float]:
    """Play ``split`` in this process with the dataset writer, timing render, plan, write and assemble."""
    from agos.agents.dataset.writer import DatasetWriter
    from agos.deploy.dataset.build import Assembler
    from agos.env import Env
    from agos.runtime.episode_config import EpisodeConfig, ToolConfig
    from agos.world import expert
    from agos.world.episodes.sampling import read_episodes
    from agos.world.sim import capture, engine, observations, sensors
    from agos.world.sim.scene import Scene
    from agos.world.towns.asset import town_for

    expert.install()
    watch = Stopwatch()
    # The world's rendering (plus encoding) of what the dataset stores; the expert's planning, which
    # runs inside the first observation, is timed on its own and taken out of it.
    patches = [(engine, "observe"), (capture, "views_along"), (sensors, "six_views"), (sensors, "reference_views"),
               (observations, "_expert_planner"), (DatasetWriter, "_write_decision")]
    saved = [(module, name, getattr(module, name)) for module, name in patches]
    for module, name, fn in saved:
        setattr(module, name, watch.wrap(name, fn))
    out = work / "inprocess"
    specs = read_episodes(split)
    assembler = Assembler(out, {s.episode_id: s for s in specs}, Console(quiet=True))
    config = EpisodeConfig(tools=ToolConfig(expert=True), capture_every_m=capture_every_m, look=look)  # type: ignore[arg-type]
    scenes: dict[str, tuple[Any, Any]] = {}
    t0 = time.perf_counter()
    decisions = 0
    try:
        for spec in specs:
            if spec.asset_sha256 not in scenes:
                town = town_for(spec.town.generator, spec.town.seed, spec.asset_sha256, town_id=spec.town.town_id)
                scenes[spec.asset_sha256] = (town, Scene(town.layout, look=look))
            town, scene = scenes[spec.asset_sha256]
            with Env(spec, config, illegal="wait", run_id="bench", worker_id="bench", scene=scene, town=town) as env:
                record = env.play({r: DatasetWriter(r, out) for r in ("uav", "ugv")})
            decisions += record.decisions_uav + record.decisions_ugv
            ta = time.perf_counter()
            problem = assembler.assemble(record)
            watch.s["assemble"] = watch.s.get("assemble", 0.0) + time.perf_counter() - ta
            if problem:
                raise SystemExit(f"{spec.episode_id}: {problem}")
    finally:
        for module, name, fn in saved:
            setattr(module, name, fn)
    s = watch.s
    plan = s.get("_expert_planner", 0.0)
    render = s.get("observe", 0.0) - plan + s.get("views_along", 0.0) + s.get("six_views", 0.0) + \
        s.get("reference_views", 0.0)
    return {"episodes": len(specs), "decisions": decisions, "total_s": time.perf_counter() - t0, "plan_s": plan,
            "render_s": render, "write_s": s.get("_write_decision", 0.0), "assemble_s": s.get("assemble", 0.0),
            "bytes": tree_bytes(out / "episodes")}


# ----- the report -------------------------------------------------------------------------------
def report(console: Console, split: Path, n: int, pairs: list[tuple[Command, Command]], builds: list[Command],
           parts: dict[str, float] | None, cores: int) -> dict[str, Any]:
    ratio_table = Table(title=f"Image step: the same views rendered bare vs rendered and written ({n} episodes)",
                        title_justify="left")
    for col in ("measure", "bare", "+ written", "ratio", "goal", "other load"):
        ratio_table.add_column(col, justify="left" if col == "measure" else "right")
    for k, (base, one) in enumerate(pairs, start=1):
        which = f" (pair {k})" if len(pairs) > 1 else ""
        ratio_table.add_row(f"agos eval (capture on) vs agos dataset build, 1 worker{which}: wall s", f"{base.wall_s:.1f}",
                            f"{one.wall_s:.1f}", f"{one.wall_s / base.wall_s:.2f}x", f"<= {GOAL}x",
                            f"{100 * base.other_load:.0f} / {100 * one.other_load:.0f} %")
        ratio_table.add_row("  the same: CPU s of all processes", f"{base.cpu_s:.1f}", f"{one.cpu_s:.1f}",
                            f"{one.cpu_s / base.cpu_s:.2f}x", "", "")
    wall_ratio = statistics.median(one.wall_s / base.wall_s for base, one in pairs)
    cpu_ratio = statistics.median(one.cpu_s / base.cpu_s for base, one in pairs)
    if len(pairs) > 1:
        ratio_table.add_row("median over the pairs: wall / CPU", "", "", f"{wall_ratio:.2f}x / {cpu_ratio:.2f}x", "", "")
    base = pairs[0][0]
    result: dict[str, Any] = {"episodes": n, "split": str(split), "cores": cores,
                              "pairs": [{"baseline": _doc(b), "build": _doc(o)} for b, o in pairs],
                              "builds": [_doc(b) for b in builds], "ratio_wall": wall_ratio, "ratio_cpu": cpu_ratio}
    if parts is not None:
        bare, written = parts["render_s"], parts["render_s"] + parts["write_s"] + parts["assemble_s"]
        ratio_table.add_row("in-process: render (+ encode) s vs + write + assemble s", f"{bare:.1f}", f"{written:.1f}",
                            f"[bold]{written / bare:.2f}x", f"<= {GOAL}x", "")
        result["breakdown"] = {**parts, "ratio": written / bare}
    console.print(ratio_table)
    if parts is not None:
        per = 1000.0 / max(1, parts["decisions"])
        console.print(f"in-process, per decision ({parts['decisions']} decisions, {parts['total_s']:.1f} s in all): render "
                      f"{parts['render_s'] * per:.0f} ms, expert planning {parts['plan_s'] * per:.0f} ms, writing "
                      f"{parts['write_s'] * per:.0f} ms, assembling {parts['assemble_s'] * per:.0f} ms; "
                      f"{parts['bytes'] / 1e6:.1f} MB written", highlight=False, soft_wrap=True)

    tp = Table(title=f"Build throughput on {n} episodes and the projection to {FULL_EPISODES:,} "
                     "(5,500 train + 2,200 val)", title_justify="left")
    for col in ("workers", "wall s", "episodes/h (wall)", "episodes/h (steady)", "CPU s/episode", "world share",
                "other load", f"{FULL_EPISODES:,} eps: time", "disk"):
        tp.add_column(col, justify="right")
    for b in builds:
        per_hour_wall = 3600.0 * n / b.wall_s
        per_hour = 60.0 * b.rate_per_min if b.rate_per_min else per_hour_wall
        size = b.extra["bytes_all"] / n * FULL_EPISODES
        tp.add_row(str(b.extra["workers"]), f"{b.wall_s:.1f}", f"{per_hour_wall:.0f}", f"{per_hour:.0f}",
                   f"{b.cpu_s / n:.1f}", f"{100 * b.world_cpu_s / b.cpu_s:.0f} %", f"{100 * b.other_load:.0f} %",
                   f"{FULL_EPISODES / per_hour:.0f} h", f"{size / 1e9:.0f} GB")
    console.print(tp)
    one_ep = statistics.mean(b.cpu_s / n for b in builds)
    console.print(f"per episode: {builds[0].extra['bytes_episodes'] / n / 1e6:.2f} MB of episode files, "
                  f"{builds[0].extra['bytes_all'] / n / 1e6:.2f} MB with the export and the run; {one_ep:.1f} CPU s "
                  f"(all processes) -> {FULL_EPISODES * one_ep / 3600:.0f} CPU h for {FULL_EPISODES:,}, "
                  f"{FULL_EPISODES * one_ep / 3600 / cores:.0f} h on {cores} cores if the cores are the limit. "
                  "Steady: first lease to last stored episode (start-up excluded); with few episodes per worker "
                  "the last episode's tail weighs on it.", highlight=False, soft_wrap=True)
    baseline_rate = 3600.0 * n / base.wall_s
    console.print(f"baseline (agos eval, capture on, 1 worker): {baseline_rate:.0f} episodes/h (wall); config hash "
                  f"{base.extra['config_hash']} = the builds'; every run took the same decisions", highlight=False)
    if max(c.other_load for c in [*(x for pair in pairs for x in pair), *builds]) > 0.05:
        console.print("[yellow]other processes used more than 5 % of the machine during a command: walls are not clean; "
                      "the CPU ratio is the steadier figure")
    return result


def _doc(c: Command) -> dict[str, Any]:
    return {"label": c.label, "wall_s": c.wall_s, "cpu_s": c.cpu_s, "world_cpu_s": c.world_cpu_s,
            "other_load": c.other_load, "rate_per_min": c.rate_per_min, **c.extra}


def main(argv: list[str] | None = None) -> int:
    from agos.deploy.run.launcher import free_port

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--towns", nargs="+", default=["grid-s7"],
                    help="procedural ids or CARLA names in ../shared/maps/carla (Town01 ... : the paper's train/val towns)")
    ap.add_argument("--per-difficulty", type=int, default=1, help="episodes per difficulty and town (default 1)")
    ap.add_argument("--seed", type=int, default=3)
    ap.add_argument("--look", choices=["rich", "flat"], default="rich", help="the build's look (default rich, its default)")
    ap.add_argument("--capture-every", type=float, default=10.0, metavar="M")
    ap.add_argument("--workers", type=int, nargs="+", default=[1, 2], help="world workers of the builds (default 1 2)")
    ap.add_argument("--repeat", type=int, default=1,
                    help="baseline / 1-worker build pairs, alternated (default 1; the ratio is their median)")
    ap.add_argument("--no-breakdown", action="store_true", help="skip the in-process breakdown")
    ap.add_argument("--quick", action="store_true", help="smoke test: one easy episode of grid-s7")
    ap.add_argument("--work", type=Path, help="where the splits, runs and datasets go (default a fresh temporary dir)")
    ap.add_argument("--out", type=Path, help="also write bench_dataset.json here")
    ap.add_argument("--json", action="store_true", help="also print each figure as a BENCH-FIGURE line")
    args = ap.parse_args(argv)
    if args.quick:
        args.towns, args.per_difficulty = ["grid-s7"], 1
    console = Console(width=160)
    cores = len(os.sched_getaffinity(0))
    work = args.work or Path(tempfile.mkdtemp(prefix="agos-bench-dataset-"))
    work.mkdir(parents=True, exist_ok=True)
    t_start = time.monotonic()
    split = sample_split(args.towns, args.per_difficulty, args.seed, args.look, work, console, easy_only=args.quick)
    n = sum(1 for x in split.read_text().splitlines() if x.strip())
    each = "easy" if args.quick else "per difficulty"
    console.print(f"[bold]bench_dataset[/]: {n} episodes ({', '.join(args.towns)}, {args.per_difficulty} {each}, "
                  f"seed {args.seed}, look {args.look}, views every {args.capture_every:g} m), {cores} cores; "
                  f"work dir {work}", highlight=False)

    cfg = work / "capture.toml"  # the world as a build configures it: capture on, the build's look
    cfg.write_text(f'[world]\ncapture_every_m = {args.capture_every}\nlook = "{args.look}"\n')

    def run_eval(tag: str) -> Command:
        run_dir = work / f"eval-w1{tag}"
        shutil.rmtree(run_dir, ignore_errors=True)
        c = timed("eval, capture on, 1 worker",
                  ["eval", "--config", str(cfg), "--split", str(split), "--policy", "expert", "--workers", "1",
                   "--run-dir", str(run_dir), "--port", str(free_port(7447))], run_dir, None, console)
        c.extra["config_hash"] = config_hash(run_dir)
        return c

    def run_build(workers: int, tag: str) -> Command:
        out = work / f"build-w{workers}{tag}"
        shutil.rmtree(out, ignore_errors=True)  # a fresh directory: nothing to resume
        run_dir = out / f"dataset-{_sha8(split)}"
        c = timed(f"dataset build, {workers} workers",
                  ["dataset", "build", "--split", str(split), "--out", str(out), "--workers", str(workers),
                   "--look", args.look, "--capture-every", str(args.capture_every), "--port", str(free_port(7447))],
                  run_dir, out, console)
        manifest = json.loads((out / "manifest.json").read_text())
        c.extra.update(workers=workers, config_hash=config_hash(run_dir), bytes_episodes=manifest["counts"]["bytes"],
                       bytes_all=tree_bytes(out), images=manifest["counts"]["images"])
        if manifest["counts"]["episodes"] != n:
            raise SystemExit(f"{out}: {manifest['counts']['episodes']} of {n} episodes assembled")
        return c

    # Baseline and 1-worker build in pairs, alternating which goes first (a slow spell of a shared
    # machine then lands on both sides in turn); the ratio is the median over the pairs.
    pairs: list[tuple[Command, Command]] = []
    for k in range(args.repeat):
        tag = f"-{k + 1}" if args.repeat > 1 else ""
        if k % 2 == 0:
            base = run_eval(tag)
            pairs.append((base, run_build(1, tag)))
        else:
            build = run_build(1, tag)
            pairs.append((run_eval(tag), build))
    builds = [pairs[0][1]] + [run_build(w, "") for w in args.workers if w != 1]
    for base, build in pairs:
        if build.extra["config_hash"] != base.extra["config_hash"]:
            raise SystemExit(f"the build's configuration {build.extra['config_hash']} is not the baseline's "
                             f"{base.extra['config_hash']}: the views would differ")
    records = [decisions_by_episode(c.run_dir) for c in [*(b for b, _ in pairs), *builds]]
    if any(r != records[0] for r in records):
        raise SystemExit("the runs' episodes took different decisions: not the same views")

    parts = None
    if not args.no_breakdown:
        console.print("in-process breakdown: the same episodes with the dataset writer ...", highlight=False)
        parts = breakdown(split, args.look, args.capture_every, work)
    result = report(console, split, n, pairs, builds, parts, cores)
    figures = Figures(args.json)
    figures.add(f"dataset build vs agos eval (capture on), 1 worker, {n} episode{'s' if n > 1 else ''}: CPU", result["ratio_cpu"],
                f"{result['ratio_cpu']:.2f}x", f"<= {GOAL}x", result["ratio_cpu"] <= GOAL)
    if "breakdown" in result:
        ratio = result["breakdown"]["ratio"]
        figures.add("in-process: render + write + assemble vs render", ratio, f"{ratio:.2f}x", f"<= {GOAL}x", ratio <= GOAL)
    console.print(f"bench wall {time.monotonic() - t_start:.0f} s", highlight=False)
    if args.out:
        args.out.mkdir(parents=True, exist_ok=True)
        (args.out / "bench_dataset.json").write_text(json.dumps(result, indent=1, default=str) + "\n")
    return 0


def _sha8(path: Path) -> str:
    import hashlib

    return hashlib.sha256(path.read_bytes()).hexdigest()[:8]


if __name__ == "__main__":
    sys.exit(main())
