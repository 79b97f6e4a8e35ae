"""Every metric of evaluator/metrics.py pinned by hand-computed values (arithmetic in the comments)."""

from __future__ import annotations

import math
from typing import Any

import pytest

from agos.evaluator.metrics import (
    METRIC_KEYS,
    acg,
    aggregate,
    as_json,
    ase,
    candidate_errors,
    decision_steps,
    false_confirm,
    final_distance,
    gva_included,
    navigation_error,
    oracle_success,
    spl,
    success,
    summarize,
)
from agos.evaluator.summary import EpisodeSummary


def ep(**kw: Any) -> EpisodeSummary:
    """A finished, failed, unobserved episode with no candidates; keyword arguments override."""
    base: dict[str, Any] = dict(
        episode_id="e", difficulty="easy", success=False, ground_observed=False, n_confirm=0,
        ugv_path_length_m=0.0, shortest_path_length_m=None, final_distance_m=None, uav_budget=80,
        uav_first_visible_step=None, candidates=[], decisions_uav=0, decisions_ugv=0)
    base.update(kw)
    return EpisodeSummary.model_validate(base)


def cands(*distances: float, errors: tuple[float, ...] | None = None) -> list[dict[str, float]]:
    errs = errors if errors is not None else (0.0,) * len(distances)
    return [{"distance_to_polygon_m": float(d), "center_error_m": float(e)} for d, e in zip(distances, errs, strict=True)]


# ----- SR, OSR ---------------------------------------------------------------------------------
def test_success_and_oracle_success() -> None:
    assert success(ep(success=True, ground_observed=True, n_confirm=1)) == 1.0
    assert success(ep()) == 0.0
    assert oracle_success(ep(ground_observed=True)) == 1.0
    assert oracle_success(ep()) == 0.0
    # SR = (1 + 0 + 0) / 3, OSR = (1 + 1 + 0) / 3
    s = summarize([ep(success=True, ground_observed=True, n_confirm=1), ep(ground_observed=True), ep()])
    assert pytest.approx(1 / 3) == s.SR
    assert pytest.approx(2 / 3) == s.OSR


# ----- SPL -------------------------------------------------------------------------------------
@pytest.mark.parametrize(("kw", "expected"), [
    # C=1: L / max(P, L) = 50 / max(100, 50) = 0.5
    ({"success": True, "ugv_path_length_m": 100.0, "shortest_path_length_m": 50.0}, 0.5),
    # C=0: 0 regardless of the path
    ({"success": False, "ugv_path_length_m": 50.0, "shortest_path_length_m": 50.0}, 0.0),
    # L = P = 0: the start already verifies -> 1
    ({"success": True, "ugv_path_length_m": 0.0, "shortest_path_length_m": 0.0}, 1.0),
    # L = 0, P = 10: 0 / max(10, 0) = 0
    ({"success": True, "ugv_path_length_m": 10.0, "shortest_path_length_m": 0.0}, 0.0),
    # L unknown on success: L := P -> 120 / 120 = 1
    ({"success": True, "ugv_path_length_m": 120.0, "shortest_path_length_m": None}, 1.0),
    # L unknown and P = 0 on success: 1
    ({"success": True, "ugv_path_length_m": 0.0, "shortest_path_length_m": None}, 1.0),
    # P < L (capped): 80 / max(30, 80) = 1
    ({"success": True, "ugv_path_length_m": 30.0, "shortest_path_length_m": 80.0}, 1.0),
    # 30 / max(120, 30) = 0.25
    ({"success": True, "ugv_path_length_m": 120.0, "shortest_path_length_m": 30.0}, 0.25),
])
def test_spl(kw: dict[str, Any], expected: float) -> None:
    assert spl(ep(ground_observed=kw["success"], n_confirm=int(kw["success"]), **kw)) == pytest.approx(expected)


