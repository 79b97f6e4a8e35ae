"""Every hint is the command that works (issue 30, item 5): an interrupted dataset build names ``agos
dataset build`` (which resumes and completes the export), not ``agos eval --resume``; a run that stored
nothing says so instead of naming a results file that does not exist. In-process: the run itself is
replaced where it would start processes."""

from __future__ import annotations

import io
from pathlib import Path

import pytest
from rich.console import Console

from agos.deploy.dataset import build
from agos.deploy.run import evaluate
from agos.deploy.run.plan import RunPlan
from agos.evaluator.store import ResultStore, results_path
from agos.runtime.episode_config import EpisodeConfig
from agos.runtime.failure_records import failure_record
from agos.runtime.settings import AgosConfig, load_config
from agos.world.episodes.files import write_episodes

from support.episodes import grid_episodes, minimal_spec


def test_an_interrupted_dataset_build_names_itself_to_resume(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    split = tmp_path / "train.jsonl"
    write_episodes(split, grid_episodes())
    asked: dict = {}

    def interrupted(cfg, plan, **kwargs) -> int:  # what evaluate.run prints and returns after Ctrl-C
        asked.update(kwargs, plan=plan)
        return 130

    monkeypatch.setattr(build.evaluate, "run", interrupted)
    out = tmp_path / "data"
    console = Console(file=io.StringIO(), width=300)
    assert build.build(load_config(), split, out, workers=2, capture_every_m=10.0, console=console) == 130
    assert asked["resume"] == f"agos dataset build --split {split} --out {out} --workers 2"
    assert (out / "manifest.json").exists() and (out / "export.jsonl").exists()  # written after Ctrl-C too
    assert "resume" not in console.file.getvalue()  # type: ignore[attr-defined]  # evaluate.run says it, once

    cfg = load_config(overrides={"zenoh": {"connect": "tcp/10.0.0.2:7447"}, "run": {"run_id": "ds"}})
    attached = build.resume_command(Path("my split.jsonl"), Path("/d"), workers=1, attach=True, cfg=cfg,
                                    config_path=Path("my.toml"))
    assert attached == "agos dataset build --split 'my split.jsonl' --out /d --config my.toml --connect tcp/10.0.0.2:7447 --run ds"


def test_eval_names_eval_resume_by_default(tmp_path: Path) -> None:
    plan = RunPlan(tmp_path / "runs" / "r 1", [minimal_spec("e1")], {"uav": "heuristic", "ugv": "heuristic"},
                   EpisodeConfig())
    assert evaluate.resume_command(plan) == f"agos eval --resume '{tmp_path / 'runs' / 'r 1'}'"


def _summary(plan: RunPlan) -> str:
    console = Console(file=io.StringIO(), width=300)
    evaluate._summary(console, plan, None, attach=False, processes=6, wall_s=1.0)
    return console.file.getvalue()  # type: ignore[attr-defined]


def test_a_run_that_stored_nothing_says_so_instead_of_naming_a_missing_file(tmp_path: Path) -> None:
    """A human run stopped before any episode finished: the evaluator never opened its store."""
    plan = RunPlan(tmp_path / "runs" / "r1", [minimal_spec("e1")], {"uav": "human", "ugv": "human"}, EpisodeConfig())
    path = results_path(plan.run_dir.parent, plan.run_id)
    said = _summary(plan)
    assert f"results: none stored (no episode finished), so no {path}" in said
    assert f"results: {path}" not in said
    with ResultStore(path) as store:
        store.add(failure_record("r1", minimal_spec("e1"), status="finished", worker_id="w", error="",
                                 config=AgosConfig().world))
    assert f"results: {path}" in _summary(plan)
