"""Paired comparison (comparison.py), failure attribution (attribution.py) and paper-style reports (paper_report.py)."""

from __future__ import annotations

import csv
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from agos.evaluator.attribution import OUTCOMES, attribute, outcome_counts
from agos.evaluator.comparison import COMPARED, Comparison, compare, pair, sign_test
from agos.evaluator.paper_report import RunResults, write_report
from agos.evaluator.summary import EpisodeSummary

from support.synthetic import synthetic_summaries


def ep(**kw: Any) -> EpisodeSummary:
    """A finished, failed, unobserved episode with no candidates; keyword arguments override."""
    base: dict[str, Any] = dict(
        episode_id="e", difficulty="easy", success=False, ground_observed=False, n_confirm=0,
        ugv_path_length_m=10.0, shortest_path_length_m=5.0, final_distance_m=20.0, uav_budget=80,
        uav_first_visible_step=None, candidates=[], decisions_uav=5, decisions_ugv=3)
    base.update(kw)
    return EpisodeSummary.model_validate(base)


def cand(d: float, err: float = 1.0, status: str | None = None) -> dict[str, Any]:
    return {"distance_to_polygon_m": d, "center_error_m": err, "status": status}


def synthetic(n: int, rate: float, *, seed: int, uniforms: np.ndarray | None = None) -> list[EpisodeSummary]:
    return [EpisodeSummary.model_validate(r) for r in synthetic_summaries(n, seed=seed, success_rate=rate, uniforms=uniforms)]


def metric(c: Comparison, name: str):
    (m,) = [m for m in c.metrics if m.metric == name]
    return m


# ----- stats -----------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def planted() -> Comparison:
    u = np.random.default_rng(0).random(900)
    a = synthetic(900, 0.7, seed=1, uniforms=u)
    b = synthetic(900, 0.5, seed=2, uniforms=u)
    return compare(a, b, resamples=2000, seed=0)


def test_planted_sr_difference_is_detected(planted: Comparison) -> None:
    sr = metric(planted, "SR")
    assert planted.n_pairs == 900 and planted.per_level == {"easy": 300, "mid": 300, "hard": 300}
    assert sr.diff == pytest.approx(sr.a - sr.b)
    assert sr.ci_low < 0.2 < sr.ci_high
    assert sr.ci_low > 0
    assert sr.p_value < 0.01
    # shared uniforms: nothing succeeds in B (u < 0.5) that fails in A (u < 0.7)
    assert planted.outcomes["only_b"] == 0 and planted.outcomes["only_a"] > 100
    assert planted.sign_test_p is not None and planted.sign_test_p < 1e-6
    assert sum(planted.outcomes.values()) == 900
    assert [m.metric for m in planted.metrics] == list(COMPARED)


def test_run_compared_with_itself() -> None:
    a = synthetic(90, 0.6, seed=4)
    c = compare(a, a, resamples=300, seed=0)
    defined = [m for m in c.metrics if m.diff is not None]
    assert {m.metric for m in defined} == set(COMPARED)
    for m in defined:
        assert m.a == m.b
        assert m.diff == 0.0
        assert (m.ci_low, m.ci_high) == (0.0, 0.0)
        assert m.p_value > 0.99
    assert c.outcomes["only_a"] == c.outcomes["only_b"] == 0
    assert c.sign_test_p is None


def test_compare_is_seeded() -> None:
    u = np.random.default_rng(7).random(90)
    a, b = synthetic(90, 0.7, seed=1, uniforms=u), synthetic(90, 0.4, seed=2, uniforms=u)
    first = compare(a, b, resamples=400, seed=3)
    assert compare(a, b, resamples=400, seed=3) == first
    other = compare(a, b, resamples=400, seed=4)
    assert [(m.ci_low, m.ci_high) for m in other.metrics] != [(m.ci_low, m.ci_high) for m in first.metrics]
    # SPL is continuous: its bounds move with the seed
    assert (metric(other, "SPL").ci_low, metric(other, "SPL").ci_high) != (metric(first, "SPL").ci_low,
                                                                           metric(first, "SPL").ci_high)
    # the point estimates do not depend on the seed
    assert [m.diff for m in other.metrics] == [m.diff for m in first.metrics]


