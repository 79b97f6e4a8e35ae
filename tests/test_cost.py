"""Tokens, cost and latency (evaluator/cost.py), Wilson intervals, run cards (evaluator/card_reader.py) and
what ``agos metrics``/``agos report`` print of them, from hand-made records: unit tests, no processes."""

from __future__ import annotations

import csv
import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from agos.evaluator.card_reader import card_lines
from agos.evaluator.comparison import wilson_interval
from agos.evaluator.cost import (
    PriceError,
    cost_by_group,
    cost_of,
    cost_summary,
    flat_prices,
    percentile,
    price_table,
    prices_from_json,
    read_prices,
)
from agos.evaluator.summary import EpisodeSummary, UsageSummary, read_jsonl
from agos.runtime.schemas import DecisionTrace, StoredTrace
from agos.runtime.traces import trace_usage


def trace(model: str, prompt: int | None, completion: int | None, latency_s: float, **kw: Any) -> dict[str, Any]:
    return {"policy": "agos-agent", "model": model, "stage": "search", "prompt_sha256": "0" * 64, "image_bytes": {},
            "raw_reply": "{}", "parsed_action": "WAIT", "fallback": False, "latency_s": latency_s,
            "prompt_tokens": prompt, "completion_tokens": completion, "http_attempts": 1, "role": "uav",
            "decision_index": 1, **kw}


def summary(episode_id: str, difficulty: str, success: bool, traces: list[dict[str, Any]], *, status: str = "finished",
            usage: list[dict[str, Any]] | None = None) -> dict[str, Any]:
    out: dict[str, Any] = dict(
        episode_id=episode_id, difficulty=difficulty, success=success, ground_observed=success, n_confirm=int(success),
        ugv_path_length_m=10.0, shortest_path_length_m=10.0, final_distance_m=1.0, uav_budget=80,
        uav_first_visible_step=None, candidates=[], decisions_uav=len(traces), decisions_ugv=0, status=status,
        decision_traces=traces)
    if usage is not None:
        out["usage"] = usage
    return out


def test_prices_and_the_cost_of_tokens(tmp_path: Path) -> None:
    flat = flat_prices(2.0, 8.0)
    assert cost_of([UsageSummary("any", 1_000_000, 500_000)], flat) == pytest.approx(6.0)  # 2 + 0.5 x 8
    assert cost_of([], flat) == 0.0 and cost_of([UsageSummary("m", 0, 0)], None) == 0.0  # no tokens cost nothing
    assert cost_of([UsageSummary("m", 10, 1)], None) is None  # tokens without a price: undefined, never 0
    table = tmp_path / "prices.toml"
    table.write_text('["gpt-x"]\nin_usd_per_mtok = 2.5\nout_usd_per_mtok = 10\n\n'
                     '["*"]\nin_usd_per_mtok = 0.1\nout_usd_per_mtok = 0.2\n')
    prices = read_prices(table)
    usage = [UsageSummary("gpt-x", 2_000, 100), UsageSummary("local", 10_000, 1_000)]
    assert cost_of(usage, prices) == pytest.approx((2_000 * 2.5 + 100 * 10 + 10_000 * 0.1 + 1_000 * 0.2) / 1e6)
    assert prices_from_json(prices.as_json(), where="run.json") == prices  # as run.json keeps it
    only = prices_from_json({"models": {"gpt-x": {"in_usd_per_mtok": 1, "out_usd_per_mtok": 1}}}, where="w")
    assert cost_of(usage, only) is None  # "local" is not priced


@pytest.mark.parametrize(("text", "says"), [
    ('["m"]\nin_usd_per_mtok = 1\n', "model 'm': no out_usd_per_mtok"),
    ('["m"]\nin_usd_per_mtok = 1\nout_usd_per_mtok = -2\n', "out_usd_per_mtok: -2 is no price"),
    ('["m"]\nin_usd_per_mtok = 1\nout_usd_per_mtok = 2\nin = 3\n', "unknown key 'in'"),
    ('m = 3\n', "model 'm': not a table"),
    ('', "no prices"),
    ('["m"\n', "not valid TOML"),
])
def test_a_bad_price_file_is_one_line_naming_it(tmp_path: Path, text: str, says: str) -> None:
    path = tmp_path / "p.toml"
    path.write_text(text)
    with pytest.raises(PriceError) as info:
        read_prices(path)
    assert says in str(info.value) and str(path) in str(info.value) and "\n" not in str(info.value)


