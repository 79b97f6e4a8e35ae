"""How rows of several difficulty levels are made, as the paper's tables make them, against values
computed by hand (arithmetic in the comments): NE over successful episodes beside FD over every
episode; the overall row as the mean of the levels; the ablation table's Total pooling GVA, NE, FD
and CErr over episodes. docs/METRICS.md ("Aggregation") gives the paper's lines for each."""

from __future__ import annotations

import csv
from pathlib import Path

import pytest

from agos.evaluator.comparison import compare
from agos.evaluator.metrics import POOLED_IN_TOTAL, ablation_total, aggregate
from agos.evaluator.paper_report import RunResults, write_report

from support.synthetic import summary

RUN = [
    # easy: one success 10 m away (one candidate, centre 20 m off); one failure seen from the ground, 90 m away
    summary("e1", "easy", won=True, final_distance_m=10.0, errors=(20.0,), decisions_uav=10),
    summary("e2", "easy", ground_observed=True, final_distance_m=90.0),
    # mid: two successes, 30 m and 50 m away; the first had two candidates (40 and 60 m off)
    summary("m1", "mid", won=True, final_distance_m=30.0, errors=(40.0, 60.0)),
    summary("m2", "mid", won=True, final_distance_m=50.0),
    # hard: no success; one false CONFIRM (in GVA's denominator), one candidate 100 m off
    summary("h1", "hard", final_distance_m=200.0, errors=(100.0,), decisions_uav=30),
    summary("h2", "hard", n_confirm=1, final_distance_m=150.0),
    summary("h3", "hard", final_distance_m=250.0),
    # an infrastructure failure: in no mean and no pool
    summary("h4", "hard", status="world_crashed", won=True, final_distance_m=0.0, errors=(0.0,)),
]


def test_ne_is_over_successes_and_fd_over_every_episode() -> None:
    levels = aggregate(RUN)
    easy, mid, hard = levels["easy"], levels["mid"], levels["hard"]
    assert (pytest.approx(10.0), pytest.approx(50.0)) == (easy.NE, easy.FD)   # e1 alone; (10 + 90) / 2
    assert (pytest.approx(40.0), pytest.approx(40.0)) == (mid.NE, mid.FD)     # (30 + 50) / 2 both ways
    assert hard.SR == 0.0 and hard.NE is None                                 # no success: "--", not 0
    assert pytest.approx(200.0) == hard.FD                                    # (200 + 150 + 250) / 3; h4 not scored
    assert (hard.n, hard.excluded) == (3, 1)


def test_overall_is_the_mean_of_the_levels() -> None:
    o = aggregate(RUN)["overall"]
    assert pytest.approx(0.5) == o.SR               # (1/2 + 2/2 + 0/3) / 3; pooled would be 3/7
    assert pytest.approx(25.0) == o.NE              # (10 + 40) / 2: hard has none and is left out
    assert pytest.approx(290 / 3) == o.FD           # (50 + 40 + 200) / 3
    assert pytest.approx(0.5) == o.GVA              # (1/2 + 2/2 + 0/1) / 3
    assert o.CErr == pytest.approx(170 / 3)         # (20 + 50 + 100) / 3
    assert pytest.approx(5.0) == o.DS               # (10/2 + 0/2 + 30/3) / 3
    assert (o.n, o.excluded, o.GVA_support) == (7, 1, 5)


def test_ablation_total_pools_gva_ne_fd_and_cerr_and_averages_the_rest() -> None:
    t = ablation_total(RUN)
    assert POOLED_IN_TOTAL == ("GVA", "NE", "FD", "CErr")
    assert pytest.approx(30.0) == t.NE              # (10 + 30 + 50) / 3 successes; the mean of levels is 25
    assert pytest.approx(780 / 7) == t.FD           # (10 + 90 + 30 + 50 + 200 + 150 + 250) / 7
    assert pytest.approx(3 / 5) == t.GVA            # V = e1 e2 m1 m2 h2, C = e1 m1 m2; the mean of levels is 1/2
    assert t.CErr == pytest.approx(55.0)            # (20 + 40 + 60 + 100) / 4 candidates
    assert pytest.approx(0.5) == t.SR               # as the overall row, not 3/7
    assert pytest.approx(5.0) == t.DS               # as the overall row, not 40/7
    assert (t.n, t.excluded, t.GVA_support) == (7, 1, 5)


def test_ablation_total_pools_gva_as_the_paper_does() -> None:
    # the paper's no_RGPP rows: GVA 14.3 / 0.0 / 0.0 % and Total 7.1 %. One verified episode in seven
    # supported easy episodes, none in seven supported mid and hard ones: 1/7 = 14.3 %, 0, 0; pooled
    # 1/14 = 7.1 %, where the mean of the levels would give 4.8 %
    easy = [summary("e0", "easy", won=True, final_distance_m=20.0)] + [
        summary(f"e{k}", "easy", ground_observed=True, final_distance_m=60.0) for k in range(1, 7)]
    mid = [summary(f"m{k}", "mid", ground_observed=True, final_distance_m=60.0) for k in range(3)]
    hard = [summary(f"h{k}", "hard", n_confirm=1, final_distance_m=60.0) for k in range(4)]
    levels = aggregate(easy + mid + hard)
    assert [round(100 * levels[d].GVA, 1) for d in ("easy", "mid", "hard")] == [14.3, 0.0, 0.0]
    assert round(100 * ablation_total(easy + mid + hard).GVA, 1) == 7.1
    assert round(100 * levels["overall"].GVA, 1) == 4.8


def _csv(path: Path) -> list[dict[str, str]]:
    with open(path, newline="") as fh:
        return list(csv.DictReader(fh))


def test_report_prints_both_tables_with_their_conventions(tmp_path: Path) -> None:
    write_report([RunResults("Run", RUN)], tmp_path)
    (main,) = _csv(tmp_path / "main.csv")
    assert (main["Easy NE"], main["Mid NE"], main["Hard NE"]) == ("10.0", "40.0", "--")
    assert "FD" not in " ".join(main)  # the main table keeps the paper's five columns
    rows = {r["Difficulty"]: r for r in _csv(tmp_path / "ablation.csv")}
    assert list(rows) == ["easy", "mid", "hard", "total"]
    assert (rows["hard"]["NE"], rows["hard"]["FD"]) == ("--", "200.0")
    total = rows["total"]
    assert (total["SR"], total["NE"], total["FD"], total["GVA"], total["GVA_support"], total["CErr"], total["DS"]) == (
        "50.0", "30.0", "111.4", "60.0", "5", "55.0", "5.0")
    assert " & -- & " in (tmp_path / "main.tex").read_text()  # LaTeX's en dash, as the paper prints it


def test_compare_reads_ne_and_fd_as_the_overall_row_does() -> None:
    c = compare(RUN, RUN, resamples=20)
    values = {m.metric: m.a for m in c.metrics}
    assert values["NE"] == pytest.approx(25.0) and values["FD"] == pytest.approx(290 / 3)
