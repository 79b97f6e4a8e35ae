"""Oracle sweep (issue 18, item 2): the oracle policy on sampled episodes of every procedural town
and every imported CARLA town, at every difficulty. Every sampled episode is solvable, so every
failure is a bug in the oracle, the solvability check or the sampler.

Stages, each kept in OUT so a rerun repeats only what is missing (a changed seed, count or town
list starts afresh; so does ``--fresh``, needed after a change to the sampler): import the CARLA
towns (``agos map import``), sample ``--per-cell`` episodes per town and difficulty (exactly what
``agos episodes sample --town T --per-difficulty N --seed S`` writes), then play them with the
oracle in-process in ``--workers`` processes under the run configuration ``agos eval --policy
oracle`` would use (the same records, without a router: ARCHITECTURE §7). Prints a table per town
and difficulty (episodes, SR %, SPL %, decisions) and every failure; exits 1 when any episode
failed. 360 episodes (``--per-cell 10``) take about 11 min on 2 cores.

    .venv/bin/python bench/oracle_sweep.py --per-cell 3 --workers 2 --out /tmp/oracle-sweep
    # the same episodes through the whole stack (one CARLA town per run until world/sim/worker.py
    # keys its scene cache by asset hash: see tests/test_oracle_sweep_cases.py):
    .venv/bin/agos eval --split /tmp/oracle-sweep/episodes.jsonl --policy oracle --workers 2 --run-dir runs/oracle-sweep
    .venv/bin/agos metrics runs/oracle-sweep --by town
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn
from rich.table import Table

from agos.runtime.process import interruptible_imap

ROOT = Path(__file__).resolve().parents[1]
CARLA = ROOT.parent / "shared" / "maps" / "carla"
DIFFICULTIES = ("easy", "mid", "hard")
POLICIES = {"uav": "oracle", "ugv": "oracle"}

_WORKER: dict[str, Any] = {}


def _town(name: str, towns_dir: Path):
    """A procedural town by id, or an imported CARLA town (imported into ``towns_dir`` once)."""
    from agos.world.towns.asset import freeze, open_town, save_town
    from agos.world.towns.procedural import TOWNS

    if name in TOWNS:
        return open_town(name)
    asset = towns_dir / name
    if not (asset / "asset.msgpack").exists():
        from agos.world.towns.imported import imported_layout

        save_town(freeze(imported_layout(CARLA / f"{name}.xodr")), asset)
    return open_town(asset)  # also puts it in the asset cache, where workers find it by hash


def _scene(key: tuple, town_of: Callable[[], Any], look: str) -> tuple[Any, Any]:
    """The worker's (town, scene) for ``key``, built by ``town_of`` in ``look`` when the key changes
    (one scene at a time per worker process)."""
    from agos.world.sim.scene import Scene

    if _WORKER.get("key") != key:
        if "scene" in _WORKER:
            _WORKER["scene"].close()
        town = town_of()
        _WORKER.update(key=key, town=town, scene=Scene(town.layout, look=look))
    return _WORKER["town"], _WORKER["scene"]


def _sample(job: tuple[str, str, int, int, str, str]) -> tuple[str, str, list[str], float]:
    """Worker: ``n`` episodes of one town and difficulty (as ``agos episodes sample`` samples them)."""
    from agos.runtime.codec import to_json
    from agos.world.episodes.sampling import sample_episode

    name, difficulty, n, seed, towns_dir, look = job
    start = time.perf_counter()
    town, scene = _scene(("name", name, look), lambda: _town(name, Path(towns_dir)), look)
    lines = [to_json(sample_episode(town, scene, difficulty, i, seed=seed, stream=DIFFICULTIES.index(difficulty))).decode()  # type: ignore[arg-type]
             for i in range(n)]
    return name, difficulty, lines, time.perf_counter() - start


def _play(job: tuple[str, str]) -> str:
    """Worker: one episode with the oracle in-process; returns its record as JSON."""
    from agos import Env
    from agos.agents.registry import make_policy
    from agos.runtime.codec import from_json, to_json
    from agos.runtime.episode_config import EpisodeConfig
    from agos.runtime.schemas import EpisodeSpec
    from agos.world.towns.asset import town_for

    config_json, episode_json = job
    spec = from_json(episode_json, EpisodeSpec)
    config = EpisodeConfig.model_validate_json(config_json)
    town, scene = _scene(("sha", spec.asset_sha256, config.look),
                         lambda: town_for(spec.town.generator, spec.town.seed, spec.asset_sha256,
                                          town_id=spec.town.town_id), config.look)
    with Env(spec, config, run_id="oracle-sweep", scene=scene, town=town) as env:
        record = env.play({r: make_policy(POLICIES[r], r) for r in ("uav", "ugv")})
    return to_json(record).decode()


def _progress(console: Console) -> Progress:
    return Progress(TextColumn("[bold]{task.description}"), BarColumn(), MofNCompleteColumn(), TextColumn("{task.fields[note]}"),
                    TimeElapsedColumn(), TimeRemainingColumn(), console=console)


def main(argv: list[str] | None = None) -> int:
    from agos.deploy.run.configure import run_episode_config
    from agos.runtime.settings import load_config
    from agos.world.towns.procedural import TOWNS

    carla = sorted(p.stem for p in CARLA.glob("*.xodr")) if CARLA.exists() else []
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--towns", nargs="*", default=[*TOWNS, *carla], help="procedural ids and CARLA names (default: all)")
    ap.add_argument("--per-cell", type=int, default=3, help="episodes per town and difficulty")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--out", type=Path, default=Path("/tmp/oracle-sweep"))
    ap.add_argument("--replay", action="store_true", help="play the episodes again (keep the sampled ones)")
    ap.add_argument("--fresh", action="store_true", help="sample and play afresh (after a change to the sampler)")
    args = ap.parse_args(argv)
    console = Console()
    out: Path = args.out
    out.mkdir(parents=True, exist_ok=True)
    (out / "towns").mkdir(exist_ok=True)
    stamp = {"towns": args.towns, "per_cell": args.per_cell, "seed": args.seed}
    stamp_file, episodes_file, records_file = out / "sweep.json", out / "episodes.jsonl", out / "records.jsonl"
    if args.fresh or not stamp_file.exists() or json.loads(stamp_file.read_text()) != stamp:
        for f in (episodes_file, records_file, out / ".sampled.jsonl"):
            f.unlink(missing_ok=True)
        stamp_file.write_text(json.dumps(stamp))
    if args.replay:
        records_file.unlink(missing_ok=True)

    timings: dict[str, float] = {}
    # 1. import (the CARLA towns, once, in this process: seconds)
    t0 = time.perf_counter()
    for name in args.towns:
        if name not in TOWNS:
            _town(name, out / "towns")
    timings["import"] = time.perf_counter() - t0

    # 2. sample: one job per town and difficulty; finished cells are kept in .sampled.jsonl
    t0 = time.perf_counter()
    sampled_file = out / ".sampled.jsonl"
    done = {(r["town"], r["difficulty"]): r["lines"] for r in map(json.loads, sampled_file.read_text().splitlines())} \
        if sampled_file.exists() else {}
    config = run_episode_config(load_config(), policies=POLICIES)  # episodes are sampled in the run's look
    jobs = [(t, d, args.per_cell, args.seed, str(out / "towns"), config.look) for t in args.towns for d in DIFFICULTIES
            if (t, d) not in done]
    with _progress(console) as bar:
        task = bar.add_task("sampling", total=len(args.towns) * len(DIFFICULTIES), note="", completed=len(done))
        for name, difficulty, lines, seconds in interruptible_imap(_sample, jobs, args.workers):
            done[(name, difficulty)] = lines
            with sampled_file.open("a") as fh:
                fh.write(json.dumps({"town": name, "difficulty": difficulty, "lines": lines}) + "\n")
            bar.update(task, advance=1, note=f"{name} {difficulty} {seconds:.0f} s")
    episodes = [line for t in args.towns for d in DIFFICULTIES for line in done[(t, d)]]
    episodes_file.write_text("\n".join(episodes) + "\n")
    timings["sample"] = time.perf_counter() - t0

    # 3. play with the oracle; finished records are appended to records.jsonl at once
    t0 = time.perf_counter()
    records = {json.loads(line)["episode_id"]: json.loads(line) for line in records_file.read_text().splitlines()} \
        if records_file.exists() else {}
    todo = [(config.model_dump_json(), line) for line in episodes if json.loads(line)["episode_id"] not in records]
    with _progress(console) as bar:
        task = bar.add_task("oracle", total=len(episodes), completed=len(episodes) - len(todo), note="")
        failed = 0
        for line in interruptible_imap(_play, todo, args.workers):
            rec = json.loads(line)
            records[rec["episode_id"]] = rec
            with records_file.open("a") as fh:
                fh.write(line + "\n")
            failed += not rec["success"]
            bar.update(task, advance=1, note=f"[red]{failed} failed" if failed else "")
    timings["play"] = time.perf_counter() - t0
    return report(console, args.towns, [records[json.loads(e)["episode_id"]] for e in episodes], timings)


def report(console: Console, towns: list[str], records: list[dict], timings: dict[str, float]) -> int:
    from agos.evaluator.metrics import spl
    from agos.evaluator.summary import EpisodeSummary

    table = Table(title="oracle per town and difficulty")
    for col in ("town", "difficulty", "episodes", "SR %", "SPL %", "decisions (mean)"):
        table.add_column(col, justify="left" if col in ("town", "difficulty") else "right")

    def cells(recs: list[dict]) -> list[str]:
        if not recs:
            return ["0", "-", "-", "-"]
        sr = 100 * sum(r["success"] for r in recs) / len(recs)
        spls = [spl(EpisodeSummary.model_validate(r)) for r in recs]
        decisions = sum(r["decisions_uav"] + r["decisions_ugv"] for r in recs) / len(recs)
        colour = "green" if sr == 100 else "red"
        return [str(len(recs)), f"[{colour}]{sr:.1f}", f"{100 * sum(spls) / len(spls):.1f}", f"{decisions:.1f}"]

    for t in towns:
        mine = [r for r in records if r["episode_id"].startswith(f"{t}-")]
        for d in DIFFICULTIES:
            table.add_row(t if d == DIFFICULTIES[0] else "", d, *cells([r for r in mine if r["difficulty"] == d]))
        table.add_row("", "all", *cells(mine), style="bold", end_section=True)
    for d in DIFFICULTIES:
        table.add_row("all towns" if d == DIFFICULTIES[0] else "", d, *cells([r for r in records if r["difficulty"] == d]))
    table.add_row("", "all", *cells(records), style="bold")
    console.print(table)
    failures = [r for r in records if not r["success"]]
    for r in failures:
        console.print(f"[red]FAILED[/] {r['episode_id']}: {r['termination']}, {r['final_distance_m']:.1f} m from the "
                      f"target, decisions uav {r['decisions_uav']} ugv {r['decisions_ugv']}, "
                      f"rejection {r['confirm_rejection']}")
    walls = sorted(r["wall_time_s"] for r in records)
    console.print(f"{len(records)} episodes, {len(failures)} failed; import {timings['import']:.0f} s, sample "
                  f"{timings['sample']:.0f} s, play {timings['play']:.0f} s (per episode median "
                  f"{walls[len(walls) // 2] if walls else 0:.1f} s, max {walls[-1] if walls else 0:.1f} s)")
    return 1 if failures else 0


if __name__ == "__main__":
    sys.exit(main())