def test_price_flags_are_both_or_a_file() -> None:
    assert price_table(prices_file=None, price_in=None, price_out=None) is None
    with pytest.raises(PriceError, match="--price-out is missing"):
        price_table(prices_file=None, price_in=1.0, price_out=None)
    with pytest.raises(PriceError, match="not both"):
        price_table(prices_file=Path("p.toml"), price_in=1.0, price_out=1.0)
    with pytest.raises(PriceError, match="--price-in: nan is no price"):
        price_table(prices_file=None, price_in=float("nan"), price_out=1.0)


def test_percentiles_match_numpy() -> None:
    rng = np.random.default_rng(4)
    for n in (1, 2, 7, 100):
        values = list(rng.exponential(1.0, n))
        for q in (50, 95):
            assert percentile(values, q) == pytest.approx(float(np.percentile(values, q)))
    assert percentile([], 50) is None


def test_usage_per_model_from_traces() -> None:
    traces = [StoredTrace(role="uav", decision_index=k, **{f: getattr(t, f) for f in t.__struct_fields__})
              for k, t in enumerate([DecisionTrace(policy="p", model=m, stage="s", prompt_sha256="", image_bytes={},
                                                   raw_reply=None, parsed_action="WAIT", fallback=False, http_attempts=a,
                                                   prompt_tokens=pt, completion_tokens=ct)
                                     for m, a, pt, ct in [("a", 1, 100, 10), ("b", 3, 50, None), ("a", 2, 7, 3)]], 1)]
    usage = trace_usage(traces)
    assert [(u.model, u.decisions, u.http_attempts, u.prompt_tokens, u.completion_tokens) for u in usage] == [
        ("a", 2, 3, 107, 13), ("b", 1, 3, 50, 0)]
    assert trace_usage([]) == []


def test_tokens_cost_and_latency_per_group(tmp_path: Path) -> None:
    rows = [
        summary("e1", "easy", True, [trace("m", 1000, 100, 0.5), trace("m", 2000, 200, 1.5)]),
        summary("e2", "easy", False, [trace("m", 3000, None, 2.5)]),
        summary("m1", "mid", True, [trace("m", 500, 50, 0.1)]),
        summary("m2", "mid", True, [], status="world_crashed"),  # counted, no tokens, not a success
        # a record with usage totals: they are read instead of totalling the traces
        summary("h1", "hard", False, [trace("m", 1, 1, 4.0)], usage=[{"model": "m", "prompt_tokens": 9000,
                                                                      "completion_tokens": 900, "decisions": 1}]),
    ]
    path = tmp_path / "s.jsonl"
    path.write_text("".join(json.dumps(r) + "\n" for r in rows))
    episodes = read_jsonl(path)
    assert episodes[0].usage == (UsageSummary("m", 3000, 300),) and episodes[0].decision_latencies_s == (0.5, 1.5)
    assert episodes[4].usage == (UsageSummary("m", 9000, 900),)
    costs = cost_by_group(episodes, flat_prices(1.0, 10.0), ["easy", "mid", "hard"], lambda e: e.difficulty)
    easy = costs["easy"]
    assert (easy.episodes, easy.successes, easy.decisions, easy.prompt_tokens, easy.completion_tokens) == (2, 1, 3, 6000, 300)
    assert easy.cost_usd == pytest.approx((6000 + 3000) / 1e6)
    assert easy.cost_per_success_usd == pytest.approx(easy.cost_usd)
    assert easy.tokens_per_decision == pytest.approx(2100) and easy.tokens_per_episode == pytest.approx(3150)
    assert (easy.latency_p50_s, easy.latency_p95_s) == pytest.approx((1.5, 2.4))
    mid = costs["mid"]
    assert (mid.episodes, mid.successes, mid.decisions) == (2, 1, 1)  # the crashed episode is counted, never a success
    assert costs["hard"].cost_per_success_usd is None  # no success: undefined
    total = costs["total"]
    assert (total.episodes, total.prompt_tokens, total.completion_tokens) == (5, 15500, 1250)
    assert total.cost_usd == pytest.approx((15500 + 12500) / 1e6)
    assert total.cost_per_success_usd == pytest.approx(total.cost_usd / 2)
    assert total.latency_p50_s == pytest.approx(float(np.percentile([0.5, 1.5, 2.5, 0.1, 4.0], 50)))
    assert cost_summary(episodes, None).cost_usd is None and cost_summary([], None).latency_p95_s is None


