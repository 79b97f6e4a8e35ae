"""``agos eval``'s caps (deploy/run/budget.py): the "could cross" decision, the orchestrator's gate and the
stop on a MemoryBus, resuming with a new cap, and the run card a new plan writes (deploy/run/card_writer.py).
Unit tests: no processes, no sockets."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import msgspec
import pytest

from agos.deploy.run.budget import EXIT_CAPPED, Budget, Caps, check_prices, spending
from agos.deploy.run.evaluate import Capped, usage_line
from agos.evaluator.cost import flat_prices, prices_from_json
from agos.runtime.episode_config import EpisodeConfig
from agos.runtime.failure_records import failure_record
from agos.runtime.schemas import EpisodeRecord, ModelUsage
from tests.test_run_converges import Bench

from support.episodes import minimal_spec


def usage(prompt: int, completion: int = 0, model: str = "m") -> list[ModelUsage]:
    return [ModelUsage(model=model, decisions=1, http_attempts=1, prompt_tokens=prompt, completion_tokens=completion)]


def record(episode_id: str, tokens: int, *, status: str = "finished", model: str = "m") -> EpisodeRecord:
    r = failure_record("r", minimal_spec(episode_id), status="world_crashed", worker_id="w", error="x",
                       config=EpisodeConfig())
    return msgspec.structs.replace(r, status=status, usage=usage(tokens, model=model))


def test_spending_counts_every_record_and_averages_the_finished() -> None:
    s = spending([record("a", 100), record("b", 300), record("c", 50, status="world_crashed")], flat_prices(1.0, 0.0))
    assert (s.episodes, s.tokens, s.finished, s.finished_tokens) == (3, 450, 2, 400)
    assert s.cost_usd == pytest.approx(450e-6) and s.per_episode("tokens") == 200
    assert s.per_episode("cost") == pytest.approx(200e-6)
    assert spending([], None).per_episode("tokens") is None


def test_could_cross_counts_the_episodes_in_flight() -> None:
    budget = Budget(Caps(max_tokens=250), None)
    assert budget.refusal(0) is None  # nothing known yet: one episode may start ...
    flag, why = budget.refusal(1) or ("", "")  # ... but only one at a time
    assert flag == "--max-tokens" and "one episode at a time" in why
    budget.see([record("a", 100)])
    assert budget.refusal(0) is None  # 100 spent + 1 x 100 <= 250
    flag, why = budget.refusal(1) or ("", "")  # 100 + 2 x 100 > 250
    assert why == ("the next episode could cross --max-tokens 250: the run spent 100 tokens on 1 episode (about 100 tokens "
                   "a finished episode), 1 in flight")
    budget.see([record("a", 100), record("b", 160)])
    assert budget.refusal(0) is not None  # 260 >= 250
    assert budget.refusal(0) == ("--max-tokens", "the run has spent 260 tokens on 2 episodes, reaching --max-tokens 250")


def test_a_resumed_run_counts_what_it_spent_before() -> None:
    budget = Budget(Caps(max_cost_usd=0.001), flat_prices(2.0, 0.0), before=[record("a", 300)])  # $0.0006 spent
    assert budget.refusal(0) == ("--max-cost-usd", "the next episode could cross --max-cost-usd 0.001: the run spent "
                                 "$0.0006 on 1 episode (about $0.0006 a finished episode), 0 in flight")
    assert Budget(Caps(max_cost_usd=0.01), flat_prices(2.0, 0.0), before=[record("a", 300)]).refusal(0) is None
    unpriced = Budget(Caps(max_cost_usd=1.0), prices_from_json({"models": {"m": {"in_usd_per_mtok": 1,
                                                                                  "out_usd_per_mtok": 1}}}, where="w"))
    unpriced.see([record("a", 10, model="other")])
    assert unpriced.refusal(0) == ("--max-cost-usd", "--max-cost-usd 1 cannot be kept: a model of the run has no price")
    assert Budget(Caps(), None, before=[record("a", 10**9)]).refusal(5) is None  # no cap: never refused


def test_a_cost_cap_needs_a_price_for_the_model() -> None:
    check_prices(Caps(max_cost_usd=1.0), None, None)  # a run of scripted policies asks no model
    check_prices(Caps(max_tokens=10), None, "m")
    with pytest.raises(ValueError, match="--max-cost-usd needs the price of model m: give --price-in/--price-out"):
        check_prices(Caps(max_cost_usd=1.0), None, "m")
    with pytest.raises(ValueError, match="has no price for model m"):
        check_prices(Caps(max_cost_usd=1.0), prices_from_json({"models": {"x": {"in_usd_per_mtok": 1,
                                                                                  "out_usd_per_mtok": 1}}}, where="w"), "m")


def test_the_gate_holds_episodes_back_and_the_run_stops_once_played_ones_are_stored(tmp_path: Path) -> None:
    bench = Bench(tmp_path, [minimal_spec(e) for e in ("e1", "e2", "e3")])
    capped = Capped(Budget(Caps(max_tokens=250), None), bench.orch, "agos eval --resume runs/r")
    first = bench.job("w1")
    assert first.episode is not None and bench.job("w2").episode is None  # a probe: one at a time
    assert capped.check() is None  # an episode is leased
    bench.bus.publish(*_result(bench.record(first.episode.episode_id, "w1", usage=usage(100))))
    bench.turn(0.0)
    assert capped.check() is None  # 100 + 1 x 100 <= 250
    second = bench.job("w1")
    assert second.episode is not None
    held = bench.job("w2")
    assert held.episode is None and not held.run_finished  # 100 + 2 x 100 > 250
    bench.bus.publish(*_result(bench.record(second.episode.episode_id, "w1", usage=usage(100))))
    bench.turn(0.0)
    halt = capped.check()
    assert halt is not None and halt.code == EXIT_CAPPED == 5 and halt.announce
    assert halt.line == ("[red]stopping: the next episode could cross --max-tokens 250: the run spent 200 tokens on 2 "
                         "episodes (about 100 tokens a finished episode), 0 in flight; 1 of 3 episodes not run; resume "
                         "with a higher cap: agos eval --resume runs/r --max-tokens N (or none)")
    assert len(bench.rows()) == 2  # both played episodes are stored


def _result(r: EpisodeRecord) -> tuple[str, EpisodeRecord]:
    from agos.runtime import keys

    return keys.result(r.run_id, r.worker_id), r


def _plan(tmp_path: Path, monkeypatch: pytest.MonkeyPatch, **kw):
    from agos.deploy.run.plan import new_plan
    from agos.runtime.settings import load_config
    from agos.world.episodes.files import read_episodes
    from agos.world.episodes.sampling import write_episodes

    monkeypatch.setattr("agos.world.episodes.files.read_split", lambda path, look=None: read_episodes(path))  # a made-up town
    split = tmp_path / "split.jsonl"
    write_episodes(split, [minimal_spec("e1"), minimal_spec("e2")])
    cfg = load_config(overrides={"run": {"episodes_file": str(split), "runs_dir": str(tmp_path),
                                         "policy_uav": "agos-agent", "policy_ugv": "agos-agent"}})
    return new_plan(cfg, run_dir=tmp_path / "run", comm="ideal", timing_mode="lockstep", stamp=False, vlm_standin="", **kw)


def test_a_new_plan_writes_the_run_card(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from agos.deploy.run.card_writer import PROMPT_MODULES, prompts_text

    plan = _plan(tmp_path, monkeypatch, caps=Caps(max_tokens=1000), prices=flat_prices(1.0, 2.0))
    meta = json.loads((plan.run_dir / "run.json").read_text())
    card = meta["card"]
    prompts = (plan.run_dir / "prompts.txt").read_bytes()
    assert card["prompts"] == {"sha256": hashlib.sha256(prompts).hexdigest(), "file": "prompts.txt",
                               "modules": list(PROMPT_MODULES)}
    assert prompts.decode() == prompts_text() and "UAV_SYSTEM = " in prompts.decode()
    assert card["model"] == "agos-standin" and card["endpoint"].startswith("agos vlm-standin started by the run")
    assert card["models_answer"] is None  # filled in once the stand-in listens (deploy/run/local.py)
    assert card["sampling"]["temperature"] == 0.0 and card["sampling"]["max_tokens"] == 512
    split = tmp_path / "split.jsonl"
    assert card["split"] == {"file": str(split.resolve()), "sha256": hashlib.sha256(split.read_bytes()).hexdigest()}
    assert card["episodes_sha256"] == hashlib.sha256((plan.run_dir / "episodes.jsonl").read_bytes()).hexdigest()
    assert card["cache"] is None
    assert meta["caps"] == {"max_cost_usd": None, "max_tokens": 1000}
    assert prices_from_json(meta["prices"], where="run.json") == flat_prices(1.0, 2.0)
    assert {"agos", "commit", "packages"} <= set(meta["provenance"])
    with pytest.raises(ValueError, match="needs the price of model agos-standin"):  # refused before anything is written
        _plan(tmp_path / "again", monkeypatch, caps=Caps(max_cost_usd=1.0))
    assert not (tmp_path / "again" / "run").exists()


def test_resume_replaces_lifts_or_keeps_each_cap(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from agos.deploy.run.plan import resume_plan, resume_with

    plan = _plan(tmp_path, monkeypatch, caps=Caps(max_cost_usd=0.5, max_tokens=1000), prices=flat_prices(1.0, 2.0))
    again = resume_plan(plan.run_dir)
    assert again.caps == Caps(0.5, 1000) and again.prices == flat_prices(1.0, 2.0)
    resume_with(again, max_cost_usd=2.0, max_tokens="none", prices=None)
    assert again.caps == Caps(2.0, None)
    meta = json.loads((plan.run_dir / "run.json").read_text())
    assert meta["caps"] == {"max_cost_usd": 2.0, "max_tokens": None}
    assert [r["caps"] for r in meta["resumes"]] == [{"max_cost_usd": 2.0, "max_tokens": None}]
    third = resume_plan(plan.run_dir)
    resume_with(third, max_cost_usd=None, max_tokens=None, prices=flat_prices(3.0, 3.0))
    assert third.caps == Caps(2.0, None) and third.prices == flat_prices(3.0, 3.0)  # kept; new prices
    assert len(json.loads((plan.run_dir / "run.json").read_text())["resumes"]) == 2


def test_the_run_summary_says_tokens_and_cost(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    plan = _plan(tmp_path, monkeypatch, prices=flat_prices(1.0, 4.0))
    records = [msgspec.structs.replace(record("a", 0), usage=usage(1000, 100)), record("b", 2000)]
    assert usage_line(records, plan) == ("model calls: 3,000 prompt + 100 completion tokens over 2 decisions (1,550 a "
                                         "decision), $0.0034 at * $1/$4 per M tokens in/out (--price-in/--price-out)")
    assert usage_line([record("c", 0)], plan) is None