# ----- NE and FD --------------------------------------------------------------------------------
def test_navigation_error_over_successes_and_final_distance_over_all() -> None:
    won = dict(success=True, ground_observed=True, n_confirm=1)
    assert navigation_error(ep(final_distance_m=12.5, **won)) == 12.5
    assert navigation_error(ep(final_distance_m=12.5)) is None       # a failure has no NE_e
    assert final_distance(ep(final_distance_m=12.5)) == 12.5         # but it has a final distance
    assert navigation_error(ep(**won)) is None and final_distance(ep()) is None
    s = summarize([ep(final_distance_m=10.0, **won), ep(final_distance_m=30.0, **won),
                   ep(final_distance_m=200.0), ep(final_distance_m=None)])
    assert pytest.approx(20.0) == s.NE    # (10 + 30) / 2: the successes only
    assert pytest.approx(80.0) == s.FD    # (10 + 30 + 200) / 3: every known distance
    # no success: NE undefined (the paper's "--"), never 0; FD still defined
    failed = summarize([ep(final_distance_m=60.0), ep(final_distance_m=90.0)])
    assert failed.NE is None and pytest.approx(75.0) == failed.FD
    assert summarize([ep(), ep()]).FD is None


# ----- ASE -------------------------------------------------------------------------------------
@pytest.mark.parametrize(("tau", "expected"), [
    (1, 1.0),             # (80 - 1 + 1) / 80 = 1
    (2, 79 / 80),         # (80 - 2 + 1) / 80
    (41, 0.5),            # (80 - 41 + 1) / 80 = 40 / 80
    (80, 1 / 80),         # (80 - 80 + 1) / 80
    (None, 0.0),          # never visible from the air
    (81, 0.0),            # beyond T: (80 - 81 + 1) / 80 = 0
    (200, 0.0),           # far beyond T: clamped to 0
])
def test_ase(tau: int | None, expected: float) -> None:
    assert ase(ep(uav_budget=80, uav_first_visible_step=tau)) == pytest.approx(expected)


# ----- ACG -------------------------------------------------------------------------------------
def test_acg_no_candidates_is_zero() -> None:
    assert acg(ep()) == 0.0


def test_acg_single_candidate() -> None:
    # j = 1, d = 0: 1/log2(2) * 50/(50 + 0) = 1
    assert acg(ep(candidates=cands(0))) == pytest.approx(1.0)
    # d = 50 = R: 1 * 50/100 = 0.5
    assert acg(ep(candidates=cands(50))) == pytest.approx(0.5)
    # d = 150: 50/200 = 0.25
    assert acg(ep(candidates=cands(150))) == pytest.approx(0.25)


def test_acg_max_over_ranked_candidates() -> None:
    # j=1, d=100: 50/150 = 1/3; j=2, d=0: 1/log2(3) = 0.63093 -> max = 0.63093
    value = acg(ep(candidates=cands(100, 0)))
    assert value == pytest.approx(1 / math.log2(3))
    assert value == pytest.approx(0.6309297535714575)
    # the reverse order: j=1, d=0 gives 1
    assert acg(ep(candidates=cands(0, 100))) == pytest.approx(1.0)
    # both far: j=1 d=150 -> 0.25; j=2 d=50 -> 0.5 / log2(3) = 0.31546 -> 0.31546
    assert acg(ep(candidates=cands(150, 50))) == pytest.approx(0.5 / math.log2(3))


@pytest.mark.parametrize(("j", "discount"), [
    (1, 1.0),                     # 1/log2(2)
    (2, 0.6309297535714575),      # 1/log2(3)
    (3, 0.5),                     # 1/log2(4)
    (4, 0.43067655807339306),     # 1/log2(5)
])
def test_acg_rank_discount(j: int, discount: float) -> None:
    # the only d = 0 candidate sits at rank j; all earlier ones are infinitely bad (d huge -> ~0)
    distances = [1e12] * (j - 1) + [0.0]
    assert acg(ep(candidates=cands(*distances))) == pytest.approx(discount)


# ----- GVA -------------------------------------------------------------------------------------
def test_gva_invalid_confirm_is_in_denominator_and_scores_zero() -> None:
    bad = ep(success=False, ground_observed=False, n_confirm=1)
    assert false_confirm(bad) and gva_included(bad)
    s = summarize([bad])
    assert (s.GVA, s.GVA_support) == (0.0, 1)


