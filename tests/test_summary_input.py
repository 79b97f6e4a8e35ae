"""Reading episode summaries (evaluator/summary.py) and ``agos metrics`` on good and bad files."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest

from agos.evaluator.store import ResultStore
from agos.evaluator.summary import EpisodeSummary, SummaryError, read_jsonl, read_run
from agos.runtime.schemas import EpisodeRecord

from support.synthetic import synthetic_summaries, write_jsonl


def row(**kw: Any) -> dict[str, Any]:
    base: dict[str, Any] = dict(
        episode_id="e1", difficulty="easy", success=True, ground_observed=True, n_confirm=1, ugv_path_length_m=100.0,
        shortest_path_length_m=50.0, final_distance_m=3.0, uav_budget=80, uav_first_visible_step=4,
        candidates=[{"distance_to_polygon_m": 0.0, "center_error_m": 2.5}], decisions_uav=10, decisions_ugv=5)
    base.update(kw)
    return base


def write_lines(path: Path, rows: list[dict[str, Any] | str]) -> Path:
    path.write_text("".join((r if isinstance(r, str) else json.dumps(r)) + "\n" for r in rows))
    return path


def test_jsonl_round_trip(tmp_path: Path) -> None:
    rows = list(synthetic_summaries(12, seed=3))
    path = tmp_path / "s.jsonl"
    write_jsonl(path, rows)
    episodes = read_jsonl(path)
    assert episodes == [EpisodeSummary.model_validate(r) for r in rows]
    assert [e.episode_id for e in episodes] == [r["episode_id"] for r in rows]
    assert [e.difficulty for e in episodes[:3]] == ["easy", "mid", "hard"]
    assert episodes[0].candidates == EpisodeSummary.model_validate(rows[0]).candidates
    assert read_run(path) == episodes  # a JSONL file given to read_run


def test_extra_fields_are_accepted(tmp_path: Path) -> None:
    extra = row(wall_time_s=12.0, something_new={"nested": [1, 2]},
                candidates=[{"distance_to_polygon_m": 1.0, "center_error_m": 2.0, "cell": "c3", "candidate_id": "k"}])
    (episode,) = read_jsonl(write_lines(tmp_path / "x.jsonl", [extra]))
    assert episode.episode_id == "e1" and episode.candidates[0].distance_to_polygon_m == 1.0
    assert not hasattr(episode, "something_new")


def test_blank_lines_are_skipped_but_counted(tmp_path: Path) -> None:
    path = write_lines(tmp_path / "b.jsonl", [row(episode_id="a"), "", row(episode_id="b"), "  ", row(decisions_uav="3")])
    with pytest.raises(SummaryError) as info:
        read_jsonl(path)
    assert f"{path}:5" in str(info.value)


@pytest.mark.parametrize(("bad", "field"), [
    ({"uav_budget": None}, "uav_budget"),           # missing (None here means: delete the key)
    ({"success": "yes"}, "success"),                # wrong type
    ({"decisions_uav": "3"}, "decisions_uav"),      # a string, not an int
    ({"difficulty": "medium"}, "difficulty"),       # not easy / mid / hard
    ({"ugv_path_length_m": -1.0}, "ugv_path_length_m"),
    ({"uav_budget": 0}, "uav_budget"),
    ({"uav_first_visible_step": 0}, "uav_first_visible_step"),
    ({"candidates": [{"distance_to_polygon_m": 1.0}]}, "candidates.0.center_error_m"),
])
def test_bad_field_names_path_line_and_field(tmp_path: Path, bad: dict[str, Any], field: str) -> None:
    broken = row(episode_id="e2", **{k: v for k, v in bad.items() if v is not None})
    for k, v in bad.items():
        if v is None:
            del broken[k]
    path = write_lines(tmp_path / "bad.jsonl", [row(), broken, row(episode_id="e3")])
    with pytest.raises(SummaryError) as info:
        read_jsonl(path)
    message = str(info.value)
    assert str(path) in message
    assert f"{path}:2" in message
    assert field in message


def test_invalid_json_names_path_and_line(tmp_path: Path) -> None:
    path = write_lines(tmp_path / "j.jsonl", [row(), row(episode_id="e2"), '{"episode_id": "e3", "difficulty": '])
    with pytest.raises(SummaryError) as info:
        read_jsonl(path)
    message = str(info.value)
    assert f"{path}:3" in message and "JSON" in message


def test_summary_error_is_a_value_error() -> None:
    assert issubclass(SummaryError, ValueError)


def test_run_directory_without_results(tmp_path: Path) -> None:
    run_dir = tmp_path / "runs" / "r1"
    run_dir.mkdir(parents=True)
    with pytest.raises(SummaryError) as info:
        read_run(run_dir)
    message = str(info.value)
    assert str(run_dir) in message and "results.sqlite" in message


def test_missing_file(tmp_path: Path) -> None:
    with pytest.raises(SummaryError, match=r"nope\.jsonl"):
        read_run(tmp_path / "nope.jsonl")
    with pytest.raises(SummaryError, match=r"nope\.jsonl"):
        read_jsonl(tmp_path / "nope.jsonl")


def test_run_directory_with_results(tmp_path: Path) -> None:
    with ResultStore(tmp_path / "r1" / "results.sqlite") as store:
        for k, difficulty in enumerate(("hard", "easy")):
            store.add(EpisodeRecord(
                run_id="r1", episode_id=f"ep-{k}", difficulty=difficulty, status="finished", termination="confirmed",
                success=True, ground_observed=True, n_confirm=1, ugv_path_length_m=100.0, shortest_path_length_m=50.0,
                final_distance_m=4.0, uav_budget=80, uav_first_visible_step=2,
                candidates=[{"candidate_id": "c", "cell": "x", "center_world_m": [0.0, 0.0], "status": "confirmed",
                             "distance_to_polygon_m": 0.0, "center_error_m": 1.5}],
                decisions_uav=3, decisions_ugv=2, sim_time_s=10.0, wall_time_s=1.0, worker_id="w", town_id="t",
                asset_sha256="0" * 64, seed=1, renderer="r"))
    episodes = read_run(tmp_path / "r1")
    assert [(e.episode_id, e.difficulty) for e in episodes] == [("ep-0", "hard"), ("ep-1", "easy")]
    assert episodes[0].candidates[0].center_error_m == 1.5 and episodes[0].candidates[0].status == "confirmed"
    assert read_run(tmp_path / "r1" / "results.sqlite") == episodes


# ----- the CLI ---------------------------------------------------------------------------------
def test_cli_metrics_json(tmp_path: Path, agos) -> None:
    path = tmp_path / "s.jsonl"
    write_jsonl(path, synthetic_summaries(30, seed=5))
    proc = agos("metrics", path, "--json")
    assert proc.returncode == 0, proc.stderr
    data = json.loads(proc.stdout)
    assert set(data) == {"easy", "mid", "hard", "overall"}
    assert data["overall"]["n"] == 30 and data["easy"]["n"] == 10
    assert set(data["overall"]) >= {"SR", "GVA_support", "CErr", "n", "not_scored"}


def test_cli_metrics_bad_file(tmp_path: Path, agos) -> None:
    path = write_lines(tmp_path / "bad.jsonl", [row(), row(episode_id="e2", success="yes")])
    proc = agos("metrics", path, "--json")
    assert proc.returncode == 2
    assert proc.stdout == ""
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1, proc.stderr
    assert f"{path}:2" in lines[0] and "success" in lines[0]


@pytest.mark.e2e  # a real pipe whose reader leaves: the command as a process
def test_metrics_piped_into_head_prints_no_traceback(tmp_path) -> None:
    """`agos metrics --json | head`: the reader leaves early (here `true`, which reads nothing and exits
    before agos writes); agos says nothing about it."""
    import subprocess
    import sys

    from support.synthetic import synthetic_summaries, write_jsonl

    path = tmp_path / "s.jsonl"
    write_jsonl(path, synthetic_summaries(3000, seed=1))
    out = subprocess.run(f"{sys.executable} -m agos.deploy.cli metrics {path} --json | true", shell=True,
                         capture_output=True, text=True, timeout=120)
    assert "Traceback" not in out.stderr and "BrokenPipe" not in out.stderr, out.stderr