def test_records_without_traces_cost_nothing() -> None:
    scripted = EpisodeSummary.model_validate(summary("e", "easy", True, []))
    c = cost_summary([scripted], None)
    assert (c.prompt_tokens, c.cost_usd, c.cost_per_success_usd, c.latency_p50_s, c.tokens_per_decision) == (
        0, 0.0, 0.0, None, None)


def test_wilson_interval_by_hand() -> None:
    # 5 of 10: p = 0.5, z = 1.96: (0.5 + 0.19207 -+ 1.96 sqrt(0.025 + 0.0096)) / 1.38415
    low, high = wilson_interval(5, 10) or (0, 0)
    assert (low, high) == pytest.approx((0.236593, 0.763407), abs=1e-6)
    assert wilson_interval(0, 10) == pytest.approx((0.0, 0.277533), abs=1e-6)
    assert wilson_interval(10, 10) == pytest.approx((0.722467, 1.0), abs=1e-6)
    assert wilson_interval(24, 30) == pytest.approx((0.627, 0.905), abs=1e-3)
    assert wilson_interval(0, 0) is None
    with pytest.raises(ValueError):
        wilson_interval(3, 2)


CARD_RUN = {
    "run_id": "r1", "created_utc": "2025-01-01T00:00:00+00:00", "episodes": 3, "policies": {"uav": "agos-agent",
                                                                                             "ugv": "agos-agent"},
    "comm": "ideal", "timing_mode": "lockstep", "config_hash": "abc123def456",
    "provenance": {"agos": "0.1.0", "commit": "0123456789abcdef", "dirty": True, "lock_sha256": "f" * 64,
                   "python": "3.11.9", "packages": {"eclipse-zenoh": "1.5.1", "httpx": "0.28.1", "numpy": "2.3.1",
                                                    "pybullet": "3.2.7"}},
    "card": {"model": "agos-standin", "endpoint": "http://127.0.0.1:9/v1",
             "models_answer": [{"id": "agos-standin", "object": "model"}],
             "sampling": {"temperature": 0.0, "max_tokens": 512}, "prompts": {"sha256": "9" * 64, "file": "prompts.txt"},
             "cache": {"mode": "record", "dir": "/tmp/cache"}, "split": {"file": "val.jsonl", "sha256": "8" * 64},
             "episodes_sha256": "7" * 64},
    "prices": {"source": "--price-in/--price-out", "models": {"*": {"in_usd_per_mtok": 1.0, "out_usd_per_mtok": 4.0}}},
    "caps": {"max_cost_usd": 2.5, "max_tokens": None},
}


def test_card_lines_name_what_made_the_run() -> None:
    text = "\n".join(card_lines(CARD_RUN, label="A"))
    for part in ("run r1", "commit 0123456789ab (dirty tree)", "eclipse-zenoh 1.5.1", "pybullet 3.2.7", "httpx 0.28.1",
                 "model: agos-standin at http://127.0.0.1:9/v1; /models: agos-standin", "temperature 0.0",
                 "prompts: sha256 9999999999999999 (prompts.txt)", "model-call cache: record /tmp/cache",
                 "val.jsonl sha256 8888888888888888", "* $1/$4 per M tokens", "max cost usd 2.5"):
        assert part in text, part
    old = {k: v for k, v in CARD_RUN.items() if k not in ("card", "prices", "caps")}
    assert "made before agos recorded one" in "\n".join(card_lines(old, label="B"))
    assert card_lines(None, label="C") == ["C: no run.json (a file of records): no card"]


def _write_run(run_dir: Path, rows: list[dict[str, Any]], meta: dict[str, Any]) -> Path:
    from agos.evaluator.store import ResultStore
    from agos.runtime.schemas import EpisodeRecord

    run_dir.mkdir(parents=True)
    (run_dir / "run.json").write_text(json.dumps(meta))
    with ResultStore(run_dir / "results.sqlite") as store:
        for r in rows:
            store.add(EpisodeRecord(
                run_id="r1", episode_id=r["episode_id"], difficulty=r["difficulty"], status=r["status"],
                termination="confirmed" if r["success"] else "budget_exhausted", success=r["success"],
                ground_observed=r["success"], n_confirm=int(r["success"]), ugv_path_length_m=10.0,
                shortest_path_length_m=10.0, final_distance_m=1.0, uav_budget=80, uav_first_visible_step=None,
                candidates=[], decisions_uav=len(r["decision_traces"]), decisions_ugv=0, sim_time_s=1.0, wall_time_s=1.0,
                worker_id="w", town_id="grid-s7", asset_sha256="0" * 64, seed=1, renderer="tiny",
                decision_traces=[StoredTrace(**t) for t in r["decision_traces"]]))
    return run_dir


