"""The validity table (docs/VALIDITY.md): how far each policy gets on one split, per difficulty, with
95% confidence intervals, so that what a single cue buys is printed beside what the full
description buys.

Runs ``agos eval --split SPLIT --policy P`` for every policy (the VLM methods against the offline
stand-in, ``--vlm-standin``), each in its own run directory under OUT; a run whose results already
hold every episode is not run again, so a stopped table resumes. Then prints one row per policy:
SR % per difficulty with its Wilson 95% interval, SR pooled over easy and mid (the paint-only goal
of issue 29 is at most 40 % there), and the run's overall SR (the mean of the difficulties, as
``agos eval`` prints it). ``--markdown`` prints the table as docs/VALIDITY.md holds it.

    .venv/bin/agos episodes sample --town grid-s7 --per-difficulty 10 --seed 29 --out /tmp/v/grid-s7.jsonl
    ...  # parks-s23 and Town01 alike, then cat the three files into /tmp/v/validity90.jsonl
    .venv/bin/python bench/validity.py --split /tmp/v/validity90.jsonl --out /tmp/v/runs --workers 2 --markdown
"""

from __future__ import annotations

import argparse
import json
import sqlite3
import subprocess
import sys
from pathlib import Path

import numpy as np
from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn
from rich.table import Table
from scipy.stats import binomtest

ROOT = Path(__file__).resolve().parents[1]
AGOS = [sys.executable, "-m", "agos.deploy.cli"]
DIFFICULTIES = ("easy", "mid", "hard")
POLICIES: dict[str, list[str]] = {
    "random": ["--policy", "random"],
    "paint-only": ["--policy", "paint-only"],
    "heuristic": ["--policy", "heuristic"],
    "oracle": ["--policy", "oracle"],
    "expert": ["--policy", "expert"],
    "agos-agent (stand-in)": ["--policy", "agos-agent", "--vlm-standin"],
    "baseline (stand-in)": ["--policy", "baseline", "--vlm-standin"],
}


def outcomes(results: Path) -> dict[str, list[bool]]:
    """difficulty -> success of each stored episode (empty when the run stored none)."""
    out: dict[str, list[bool]] = {d: [] for d in DIFFICULTIES}
    if not results.exists():
        return out
    with sqlite3.connect(results) as db:
        for (record,) in db.execute("SELECT record_json FROM episodes"):
            r = json.loads(record)
            if r.get("status") == "finished":
                out[r["difficulty"]].append(bool(r["success"]))
    return out


def interval(wins: int, n: int) -> str:
    """``SR [lo, hi]`` in percent, Wilson's 95% interval; ``--`` without episodes."""
    if n == 0:
        return "--"
    ci = binomtest(wins, n).proportion_ci(confidence_level=0.95, method="wilson")
    return f"{100 * wins / n:.0f} [{100 * ci.low:.0f}, {100 * ci.high:.0f}]"


