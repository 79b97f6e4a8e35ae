"""The same episodes with the EGL renderer and with TinyRenderer (issue 39, item 1): a correctness
check, not a timing. Target visibility and the CONFIRM checker read instance pixels, so a renderer
that drops, adds or misplaces objects changes outcomes: the oracle must succeed on every episode with
both renderers, and the heuristic's outcomes are printed side by side (they may differ: its detector
reads RGB, and shading differs between the two).

Episodes are sampled as ``agos episodes sample --town TOWN --per-difficulty N --seed S`` samples them
(TinyRenderer), or read from ``--split``; each renderer plays them all in its own process (the two
at once on two cores), in-process (``agos.Env``, the records ``agos eval`` would store). Exits 1 when
the oracle fails an episode with either renderer. On the 2-core VM (llvmpipe, no GPU), one episode
per difficulty on ``grid-s7`` (three episodes) takes about 1.5 min, two (six) about 3 min.

    .venv/bin/python bench/egl_outcomes.py [--town grid-s7] [--per-difficulty 1] [--seed 0] [--look rich]
    .venv/bin/python bench/egl_outcomes.py --split one.jsonl
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

from rich.console import Console
from rich.table import Table

from agos.runtime.process import interruptible_imap

RENDERERS = ("tiny", "egl")
POLICIES = ("oracle", "heuristic")
DIFFICULTIES = ("easy", "mid", "hard")


def _sample(town_name: str, per_difficulty: int, seed: int, look: str) -> list[str]:
    from agos.runtime.codec import to_json
    from agos.world.episodes.sampling import sample_episode
    from agos.world.sim.scene import Scene
    from agos.world.towns.asset import open_town

    town = open_town(town_name)
    with Scene(town.layout, look=look) as scene:
        return [to_json(sample_episode(town, scene, d, i, seed=seed, stream=DIFFICULTIES.index(d))).decode()  # type: ignore[arg-type]
                for d in DIFFICULTIES for i in range(per_difficulty)]


def _play(job: tuple[str, str, list[str]]) -> tuple[str, list[dict], float]:
    """Worker: every episode with every policy under one renderer (one scene for all)."""
    import msgspec

    from agos import Env, episode_config
    from agos.agents.registry import make_policy
    from agos.runtime.codec import from_json
    from agos.runtime.schemas import EpisodeSpec
    from agos.world.sim.scene import Scene
    from agos.world.towns.asset import town_for

    renderer, look, lines = job
    specs = [from_json(line, EpisodeSpec) for line in lines]
    first = specs[0]
    town = town_for(first.town.generator, first.town.seed, first.asset_sha256, town_id=first.town.town_id)
    start = time.process_time()
    out = []
    with Scene(town.layout, look=look, renderer=renderer) as scene:
        for spec in specs:
            for policy in POLICIES:
                config = episode_config(policies=policy, look=look, renderer=renderer)
                with Env(spec, config, run_id=f"egl-outcomes-{renderer}", scene=scene, town=town) as env:
                    record = env.play({r: make_policy(policy, r) for r in ("uav", "ugv")})
                out.append({"policy": policy, **msgspec.to_builtins(record)})
    return renderer, out, time.process_time() - start


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--town", default="grid-s7")
    ap.add_argument("--per-difficulty", type=int, default=1)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--look", default="rich", choices=("flat", "rich"))
    ap.add_argument("--split", type=Path, help="play this episode file (one town) instead of sampling")
    ap.add_argument("--json", type=Path, help="also write every record here (JSONL)")
    args = ap.parse_args(argv)
    console = Console(width=150)
    lines = ([line for line in args.split.read_text().splitlines() if line.strip()] if args.split
             else _sample(args.town, args.per_difficulty, args.seed, args.look))
    results: dict[str, list[dict]] = {}
    for renderer, records, cpu in interruptible_imap(_play, [(r, args.look, lines) for r in RENDERERS], len(RENDERERS)):
        results[renderer] = records
        console.print(f"{renderer}: {len(records)} episodes played in {cpu:.0f} s of CPU")
    if args.json:
        with args.json.open("w") as fh:
            for renderer in RENDERERS:
                for rec in results[renderer]:
                    fh.write(json.dumps({"renderer_setting": renderer, **rec}) + "\n")
    return report(console, results)


def _outcome(rec: dict) -> str:
    """Success, how it ended, decisions (UAV + UGV) and the UGV's final distance to the target."""
    return (f"{'ok' if rec['success'] else 'FAIL'} {rec['termination']}, "
            f"{rec['decisions_uav']}+{rec['decisions_ugv']} dec, {rec['final_distance_m']:.1f} m")


def report(console: Console, results: dict[str, list[dict]]) -> int:
    table = Table(title="the same episodes, TinyRenderer | EGL")
    for col in ("episode", "policy", "tiny", "egl", "same"):
        table.add_column(col)
    failed = 0
    summary: dict[tuple[str, str], int] = {}
    for tiny, egl in zip(results["tiny"], results["egl"], strict=True):
        assert (tiny["episode_id"], tiny["policy"]) == (egl["episode_id"], egl["policy"])
        assert (tiny["renderer"], egl["renderer"]) == ("pybullet-tiny", "pybullet-egl")
        same = (tiny["success"], tiny["termination"]) == (egl["success"], egl["termination"])
        table.add_row(tiny["episode_id"], tiny["policy"], _outcome(tiny), _outcome(egl), "yes" if same else "no")
        for renderer, rec in (("tiny", tiny), ("egl", egl)):
            summary[(tiny["policy"], renderer)] = summary.get((tiny["policy"], renderer), 0) + rec["success"]
            failed += tiny["policy"] == "oracle" and not rec["success"]
    console.print(table)
    n = len(results["tiny"]) // len(POLICIES)
    for policy in POLICIES:
        console.print(f"{policy}: SR tiny {summary[(policy, 'tiny')]}/{n}, egl {summary[(policy, 'egl')]}/{n}")
    if failed:
        console.print(f"[red]the oracle failed {failed} episode(s)")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