def test_report_shows_the_card_sr_intervals_tokens_cost_and_latency(tmp_path: Path, agos) -> None:
    rows = [summary("e1", "easy", True, [trace("agos-standin", 1000, 100, 0.5)]),
            summary("e2", "easy", False, [trace("agos-standin", 3000, 300, 1.5)]),
            summary("m1", "mid", True, [trace("agos-standin", 2000, 200, 0.25)])]
    run = _write_run(tmp_path / "r1", rows, CARD_RUN)
    result = agos("report", run, "--out", tmp_path / "out")
    assert result.returncode == 0, result.stderr
    out = result.stdout
    assert out.index("commit 0123456789ab") < out.index("success rate")  # the card above the tables
    assert "50.0 [9.5, 90.5]" in out and "100.0 [20.7, 100.0]" in out  # SR with Wilson intervals
    for name in ("card.md", "main.md", "main.csv", "main.tex", "cost.md", "cost.csv"):
        assert str(tmp_path / "out" / name) in out
    assert "prompts: sha256" in (tmp_path / "out" / "card.md").read_text()
    with open(tmp_path / "out" / "main.csv", newline="") as fh:
        (main,) = list(csv.DictReader(fh))
    assert (main["Easy SR"], main["Easy SR CI low"], main["Easy SR CI high"]) == ("50.0", "9.5", "90.5")
    assert "{\\scriptsize[9.5, 90.5]}" in (tmp_path / "out" / "main.tex").read_text()
    with open(tmp_path / "out" / "cost.csv", newline="") as fh:
        cost = {r["Difficulty"]: r for r in csv.DictReader(fh)}
    total = cost["total"]  # prices from run.json: $1 in, $4 out per M tokens
    assert (total["prompt tok"], total["completion tok"], total["cost USD"]) == ("6,000", "600", "0.0084")
    assert (total["USD/success"], total["p50 latency s"], total["p95 latency s"]) == ("0.0042", "0.500", "1.400")
    assert cost["easy"]["tok/decision"] == "2,200"
    flags = agos("report", run, "--out", tmp_path / "out2", "--price-in", "0", "--price-out", "1000")
    assert flags.returncode == 0 and "| r1 | total | 3 | 3 | 6,000 | 600 | 2,200 | 2,200 | 0.6 | 0.3 |" in (
        tmp_path / "out2" / "cost.md").read_text()  # the flags' prices replace the run's


def test_metrics_prints_tokens_cost_and_latency(tmp_path: Path, agos) -> None:
    rows = [summary("e1", "easy", True, [trace("agos-standin", 1000, 100, 0.5)]),
            summary("m1", "mid", False, [trace("agos-standin", 3000, 300, 1.5)])]
    run = _write_run(tmp_path / "r1", rows, {k: v for k, v in CARD_RUN.items() if k != "prices"})
    bare = agos("metrics", run, "--json")
    assert bare.returncode == 0 and "no prices, so cost is --" in bare.stderr
    data = json.loads(bare.stdout)
    assert data["easy"]["prompt_tokens"] == 1000 and data["easy"]["cost_usd"] is None
    assert data["overall"]["prompt_tokens"] == 4000 and data["overall"]["latency_p95_s"] == pytest.approx(1.45)
    priced = json.loads(agos("metrics", run, "--json", "--price-in", "1", "--price-out", "10").stdout)
    assert priced["overall"]["cost_usd"] == pytest.approx((4000 + 4000) / 1e6)
    assert priced["overall"]["cost_per_success_usd"] == pytest.approx(8000 / 1e6)
    assert priced["mid"]["cost_per_success_usd"] is None
    table = agos("metrics", run, "--price-in", "1", "--price-out", "10")
    assert "tokens, cost and latency" in table.stdout and "0.008" in table.stdout
    bad = agos("metrics", run, "--price-in", "1")
    assert bad.returncode == 2 and bad.stderr.strip() == ("metrics error: --price-out is missing: give both --price-in and "
                                                 "--price-out (USD per million prompt and completion tokens)")
