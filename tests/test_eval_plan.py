"""What ``agos eval``'s flags make of a run before anything starts (deploy/run/eval_plan.py) and how the
run commands' failures end (deploy/run/exits.py). Units: no processes, no sockets."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from agos.agents.contract import EndpointOutage, FatalPolicyError
from agos.deploy.run import concurrency
from agos.deploy.run.budget import Caps
from agos.deploy.run.eval_plan import caps_of, eval_plan, eval_workers, locate_here, run_dir_for
from agos.deploy.run.exits import EXIT_REFUSED, SWEEP_STOPS, refused, sweep_exit
from agos.deploy.run.plan import RunDirError, RunPlan
from agos.runtime.deaths import ChildDied
from agos.runtime.episode_config import EpisodeConfig
from agos.runtime.links import ProfileError
from agos.runtime.settings import load_config
from agos.world.episodes.files import write_episodes

from support.episodes import grid_episodes, minimal_spec


def test_caps_none_or_not_given_is_no_cap() -> None:
    assert caps_of(None, None) == Caps()
    assert caps_of("none", "none") == Caps()
    assert caps_of(2.5, 1000) == Caps(2.5, 1000)


def test_policies_are_located_only_when_the_agents_start_here() -> None:
    locate_here(["heuristic", "no.such.module:Policy"], attach=True)  # hand-started agents: nothing to find here
    with pytest.raises(ValueError):
        locate_here(["no.such.module:Policy"], attach=False)


def test_the_run_directory_of_a_new_run(tmp_path: Path) -> None:
    cfg = load_config(overrides={"run": {"runs_dir": str(tmp_path / "runs")}})
    assert run_dir_for(cfg, tmp_path / "mine", attach=True, run_id="r") == tmp_path / "mine"
    assert run_dir_for(cfg, None, attach=True, run_id="r") == tmp_path / "runs" / "r"
    assert run_dir_for(cfg, None, attach=False, run_id="r") is None  # new_plan stamps one
    assert run_dir_for(cfg, None, attach=True, run_id=None) is None


def _plan(tmp_path: Path, *, workers: int | str | None, resumed: bool, episodes: int = 4) -> RunPlan:
    return RunPlan(tmp_path, [minimal_spec(f"e{i}") for i in range(episodes)], {"uav": "standin-1000ms", "ugv": "heuristic"},
                   EpisodeConfig(), resumed=resumed, workers=workers)


def test_the_worker_count(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    cfg = load_config(overrides={"run": {"workers": 3}})
    assert eval_workers(cfg, _plan(tmp_path, workers=None, resumed=False), 5, attach=False, model_latency_s=None) == (5, None)
    assert eval_workers(cfg, _plan(tmp_path, workers=None, resumed=False), None, attach=False,
                        model_latency_s=None) == (3, None)
    assert eval_workers(cfg, _plan(tmp_path, workers=7, resumed=True), None, attach=False,
                        model_latency_s=None) == (7, None)  # a resumed run keeps its count
    assert eval_workers(cfg, _plan(tmp_path, workers=7, resumed=True), 2, attach=False, model_latency_s=None) == (2, None)
    assert eval_workers(cfg, _plan(tmp_path, workers="auto", resumed=True), None, attach=True,
                        model_latency_s=None) == (3, None)  # auto sizes only workers started here
    monkeypatch.setattr(concurrency, "host_resources", lambda: (2, None))
    workers, why = eval_workers(cfg, _plan(tmp_path, workers="auto", resumed=True), None, attach=False, model_latency_s=None)
    assert workers == 4 and why is not None  # capped by the four episodes to play
    assert (workers, why) == (lambda c: (c.workers, c.why))(concurrency.auto_workers(latency_s=1.0, cores=2, episodes=4))


def test_a_new_plan_then_its_resume_with_new_caps(tmp_path: Path) -> None:
    split = tmp_path / "eps.jsonl"
    write_episodes(split, grid_episodes())
    cfg = load_config(overrides={"run": {"episodes_file": str(split), "runs_dir": str(tmp_path / "runs")}})
    flags = {"run_id": None, "attach": False, "comm": "ideal", "timing_mode": "lockstep", "vlm_standin": None,
             "model_link": None, "pose_error": None, "prices_file": None, "price_in": None, "price_out": None}
    plan = eval_plan(cfg, resume=None, run_dir=tmp_path / "r", workers=2, max_cost_usd=None, max_tokens=100, **flags)
    assert not plan.resumed and plan.run_dir == tmp_path / "r" and plan.caps == Caps(None, 100)
    with pytest.raises(RunDirError, match="already holds results"):
        (plan.run_dir / "results.sqlite").touch()
        eval_plan(cfg, resume=None, run_dir=plan.run_dir, workers=2, max_cost_usd=None, max_tokens=None, **flags)
    again = eval_plan(cfg, resume=plan.run_dir, run_dir=None, workers=None, max_cost_usd=None, max_tokens="none", **flags)
    assert again.resumed and again.workers == 2 and again.caps == Caps()
    assert json.loads((plan.run_dir / "run.json").read_text())["resumes"][0]["caps"] == Caps().as_json()


def test_what_stops_a_sweep_and_its_exit_status(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert refused("eval", RunDirError("r: no run.json")) == EXIT_REFUSED == 2
    assert capsys.readouterr().err == "eval error: r: no run.json\n"
    assert sweep_exit(ProfileError("bad profile")) == 2 and capsys.readouterr().err == "sweep error: bad profile\n"
    assert sweep_exit(FatalPolicyError("no recorded call")) == FatalPolicyError.exit_code
    assert capsys.readouterr().err == "sweep error: no recorded call\n"
    assert sweep_exit(EndpointOutage("http://x: 503")) == 6
    assert capsys.readouterr().err.startswith("sweep error: the model endpoint gave no answer: http://x: 503; finished")
    assert sweep_exit(ChildDied("sweep worker 1", -9, None)) == 1
    assert "sweep worker 1 died:" in capsys.readouterr().err
    assert all(issubclass(kind, Exception) for kind in SWEEP_STOPS)
    with pytest.raises(KeyError):
        sweep_exit(KeyError("not a sweep's"))
