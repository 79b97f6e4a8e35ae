"""The report commands' parsers: figures from a run's records (deploy/reports/) and the
evaluator's metrics, comparisons and tables (evaluator/report_commands.py runs those).

    agos plot episode|compare ...   trajectory figures from a run's records
    agos metrics PATH [--json]      every metric of a run (run dir, sqlite or JSONL summaries), tokens, cost, latency
    agos compare RUN_A RUN_B        paired differences with bootstrap intervals and tests
    agos report RUN... --out DIR    run cards, paper-style tables with SR intervals, cost, the stage-wise plot
    agos vlm-cache stats DIR        what a cache of model calls holds: hits, misses, tokens, size
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

from agos.deploy.cli.common import Command, by_subcommand, price_flags


def _add_plot(sub: Any) -> None:
    plot = sub.add_parser("plot", help="trajectory figures of episodes from a run's records")
    what = plot.add_subparsers(dest="plot_what", required=True)
    one = what.add_parser("episode", help="one episode: map, both paths, candidates, the target, CONFIRM/REJECT")
    one.add_argument("run", type=Path, help="run directory (runs/<run>) or its results.sqlite")
    one.add_argument("episode", nargs="?", help="episode id (default: the run's first episode with a finished record)")
    one.add_argument("--out", type=Path, required=True, help="PNG file")
    two = what.add_parser("compare", help="two runs (two policies) on the same episode, side by side")
    two.add_argument("run_a", type=Path)
    two.add_argument("run_b", type=Path)
    two.add_argument("episode", nargs="?", help="episode id (default: the first both runs finished)")
    two.add_argument("--out", type=Path, required=True)
    two.add_argument("--labels", nargs=2, metavar=("A", "B"), help="panel titles (default: each run's policies)")


def _plot(args: argparse.Namespace) -> int:
    from agos.deploy.reports.plot import PlotError, plot_compare, plot_episode

    try:
        if args.plot_what == "episode":
            out = plot_episode(args.run, args.episode, args.out)
        else:
            out = plot_compare(args.run_a, args.run_b, args.episode, args.out, labels=args.labels)
    except PlotError as exc:
        print(f"plot error: {exc}", file=sys.stderr)
        return 2
    print(f"wrote {out}")
    return 0


_MIXED = "pool episodes run under different episode configurations (refused by default)"


def _add_metrics(sub: Any) -> None:
    metrics = sub.add_parser("metrics", help="every metric of a run per difficulty (or town)")
    metrics.add_argument("path", type=Path, help="runs/<run>, a results.sqlite, or a JSONL file of episode summaries")
    metrics.add_argument("--json", action="store_true", help="print JSON (rates as fractions, distances in m)")
    metrics.add_argument("--allow-mixed", action="store_true", help=_MIXED)
    metrics.add_argument("--by", choices=["difficulty", "town"], default="difficulty")
    price_flags(metrics)  # default: the prices agos eval was given (run.json)


def _add_compare(sub: Any) -> None:
    comp = sub.add_parser("compare", help="paired comparison of two runs on their shared episodes")
    comp.add_argument("run_a", type=Path)
    comp.add_argument("run_b", type=Path)
    comp.add_argument("--resamples", type=int, default=10_000)
    comp.add_argument("--seed", type=int, default=0)
    comp.add_argument("--allow-mixed", action="store_true", help=_MIXED)
    comp.add_argument("--json", action="store_true")


def _add_report(sub: Any) -> None:
    report = sub.add_parser("report", help="paper-style tables (md, csv, tex), outcomes and the stage-wise PNG")
    report.add_argument("runs", type=Path, nargs="+")
    report.add_argument("--out", type=Path, required=True)
    report.add_argument("--allow-mixed", action="store_true", help=_MIXED)
    report.add_argument("--labels", nargs="+", help="one label per run; a leading '+' marks an agent variant row")
    price_flags(report)  # default: each run's own (run.json)


def _evaluator_cli(args: argparse.Namespace) -> int:
    """``agos metrics``, ``compare`` and ``report``: the evaluator's command runner."""
    from agos.evaluator import report_commands

    return report_commands.run(args)


def _add_vlm_cache(sub: Any) -> None:
    cache = sub.add_parser("vlm-cache", help="a cache of recorded model calls (--vlm-cache DIR; docs/AGENTS.md)")
    what = cache.add_subparsers(dest="cache_what", required=True)
    stats = what.add_parser("stats", help="per model: requests, replies, hits, misses, tokens; the cache's size")
    stats.add_argument("dir", type=Path, help="the directory given to --vlm-cache")


def _vlm_cache_stats(args: argparse.Namespace) -> int:
    from rich.console import Console

    from agos.agents.vlm.cache import CacheError, cache_stats, size_line, stats_table

    try:
        stats = cache_stats(args.dir)
    except CacheError as exc:
        print(f"vlm-cache error: {exc}", file=sys.stderr)
        return 2
    console = Console(soft_wrap=True)
    console.print(stats_table(stats, title=f"VLM cache {args.dir}"))
    console.print(size_line(stats), highlight=False)
    return 0


PLOT = Command(("plot",), _add_plot, _plot)
METRICS = Command(("metrics",), _add_metrics, _evaluator_cli)
COMPARE = Command(("compare",), _add_compare, _evaluator_cli)
REPORT = Command(("report",), _add_report, _evaluator_cli)
VLM_CACHE = Command(("vlm-cache",), _add_vlm_cache, by_subcommand("cache_what", {"stats": _vlm_cache_stats}))
