"""``agos metrics``, ``agos compare`` and ``agos report``: offline analysis of stored runs."""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import asdict
from pathlib import Path

from rich.console import Console

from agos.evaluator.human_row import LABEL as HUMAN_LABEL
from agos.evaluator.human_row import is_human_run
from agos.evaluator.metrics import aggregate, as_json
from agos.evaluator.pooling import require_one_configuration
from agos.evaluator.reports import RunResults, write_report
from agos.evaluator.stats import compare
from agos.evaluator.summary import EpisodeSummary, SummaryError, read_run
from agos.evaluator.table import comparison_table, metrics_table


def _console() -> Console:
    # Wide tables stay readable when piped into a file.
    return Console(width=None if sys.stdout.isatty() else 160)


def _read(path: Path, allow_mixed: bool) -> list[EpisodeSummary]:
    """A run's summaries, refused when they mix episode configurations (unless ``allow_mixed``)."""
    summaries = read_run(path)
    require_one_configuration(summaries, where=str(path), allow_mixed=allow_mixed)
    return summaries


def run(args: argparse.Namespace) -> int:
    try:
        if args.command == "metrics":
            summaries = aggregate(_read(args.path, args.allow_mixed), args.by)
            if args.json:
                print(json.dumps(as_json(summaries), indent=2))
            else:
                _console().print(metrics_table(summaries, title=str(args.path), group=args.by))
            return 0
        if args.command == "compare":
            run_a, run_b = _read(args.run_a, args.allow_mixed), _read(args.run_b, args.allow_mixed)
            result = compare(run_a, run_b, resamples=args.resamples, seed=args.seed)
            for warning in result.warnings:
                print(f"warning: {warning}", file=sys.stderr)
            if args.json:
                print(json.dumps(asdict(result), indent=2))
            else:
                console = _console()
                console.print(f"A = {args.run_a}\nB = {args.run_b}\n{result.n_pairs} paired episodes "
                              f"({', '.join(f'{k} {v}' for k, v in result.per_level.items())}); 95% bootstrap "
                              f"intervals within difficulty levels, {result.resamples} resamples, seed {result.seed}; "
                              "paired permutation test", highlight=False)
                console.print(comparison_table(result))
                o = result.outcomes
                console.print(f"outcomes: both succeed {o['both_succeed']}, only A {o['only_a']}, only B {o['only_b']}, "
                              f"neither {o['neither']}; exact sign test on SR p = "
                              f"{'n/a' if result.sign_test_p is None else f'{result.sign_test_p:.4f}'}")
            return 0
        if args.command == "report":
            human = [is_human_run(p) for p in args.runs]
            labels = args.labels or [(HUMAN_LABEL if sum(human) == 1 else f"{HUMAN_LABEL} ({p.name})") if h else p.name
                                     for p, h in zip(args.runs, human, strict=True)]
            if len(labels) != len(args.runs):
                print(f"report error: {len(labels)} labels for {len(args.runs)} runs", file=sys.stderr)
                return 2
            runs = [RunResults(label, _read(path, args.allow_mixed), human=h)
                    for label, path, h in zip(labels, args.runs, human, strict=True)]
            for path in write_report(runs, args.out):
                print(path)
            return 0
    except (SummaryError, ValueError) as exc:
        print(f"{args.command} error: {exc}", file=sys.stderr)
        return 2
    raise AssertionError(args.command)
