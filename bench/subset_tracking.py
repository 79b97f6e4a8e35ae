"""How far a stratified subset's success rate tracks the full split's (``agos episodes subset``,
world/episodes/subset.py; docs/DATASET.md, "A quick subset").

Reads a finished run of a whole split (its records) and, for each of ``--seeds`` seeds, the subset
``agos episodes subset SPLIT --per-cell N --seed S`` would draw, then the subset's SR from the same
records: the episodes are the split's own and deterministic, so a run of the subset would give
those records. Prints the full split's overall SR (the macro mean over difficulties, as
``agos metrics``), the subset's for seed 0, and over all seeds the mean and largest absolute
difference, the share of seeds within 5 and 10 points, and how often the full SR lies inside the
subset's Wilson 95 % interval (pooled over the subset's episodes).

    .venv/bin/python bench/subset_tracking.py RUN_DIR SPLIT.jsonl [--per-cell 3] [--seeds 1000]
"""

from __future__ import annotations

import argparse
import statistics
from pathlib import Path

from agos.evaluator.comparison import wilson_interval
from agos.evaluator.metrics import aggregate
from agos.evaluator.summary import read_run
from agos.world.episodes.files import read_episodes
from agos.world.episodes.subset import draw


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("run", type=Path, help="a run directory of the whole split")
    parser.add_argument("split", type=Path, help="the split's episode file")
    parser.add_argument("--per-cell", type=int, default=3)
    parser.add_argument("--seeds", type=int, default=1000)
    args = parser.parse_args()
    episodes = read_episodes(args.split)
    records = {s.episode_id: s for s in read_run(args.run) if s.status == "finished"}
    missing = [e.episode_id for e in episodes if e.episode_id not in records]
    if missing:
        print(f"{args.run} has no finished record of {len(missing)} episodes of {args.split}, e.g. {missing[0]}")
        return 2
    full = aggregate([records[e.episode_id] for e in episodes])["overall"].SR or 0.0
    diffs, inside = [], 0
    seed0 = 0.0
    for seed in range(args.seeds):
        chosen = [records[episodes[k].episode_id] for k in draw(episodes, per_cell=args.per_cell, seed=seed)]
        sr = aggregate(chosen)["overall"].SR or 0.0
        seed0 = sr if seed == 0 else seed0
        diffs.append(abs(sr - full))
        low, high = wilson_interval(sum(e.success for e in chosen), len(chosen)) or (0.0, 1.0)
        inside += low <= full <= high
    n = len(chosen)
    print(f"{args.run.name}: full split {len(episodes)} episodes, SR {100 * full:.1f} %; subset {n} episodes "
          f"({args.per_cell} per cell), seed 0: SR {100 * seed0:.1f} % (off by {100 * abs(seed0 - full):.1f} points)")
    print(f"over {args.seeds} seeds: |subset SR - full SR| mean {100 * statistics.mean(diffs):.1f} points, "
          f"largest {100 * max(diffs):.1f}; within 5 points {100 * sum(d <= 0.05 + 1e-9 for d in diffs) / len(diffs):.0f} %, "
          f"within 10 points {100 * sum(d <= 0.10 + 1e-9 for d in diffs) / len(diffs):.0f} %; full SR inside the "
          f"subset's Wilson 95 % interval for {100 * inside / args.seeds:.0f} % of seeds")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