def test_outcome_matrix_on_a_tiny_pair() -> None:
    def run(successes: dict[str, bool]) -> list[EpisodeSummary]:
        return [ep(episode_id=k, success=v, ground_observed=v, n_confirm=int(v), difficulty=("easy", "mid")[i % 2])
                for i, (k, v) in enumerate(successes.items())]

    a = run({"e1": True, "e2": True, "e3": False, "e4": False, "e5": True, "e6": True})
    b = run({"e1": True, "e2": False, "e3": True, "e4": False, "e5": False, "e6": True})
    c = compare(a, b, resamples=200, seed=0)
    # both: e1, e6; only A: e2, e5; only B: e3; neither: e4
    assert c.outcomes == {"both_succeed": 2, "only_a": 2, "only_b": 1, "neither": 1}
    # sign test on 3 discordant pairs, k = 1: 2 * (C(3,0) + C(3,1)) / 2^3 = 2 * 4/8 = 1.0
    assert c.sign_test_p == pytest.approx(1.0)
    assert c.n_pairs == 6 and c.per_level == {"easy": 3, "mid": 3}
    # SR: easy A = {e1, e3, e5} = 2/3, mid A = {e2, e4, e6} = 2/3; easy B = {e1, e3} 2/3, mid B = {e6} 1/3
    sr = metric(c, "SR")
    assert (sr.a, sr.b, sr.diff) == (pytest.approx(2 / 3), pytest.approx(1 / 2), pytest.approx(1 / 6))
    # no candidates anywhere: CErr is undefined in both runs, nothing is invented
    cerr = metric(c, "CErr")
    assert (cerr.a, cerr.b, cerr.diff, cerr.ci_low, cerr.ci_high, cerr.p_value) == (None,) * 6


def test_sign_test() -> None:
    assert sign_test(5, 0) == pytest.approx(0.0625)   # 2 * 1/2^5
    assert sign_test(0, 5) == pytest.approx(0.0625)
    assert sign_test(3, 3) == 1.0                     # capped at 1
    assert sign_test(0, 0) is None
    # n = 10, k = 1: 2 * (1 + 10) / 1024
    assert sign_test(9, 1) == pytest.approx(22 / 1024)


def test_pair_keeps_episodes_finished_in_both() -> None:
    a = [ep(episode_id="e6"), ep(episode_id="e1"), ep(episode_id="e2"), ep(episode_id="e3", status="world_crashed"),
         ep(episode_id="e4")]
    b = [ep(episode_id="e1"), ep(episode_id="e2", status="agent_crashed"), ep(episode_id="e3"), ep(episode_id="e5"),
         ep(episode_id="e6")]
    pairs = pair(a, b)
    assert [(x.episode_id, y.episode_id) for x, y in pairs] == [("e1", "e1"), ("e6", "e6")]
    assert compare(a, b, resamples=50).n_pairs == 2


def test_pair_rejects_mismatched_difficulty() -> None:
    a = [ep(episode_id="e1", difficulty="easy"), ep(episode_id="e2")]
    b = [ep(episode_id="e1", difficulty="hard"), ep(episode_id="e2")]
    with pytest.raises(ValueError, match="e1"):
        pair(a, b)
    with pytest.raises(ValueError):
        compare(a, b, resamples=10)


def test_compare_without_shared_episodes() -> None:
    with pytest.raises(ValueError):
        compare([ep(episode_id="a")], [ep(episode_id="b")], resamples=10)