def test_gva_observed_without_confirm_counts_zero() -> None:
    e = ep(success=False, ground_observed=True, n_confirm=0)
    assert gva_included(e) and not false_confirm(e)
    s = summarize([e])
    assert (s.GVA, s.GVA_support) == (0.0, 1)


def test_gva_success_counts_one() -> None:
    s = summarize([ep(success=True, ground_observed=True, n_confirm=1)])
    assert (s.GVA, s.GVA_support) == (1.0, 1)


def test_gva_mixed_and_zero_support() -> None:
    episodes = [
        ep(success=True, ground_observed=True, n_confirm=1),    # V=1, C=1
        ep(success=False, ground_observed=False, n_confirm=1),  # V=1 (false confirm), C=0
        ep(success=False, ground_observed=True, n_confirm=0),   # V=1 (observed), C=0
        ep(success=False, ground_observed=False, n_confirm=0),  # V=0: not in the denominator
    ]
    s = summarize(episodes)
    # sum V*C / sum V = 1 / 3
    assert pytest.approx(1 / 3) == s.GVA
    assert s.GVA_support == 3
    none = summarize([ep(), ep()])
    assert none.GVA is None and none.GVA_support == 0


# ----- DS --------------------------------------------------------------------------------------
def test_decision_steps() -> None:
    assert decision_steps(ep(decisions_uav=12, decisions_ugv=7)) == 19.0
    s = summarize([ep(decisions_uav=10, decisions_ugv=4), ep(decisions_uav=30, decisions_ugv=0)])
    # DS = ((10+4) + (30+0)) / 2 = 22; DS_UAV = (10+30)/2 = 20; DS_UGV = (4+0)/2 = 2
    assert (pytest.approx(22.0), pytest.approx(20.0), pytest.approx(2.0)) == (s.DS, s.DS_UAV, s.DS_UGV)


# ----- CErr ------------------------------------------------------------------------------------
def test_cerr_pools_candidates_across_episodes() -> None:
    e1 = ep(candidates=cands(0, 0, errors=(10.0, 20.0)))
    e2 = ep(candidates=cands(0, errors=(40.0,)))
    e3 = ep()  # no candidates: contributes nothing
    assert candidate_errors(e1) == [10.0, 20.0]
    # candidate-level: (10 + 20 + 40) / 3 = 70/3 = 23.33 (episode-level would be (15 + 40) / 2 = 27.5)
    assert summarize([e1, e2, e3]).CErr == pytest.approx(70 / 3)


def test_cerr_none_without_candidates() -> None:
    assert summarize([ep(), ep()]).CErr is None


# ----- aggregate -------------------------------------------------------------------------------
def _three_levels() -> list[EpisodeSummary]:
    return [
        # easy
        ep(episode_id="e1", difficulty="easy", success=True, ground_observed=True, n_confirm=1,
           ugv_path_length_m=100.0, shortest_path_length_m=50.0, final_distance_m=10.0, uav_first_visible_step=1,
           candidates=cands(0, errors=(10.0,)), decisions_uav=10, decisions_ugv=5),
        ep(episode_id="e2", difficulty="easy", success=True, ground_observed=True, n_confirm=1,
           ugv_path_length_m=40.0, shortest_path_length_m=40.0, final_distance_m=20.0, uav_first_visible_step=80,
           candidates=cands(50, errors=(20.0,)), decisions_uav=20, decisions_ugv=10),
        ep(episode_id="e3", difficulty="easy", ugv_path_length_m=200.0, decisions_uav=30, decisions_ugv=15),
        # mid: a false confirm, NE unknown
        ep(episode_id="m1", difficulty="mid", n_confirm=1, ugv_path_length_m=60.0,
           candidates=cands(100, errors=(40.0,)), decisions_uav=40, decisions_ugv=20),
        # hard: one infrastructure failure (not scored) and one plain failure with GVA support 0
        ep(episode_id="h1", difficulty="hard", status="world_crashed", success=True, ground_observed=True, n_confirm=1,
           final_distance_m=0.0, decisions_uav=99, decisions_ugv=99),
        ep(episode_id="h2", difficulty="hard", ugv_path_length_m=10.0, shortest_path_length_m=0.0, final_distance_m=100.0,
           uav_first_visible_step=40, decisions_uav=50, decisions_ugv=25),
    ]


