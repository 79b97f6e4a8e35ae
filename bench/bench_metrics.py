"""Benchmark: `agos metrics` on 100,000 episode summaries vs merely parsing the same file.

Target (issue 4): computing every metric per difficulty (parse + validate + aggregate) takes at
most 3x the time of parsing the JSONL with ``json.loads``, measured in the same run.

    .venv/bin/python bench/bench_metrics.py [--episodes 100000] [--repeats 3]

``--quick`` (``make bench``): 20,000 summaries, best of 2. ``--json``: also one machine-readable
line per figure (bench/figures.py).
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

from figures import Figures

from agos.evaluator.metrics import aggregate
from agos.evaluator.summary import read_jsonl

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))  # the synthetic summaries are a test helper
from support.synthetic import synthetic_summaries, write_jsonl


def parse_only(path: Path) -> int:
    with path.open("rb") as fh:
        return sum(1 for line in fh if json.loads(line) is not None)


def metrics(path: Path) -> int:
    summaries = aggregate(read_jsonl(path), "difficulty")
    return summaries["overall"].n


def best_of(fn, path: Path, repeats: int) -> tuple[float, int]:
    times, result = [], 0
    for _ in range(repeats):
        start = time.perf_counter()
        result = fn(path)
        times.append(time.perf_counter() - start)
    return min(times), result


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--episodes", type=int, default=100_000)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--quick", action="store_true", help="20,000 summaries, best of 2")
    parser.add_argument("--json", action="store_true", help="also print each figure as a BENCH-FIGURE line")
    args = parser.parse_args()
    if args.quick:
        args.episodes, args.repeats = 20_000, 2
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "summaries.jsonl"
        write_jsonl(path, synthetic_summaries(args.episodes, seed=0))
        size_mb = path.stat().st_size / 1e6
        t_parse, n1 = best_of(parse_only, path, args.repeats)
        t_metrics, n2 = best_of(metrics, path, args.repeats)
    assert n1 == n2 == args.episodes
    ratio = t_metrics / t_parse
    print(f"episodes          {args.episodes:,} ({size_mb:.1f} MB JSONL)")
    print(f"json.loads only   {t_parse:.3f} s (baseline, best of {args.repeats})")
    print(f"agos metrics      {t_metrics:.3f} s (parse, validate, all metrics, per difficulty)")
    print(f"ratio             {ratio:.2f}x  (target <= 3.00x: {'met' if ratio <= 3.0 else 'NOT met'})")
    Figures(args.json).add(f"agos metrics vs json.loads, {args.episodes:,} summaries", ratio,
                           f"{ratio:.2f}x ({t_metrics:.2f} vs {t_parse:.2f} s)", "<= 3.0x", ratio <= 3.0)


if __name__ == "__main__":
    main()