# ----- attribution -----------------------------------------------------------------------------
ATTRIBUTION_CASES = {
    "success": ep(success=True, ground_observed=True, n_confirm=1, candidates=[cand(0.0)]),
    "false_confirm": ep(n_confirm=1, ground_observed=True, candidates=[cand(0.0, status="false_confirm")]),
    "never_seen_from_air": ep(uav_first_visible_step=None),
    "seen_not_annotated": ep(uav_first_visible_step=12),
    "candidate_lost_on_link": ep(uav_first_visible_step=3, candidates=[cand(0.0)],
                                 link={"candidates_lost": 2, "candidates_delivered": 0}),
    "candidate_too_far": ep(uav_first_visible_step=3, ground_observed=True, candidates=[cand(60.0), cand(50.5)]),
    "no_verifying_view": ep(uav_first_visible_step=3, candidates=[cand(80.0), cand(50.0)]),  # 50 = R is not too far
    "wrong_reject": ep(uav_first_visible_step=3, ground_observed=True, candidates=[cand(20.0, status="rejected")]),
    "budget_exhausted": ep(uav_first_visible_step=3, ground_observed=True,
                           candidates=[cand(80.0, status="rejected"), cand(10.0, status="pending")]),
    "agent_failure": ep(status="agent_crashed", success=True, ground_observed=True, n_confirm=1),
    "infrastructure_failure": ep(status="world_crashed", success=True, ground_observed=True, n_confirm=1),
}


@pytest.mark.parametrize("expected", list(ATTRIBUTION_CASES))
def test_attribute_one_episode_per_rule(expected: str) -> None:
    assert attribute(ATTRIBUTION_CASES[expected]) == expected


def test_attribute_other_statuses_are_infrastructure() -> None:
    assert attribute(ep(status="timeout")) == "infrastructure_failure"
    assert attribute(ep(status="invalid")) == "infrastructure_failure"


def test_attribute_link_with_a_delivered_candidate_is_not_lost() -> None:
    e = ep(uav_first_visible_step=3, ground_observed=True, candidates=[cand(5.0)],
           link={"candidates_lost": 1, "candidates_delivered": 1})
    assert attribute(e) == "budget_exhausted"


def test_outcome_counts_has_every_key() -> None:
    episodes = list(ATTRIBUTION_CASES.values()) + [ATTRIBUTION_CASES["success"], ATTRIBUTION_CASES["wrong_reject"]]
    counts = outcome_counts(episodes)
    assert tuple(counts) == OUTCOMES
    assert set(OUTCOMES) == set(ATTRIBUTION_CASES)
    assert counts["success"] == 2 and counts["wrong_reject"] == 2
    assert all(counts[k] == 1 for k in OUTCOMES if k not in ("success", "wrong_reject"))
    assert outcome_counts([]) == dict.fromkeys(OUTCOMES, 0)


# ----- reports ---------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def report_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("report")
    runs = [RunResults("Heuristic", synthetic(24, 0.4, seed=11)), RunResults("+Variant", synthetic(24, 0.6, seed=12))]
    written = write_report(runs, out)
    assert {p.name for p in written} == {"main.md", "main.csv", "main.tex", "ablation.md", "ablation.csv", "ablation.tex",
                                         "outcomes.md", "outcomes.csv", "comms.md", "comms.csv", "sensing.md", "sensing.csv",
                                         "cost.md", "cost.csv",
                                         "stagewise.png"}  # no card.md: these runs have no run.json
    return out


def test_report_files_exist(report_dir: Path) -> None:
    for name in ("main.md", "main.csv", "main.tex", "ablation.md", "ablation.csv", "ablation.tex", "outcomes.md",
                 "outcomes.csv", "stagewise.png"):
        assert (report_dir / name).is_file(), name
        assert (report_dir / name).stat().st_size > 0, name