def test_aggregate_per_level() -> None:
    out = aggregate(_three_levels())
    assert list(out) == ["easy", "mid", "hard", "overall"]
    easy, mid, hard = out["easy"], out["mid"], out["hard"]
    assert (easy.n, easy.excluded) == (3, 0)
    assert pytest.approx(2 / 3) == easy.SR                 # (1 + 1 + 0) / 3
    assert pytest.approx(2 / 3) == easy.OSR
    assert pytest.approx(0.5) == easy.SPL                  # (50/100 + 40/40 + 0) / 3 = 1.5 / 3
    assert pytest.approx(15.0) == easy.NE                  # (10 + 20) / 2: e1, e2 succeeded
    assert pytest.approx(15.0) == easy.FD                  # (10 + 20) / 2: e3's distance unknown
    assert pytest.approx(27 / 80) == easy.ASE              # (80/80 + 1/80 + 0) / 3 = (81/80) / 3
    assert pytest.approx(0.5) == easy.ACG                  # (1 + 0.5 + 0) / 3
    assert (easy.GVA, easy.GVA_support) == (1.0, 2)        # e1, e2 in V, both C
    assert (easy.DS, easy.DS_UAV, easy.DS_UGV) == (30.0, 20.0, 10.0)  # (15+30+45)/3, (10+20+30)/3, (5+10+15)/3
    assert easy.CErr == pytest.approx(15.0)                # (10 + 20) / 2

    assert (mid.n, mid.SR, mid.OSR, mid.SPL, mid.NE, mid.FD, mid.ASE) == (1, 0.0, 0.0, 0.0, None, None, 0.0)
    assert pytest.approx(1 / 3) == mid.ACG                 # 50 / 150
    assert (mid.GVA, mid.GVA_support) == (0.0, 1)          # the false confirm
    assert (mid.DS, mid.CErr) == (60.0, 40.0)

    assert (hard.n, hard.excluded) == (1, 1)
    assert (hard.SR, hard.SPL, hard.NE, hard.FD, hard.ACG) == (0.0, 0.0, None, 100.0, 0.0)  # SPL: C=0; NE: no success
    assert pytest.approx(41 / 80) == hard.ASE              # (80 - 40 + 1) / 80
    assert (hard.GVA, hard.GVA_support, hard.CErr) == (None, 0, None)
    assert hard.DS == 75.0


def test_aggregate_overall_is_macro_mean() -> None:
    o = aggregate(_three_levels())["overall"]
    assert (o.n, o.excluded, o.GVA_support) == (5, 1, 3)   # 3 + 1 + 1 scored; h1 not scored; 2 + 1 + 0
    assert pytest.approx(2 / 9) == o.SR                    # (2/3 + 0 + 0) / 3; the micro mean would be 2/5
    assert pytest.approx(2 / 5) != o.SR
    assert pytest.approx(2 / 9) == o.OSR
    assert pytest.approx(1 / 6) == o.SPL                   # (0.5 + 0 + 0) / 3
    assert pytest.approx(15.0) == o.NE                     # easy's 15: mid and hard (None, no success) left out
    assert pytest.approx(57.5) == o.FD                     # (15 + 100) / 2: mid (None) left out, not counted as 0
    assert pytest.approx(17 / 60) == o.ASE                 # (27/80 + 0 + 41/80) / 3 = 68/240
    assert pytest.approx(5 / 18) == o.ACG                  # (1/2 + 1/3 + 0) / 3
    assert pytest.approx(0.5) == o.GVA                     # (1 + 0) / 2: hard (None) left out; micro would be 2/3
    assert pytest.approx(55.0) == o.DS                     # (30 + 60 + 75) / 3
    assert pytest.approx(110 / 3) == o.DS_UAV              # (20 + 40 + 50) / 3
    assert pytest.approx(55 / 3) == o.DS_UGV               # (10 + 20 + 25) / 3
    assert o.CErr == pytest.approx(27.5)                   # (15 + 40) / 2: hard (None) left out


