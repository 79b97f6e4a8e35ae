"""``agos metrics``, ``agos compare`` and ``agos report``: offline analysis of stored runs."""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import asdict
from pathlib import Path

from rich.console import Console

from agos.evaluator.card_reader import card_lines, run_meta, run_prices
from agos.evaluator.comparison import compare
from agos.evaluator.cost import TOTAL, PriceError, PriceTable, cost_by_group, price_table, unpriced
from agos.evaluator.human_row import LABEL as HUMAN_LABEL
from agos.evaluator.human_row import is_human_run
from agos.evaluator.metrics import aggregate, as_json, group_key
from agos.evaluator.paper_report import COST_HEADER, RunResults, cost_cells, cost_rows, sr_rows, write_report
from agos.evaluator.pooling import require_one_configuration
from agos.evaluator.summary import EpisodeSummary, SummaryError, read_run
from agos.evaluator.table import comparison_table, metrics_table, rows_table


def _console() -> Console:
    # Wide tables stay readable when piped into a file.
    return Console(width=None if sys.stdout.isatty() else 160)


def _read(path: Path, allow_mixed: bool) -> list[EpisodeSummary]:
    """A run's summaries, refused when they mix episode configurations (unless ``allow_mixed``)."""
    summaries = read_run(path)
    require_one_configuration(summaries, where=str(path), allow_mixed=allow_mixed)
    return summaries


def _prices(args: argparse.Namespace, path: Path, episodes: list[EpisodeSummary]) -> PriceTable | None:
    """The prices of the run at ``path``: the command's flags, else the run's run.json (what ``agos eval``
    was given), else none. Warns on stderr, one line, about a model with tokens that is not priced."""
    prices = price_table(prices_file=args.prices, price_in=args.price_in, price_out=args.price_out) \
        or run_prices(run_meta(path), where=str(path))
    models = {u.model for e in episodes for u in e.usage if u.prompt_tokens or u.completion_tokens}
    missing = unpriced(models, prices)
    if missing and prices is not None:
        print(f"warning: {path}: no price for model {', '.join(missing)} in {prices.source}; its cost is --",
              file=sys.stderr)
    elif missing:
        print(f"note: {path}: no prices, so cost is --; give --price-in/--price-out USD per million tokens or "
              "--prices FILE.toml", file=sys.stderr)
    return prices


def run(args: argparse.Namespace) -> int:
    try:
        if args.command == "metrics":
            episodes = _read(args.path, args.allow_mixed)
            summaries = aggregate(episodes, args.by)
            prices = _prices(args, args.path, episodes)
            costs = cost_by_group(episodes, prices, [g for g in summaries if g != "overall"], group_key(args.by))
            if args.json:
                out = as_json(summaries)
                for group, values in out.items():  # the overall row's tokens and cost: the run's totals
                    values.update(costs[TOTAL if group == "overall" else group].as_dict())
                print(json.dumps(out, indent=2))
            else:
                console = _console()
                console.print(metrics_table(summaries, title=str(args.path), group=args.by))
                rows = [[group, *cost_cells(c)] for group, c in costs.items()]
                console.print(rows_table([args.by, *COST_HEADER[2:]], rows, title=f"tokens, cost and latency "
                                         f"(prices: {prices.describe() if prices else 'none'})"))
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
            runs = []
            for label, path, h in zip(labels, args.runs, human, strict=True):
                episodes = _read(path, args.allow_mixed)
                runs.append(RunResults(label, episodes, human=h, prices=_prices(args, path, episodes),
                                       card=card_lines(run_meta(path), label=label)))
            console = _console()
            for r in runs:
                console.print("\n".join(r.card or []), highlight=False, markup=False)
            console.print(rows_table(*sr_rows(runs), title="success rate, % [Wilson 95% interval]"))
            console.print(rows_table(*cost_rows(runs), title="tokens, cost and latency per decision", by_first=True))
            for written in write_report(runs, args.out):
                print(written)
            return 0
    except (SummaryError, PriceError, ValueError) as exc:
        print(f"{args.command} error: {exc}", file=sys.stderr)
        return 2
    raise AssertionError(args.command)