def test_report_main_table(report_dir: Path) -> None:
    tex = (report_dir / "main.tex").read_text()
    for rule in (r"\toprule", r"\midrule", r"\bottomrule"):
        assert rule in tex
    assert r"\quad Variant" in tex
    assert r"\quad Heuristic" not in tex and "Heuristic &" in tex
    md = (report_dir / "main.md").read_text()
    assert "&nbsp;&nbsp;Variant" in md
    assert "| Heuristic |" in md
    with open(report_dir / "main.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    assert [r["Method"] for r in rows] == ["Heuristic", "+Variant"]
    assert "Easy SR" in rows[0] and "Hard DS" in rows[0]


def test_report_ablation_csv(report_dir: Path) -> None:
    with open(report_dir / "ablation.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    assert "CErr" in rows[0] and "GVA_support" in rows[0]
    levels = [(r["Condition"], r["Difficulty"]) for r in rows if r["Difficulty"] in ("easy", "mid", "hard")]
    assert levels == [(run, d) for run in ("Heuristic", "Variant") for d in ("easy", "mid", "hard")]
    # then exactly one total row per run (the paper's "Total")
    rest = [(r["Condition"], r["Difficulty"]) for r in rows if r["Difficulty"] not in ("easy", "mid", "hard")]
    assert rest == [("Heuristic", "total"), ("Variant", "total")]
    assert all(r["CErr"] for r in rows)


def test_report_outcomes(report_dir: Path) -> None:
    with open(report_dir / "outcomes.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    assert [r["Run"] for r in rows] == ["Heuristic", "Variant"]
    assert all(sum(int(r[k]) for k in OUTCOMES) == 24 for r in rows)


def test_report_png(report_dir: Path) -> None:
    data = (report_dir / "stagewise.png").read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n"
    assert len(data) > 5000


def test_compare_warns_when_a_difficulty_has_too_few_pairs() -> None:
    from agos.evaluator.comparison import MIN_PAIRS_PER_LEVEL

    few = compare(synthetic(6, 0.5, seed=1), synthetic(6, 0.7, seed=2), resamples=200)
    assert few.warnings and all("too narrow" in w for w in few.warnings)
    assert len(few.warnings) == sum(n < MIN_PAIRS_PER_LEVEL for n in few.per_level.values())
    many = compare(synthetic(90, 0.5, seed=1), synthetic(90, 0.7, seed=2), resamples=200)
    assert many.warnings == []


def test_the_sensing_table_puts_pose_error_and_the_model_link_beside_sr() -> None:
    """Records of a run with localisation error and a link to the model: the per-role error, the
    degraded share and the model link's time and bytes per decision; '-' where a run has none."""
    import dataclasses

    from agos.evaluator.paper_report import sensing_rows

    plain = synthetic(6, 0.5, seed=3)
    noisy = [dataclasses.replace(e, pose_error={"uav": {"mean_m": 2.0 + i, "max_m": 4.0 + i, "degraded_share": 0.0},
                                                "ugv": {"mean_m": 3.0, "max_m": 9.5, "degraded_share": 0.5}},
                                 model_link={"profile": "lte", "decisions": 10, "bytes_up": 2_000_000, "bytes_down": 5000,
                                             "link_time_s": 4.0, "max_link_time_s": 0.6, "failed": 1})
             for i, e in enumerate(synthetic(6, 0.5, seed=3))]
    header, rows = sensing_rows([RunResults("exact", plain), RunResults("gnss", noisy)])
    exact, gnss = (dict(zip(header, row, strict=True)) for row in rows)
    assert exact["pose error UAV m (max)"] == "-" and exact["model link s/decision"] == "-"
    assert gnss["pose error UAV m (max)"] == "4.50 (9.0)" and gnss["pose error UGV m (max)"] == "3.00 (9.5)"
    assert gnss["UGV degraded %"] == "50" and gnss["model link s/decision"] == "0.40"
    assert gnss["kB up/decision"] == "200" and gnss["model link failed"] == "6"
    assert exact["SR"] == gnss["SR"]
