"""Evaluator: the store keeps each (run, episode) once; metrics match hand-computed values."""

from __future__ import annotations

from pathlib import Path

import pytest

from agos.evaluator.metrics import by_difficulty, spl, summarize
from agos.evaluator.store import ResultStore
from agos.runtime.schemas import EpisodeRecord


def record(episode: str, difficulty: str = "easy", **kw) -> EpisodeRecord:
    base = dict(run_id="r", episode_id=episode, difficulty=difficulty, status="finished", termination="confirmed",
                success=True, ground_observed=True, n_confirm=1, ugv_path_length_m=100.0, shortest_path_length_m=50.0,
                final_distance_m=10.0, uav_budget=80, uav_first_visible_step=3, candidates=[], decisions_uav=10,
                decisions_ugv=5, sim_time_s=100.0, wall_time_s=1.0, worker_id="w", town_id="t", asset_sha256="0" * 64,
                seed=1, renderer="pybullet-tiny")
    base.update(kw)
    return EpisodeRecord(**base)


def test_store_is_idempotent_per_run_and_episode(tmp_path: Path) -> None:
    with ResultStore(tmp_path / "r" / "results.sqlite") as store:
        assert store.add(record("e1")) is True
        assert store.add(record("e1", success=False)) is False  # a resubmission changes nothing
        assert store.add(record("e2")) is True
        assert store.add(record("e1", run_id="other")) is True
        assert [r.episode_id for r in store.records("r")] == ["e1", "e2"]
        assert store.records("r")[0].success is True
    with ResultStore(tmp_path / "r" / "results.sqlite") as reopened:
        assert len(reopened.records()) == 3


def test_a_finished_record_replaces_an_infrastructure_failure_never_the_reverse(tmp_path: Path) -> None:
    with ResultStore(tmp_path / "results.sqlite") as store:
        failed = record("e1", status="agent_crashed", termination="error", success=False, error="no UGV agent service")
        assert store.add(failed) is True
        assert store.finished_ids() == set()
        assert store.add(failed) is False  # the same failure again: nothing changes
        assert store.add(record("e1")) is True  # a resumed run finished it
        assert store.finished_ids() == {"e1"} and store.records()[0].status == "finished"
        assert store.add(failed) is False  # nothing replaces a finished record
        assert store.add(record("e1", success=False)) is False
        assert store.records()[0].success is True and len(store.records()) == 1


@pytest.mark.parametrize(("kw", "expected"), [
    ({}, 0.5),                                                      # 50 / max(100, 50)
    ({"success": False}, 0.0),
    ({"ugv_path_length_m": 30.0}, 1.0),                              # path shorter than L*: capped at 1
    ({"ugv_path_length_m": 0.0, "shortest_path_length_m": 0.0}, 1.0),  # started at a verifying pose
    ({"shortest_path_length_m": None}, 1.0),                         # L* unknown: P used
])
def test_spl_edge_cases(kw: dict, expected: float) -> None:
    assert spl(record("e", **kw)) == pytest.approx(expected)


def test_summary_and_macro_overall() -> None:
    records = [
        record("e1", "easy"),
        record("e2", "easy", success=False, ground_observed=False, final_distance_m=30.0, decisions_uav=40),
        record("m1", "mid", success=False, ground_observed=True, final_distance_m=20.0),
        record("h1", "hard", status="world_crashed", success=False),
    ]
    easy = summarize(records[:2])
    assert (easy.n, easy.SR, easy.OSR, easy.SPL, easy.DS) == (2, 0.5, 0.5, 0.25, (15 + 45) / 2)
    assert (easy.NE, easy.FD) == (10.0, 20.0)  # NE: e1, the success; FD: (10 + 30) / 2
    table = by_difficulty(records)
    assert table["hard"].n == 0 and table["hard"].SR is None and table["hard"].excluded == 1
    overall = table["overall"]
    # macro mean over the levels with scored episodes (easy, mid): SR (0.5 + 0) / 2
    assert pytest.approx(0.25) == overall.SR and pytest.approx(0.75) == overall.OSR
    assert overall.NE == 10.0  # mid has no success: left out of the mean, not counted as 0
    assert pytest.approx((20.0 + 20.0) / 2) == overall.FD and overall.n == 3 and overall.excluded == 1