def draw_same_paint_view(split: Path, out: Path) -> str:
    """The nadir view, at the UAV node nearest the target, of the first mid episode of ``split`` with
    the most other vehicles of the target's paint in that view: the target ringed green, the others
    of its paint red. Returns what it drew."""
    import cv2

    from agos.runtime.episode_config import CameraConfig
    from agos.world.episodes.sampling import read_episodes
    from agos.world.sim import sensors
    from agos.world.sim.episode_vehicles import add_episode_vehicles
    from agos.world.sim.scene import Scene
    from agos.world.towns.asset import Town, town_for

    cam = CameraConfig()
    best = None
    towns: dict[str, Town] = {}  # asset hash -> town: built once, not once an episode
    for spec in read_episodes(split):
        if spec.difficulty != "mid" or spec.town.generator == "opendrive":
            continue
        if spec.asset_sha256 not in towns:
            towns[spec.asset_sha256] = town_for(spec.town.generator, spec.town.seed, spec.asset_sha256,
                                                town_id=spec.town.town_id)
        town = towns[spec.asset_sha256]
        tx, ty = spec.target.position_world_m[:2]
        node = min(town.uav_grid.nodes.values(),
                   key=lambda n: (n.position_world_m[0] - tx) ** 2 + (n.position_world_m[1] - ty) ** 2)
        slots = {s.slot_id: s.position_world_m for s in town.layout.slots}
        same = [slots[p.slot_id] for p in town.layout.parked if p.colour == spec.target.colour
                and abs(slots[p.slot_id][0] - node.position_world_m[0]) < 44
                and abs(slots[p.slot_id][1] - node.position_world_m[1]) < 44]
        if best is None or len(same) > len(best[3]):
            best = (spec, town, node, same)
    if best is None:
        return "no mid episode of a procedural town in the split"
    spec, town, node, same = best
    with Scene(town.layout, look="rich") as scene:
        add_episode_vehicles(scene, spec)
        shot = sensors.nadir(scene, node.position_world_m[:2], node.position_world_m[2], cam)
    image = cv2.cvtColor(np.ascontiguousarray(shot.render.rgb[:, :, :3]), cv2.COLOR_RGB2BGR)
    for xy, colour in [(spec.target.position_world_m[:2], (0, 200, 0)), *((p, (0, 0, 230)) for p in same)]:
        pixel = sensors.ground_to_pixel(tuple(xy), shot.world_from_camera, shot.intrinsics)
        if pixel is not None:
            cv2.circle(image, (int(pixel[0]), int(pixel[1])), 16, colour, 2)
    out.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(out), image)
    return (f"{out}: {spec.episode_id} from {node.node_id}, target {spec.target.model} {spec.target.colour} "
            f"(green) and {len(same)} other vehicles of its paint (red)")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--split", type=Path, required=True, help="episode file (JSONL)")
    ap.add_argument("--out", type=Path, required=True, help="parent of the runs' directories")
    ap.add_argument("--workers", default="2", help="agos eval --workers")
    ap.add_argument("--only", help="comma-separated policies of the table to run (default every one)")
    ap.add_argument("--markdown", action="store_true", help="print the table as Markdown")
    ap.add_argument("--figure", type=Path, help="also draw the UAV's view of a mid episode of the split whose target "
                                                 "shares its paint with other vehicles in view (a PNG)")
    args = ap.parse_args()
    console = Console(soft_wrap=True)
    if not args.split.exists():
        console.print(f"[red]{args.split}: no such episode file; sample one first (see this script's docstring)")
        return 2
    if args.figure is not None:
        console.print(f"figure: {draw_same_paint_view(args.split, args.figure)}", highlight=False)
    total = sum(1 for line in args.split.read_text().splitlines() if line.strip())
    chosen = list(POLICIES) if not args.only else [p.strip() for p in args.only.split(",")]
    unknown = [p for p in chosen if p not in POLICIES]
    if unknown:
        console.print(f"[red]--only: unknown policies {unknown}; known: {', '.join(POLICIES)}")
        return 2
    args.out.mkdir(parents=True, exist_ok=True)
    columns = (TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn())
    try:
        with Progress(*columns, console=console) as progress:
            task = progress.add_task("policies", total=len(chosen))
            for name in chosen:
                run_dir = args.out / name.split(" ")[0]
                done = sum(len(v) for v in outcomes(run_dir / "results.sqlite").values())
                if done < total:
                    progress.update(task, description=f"{name}: {total} episodes")
                    if run_dir.exists():  # a resumed run keeps its split, policies and stand-in
                        argv = [*AGOS, "eval", "--resume", str(run_dir), "--workers", args.workers]
                    else:
                        argv = [*AGOS, "eval", "--split", str(args.split), *POLICIES[name], "--workers", args.workers,
                                "--run-dir", str(run_dir)]
                    with (args.out / f"{run_dir.name}.log").open("a") as log:
                        code = subprocess.run(argv, cwd=ROOT, stdout=log, stderr=subprocess.STDOUT).returncode
                    if code != 0:
                        console.print(f"[red]{name}: agos eval exited {code}; see {args.out / run_dir.name}.log")
                        return 1
                progress.advance(task)
    except KeyboardInterrupt:
        console.print(f"[yellow]stopped; run the same command again to resume ({args.out})")
        return 130
    rows = []
    for name in chosen:
        got = outcomes(args.out / name.split(" ")[0] / "results.sqlite")
        cells = [interval(sum(got[d]), len(got[d])) for d in DIFFICULTIES]
        easy_mid = got["easy"] + got["mid"]
        overall = [sum(got[d]) / len(got[d]) for d in DIFFICULTIES if got[d]]
        rows.append([name, *cells, interval(sum(easy_mid), len(easy_mid)),
                     f"{100 * sum(overall) / len(overall):.1f}" if overall else "--"])
    header = ["policy", *(f"{d} SR % [95% CI]" for d in DIFFICULTIES), "easy+mid pooled", "overall SR %"]
    if args.markdown:
        print("| " + " | ".join(header) + " |")
        print("|" + "---|" * len(header))
        for row in rows:
            print("| " + " | ".join(row) + " |")
        return 0
    table = Table(*header, title=f"{args.split.name}: {total} episodes")
    for row in rows:
        table.add_row(*row)
    console.print(table)
    return 0


if __name__ == "__main__":
    sys.exit(main())