def test_aggregate_level_with_only_unscored_episodes() -> None:
    episodes = [
        ep(episode_id="e1", difficulty="easy", success=True, ground_observed=True, n_confirm=1, final_distance_m=4.0),
        ep(episode_id="h1", difficulty="hard", status="world_crashed"),
        ep(episode_id="h2", difficulty="hard", status="agent_crashed"),
        ep(episode_id="h3", difficulty="hard", status="timeout"),
    ]
    out = aggregate(episodes)
    assert list(out) == ["easy", "hard", "overall"]
    hard = out["hard"]
    assert (hard.n, hard.excluded) == (0, 3)
    assert all(getattr(hard, k) is None for k in METRIC_KEYS if k != "GVA_support")
    assert hard.GVA_support == 0
    o = out["overall"]
    # the empty level does not drag the macro mean down: SR = 1 / 1, NE = 4
    assert (o.n, o.excluded, o.SR, o.NE) == (1, 3, 1.0, 4.0)


def test_undefined_metrics_stay_none_for_an_empty_set() -> None:
    s = summarize([])
    assert s.n == 0 and s.excluded == 0
    assert all(getattr(s, k) is None for k in METRIC_KEYS if k != "GVA_support")


def test_aggregate_by_town() -> None:
    episodes = [
        ep(episode_id="a", town_id="town-b", success=True, ground_observed=True, n_confirm=1),
        ep(episode_id="b", town_id="town-a", difficulty="hard"),
        ep(episode_id="c", town_id="town-a", difficulty="mid", success=True, ground_observed=True, n_confirm=1),
        ep(episode_id="d", town_id="town-a", difficulty="mid", success=True, ground_observed=True, n_confirm=1),
        ep(episode_id="e"),  # no town
    ]
    out = aggregate(episodes, by="town")
    assert list(out) == ["town-a", "town-b", "unknown", "overall"]
    assert (out["town-a"].n, out["town-a"].SR) == (3, pytest.approx(2 / 3))
    assert (out["town-b"].n, out["town-b"].SR) == (1, 1.0)
    assert (out["unknown"].n, out["unknown"].SR) == (1, 0.0)
    # macro over towns: (2/3 + 1 + 0) / 3 = 5/9
    assert pytest.approx(5 / 9) == out["overall"].SR
    with pytest.raises(ValueError, match="group"):
        aggregate(episodes, by="weather")


def test_as_json_keys() -> None:
    data = as_json(aggregate(_three_levels()))
    assert set(data) == {"easy", "mid", "hard", "overall"}
    expected = {"SR", "OSR", "SPL", "NE", "FD", "ASE", "ACG", "GVA", "GVA_support", "DS", "DS_UAV", "DS_UGV", "CErr",
                "n", "not_scored", "infra_error"}
    for row in data.values():
        assert set(row) == expected
    assert data["hard"]["GVA"] is None and data["hard"]["not_scored"] == 1
    assert data["overall"]["n"] == 5 and data["overall"]["not_scored"] == 1
    assert data["overall"]["infra_error"] == 0  # h1 crashed its world: not scored, no infra error


def test_infra_errors_are_counted_and_never_scored() -> None:
    """An episode whose model endpoint never answered (status infra_error) changes no metric: the same
    summaries as without it, one more not scored, and counted as an infra error in its level and overall."""
    scored = _three_levels()
    lost = [ep(episode_id="h3", difficulty="hard", status="infra_error"),
            ep(episode_id="m2", difficulty="mid", status="infra_error", decisions_uav=3)]
    with_lost, without = aggregate(scored + lost), aggregate(scored)
    for level in ("mid", "hard", "overall"):
        metrics = {k: getattr(with_lost[level], k) for k in METRIC_KEYS}
        assert metrics == {k: getattr(without[level], k) for k in METRIC_KEYS}, level
        assert with_lost[level].n == without[level].n
    assert (with_lost["mid"].excluded, with_lost["mid"].infra_errors) == (1, 1)
    assert (with_lost["hard"].excluded, with_lost["hard"].infra_errors) == (2, 1)   # h1 world_crashed, h3
    assert (with_lost["overall"].excluded, with_lost["overall"].infra_errors) == (3, 2)
    assert as_json(with_lost)["overall"]["infra_error"] == 2
