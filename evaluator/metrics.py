"""Every metric of the paper as a pure function of one episode summary, and their aggregation.

Notation (paper §4.3 and Appendix B): for episode e, C_e = success, O_e = ground_observed,
P_e = UGV path length, L_e = shortest path to a verifying pose, T_e = UAV budget,
tau_e = first oracle-visible UAV step (1-based), d_{e,j} = target-to-candidate-polygon
distance of the j-th candidate, D_e = final UGV-to-target distance, K_e = decisions. R = 50 m.

Undefined values are ``None``, never 0. Only episodes with status ``finished`` are scored;
infrastructure failures are counted apart (``excluded``). Two ways to make one row of several
difficulty levels: :func:`macro` (the paper's overall figures, the mean of the levels) and
:func:`ablation_total` (the ablation table's Total: GVA, NE, FD and CErr pooled over episodes).
See docs/METRICS.md for every decision where the paper is silent or reads two ways.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, replace
from typing import Any, Protocol

from agos.runtime.schemas import DIFFICULTIES

R_M = 50.0
"""Benchmark spatial scale R of ACG (metres)."""
DIFFICULTY_ORDER: tuple[str, ...] = DIFFICULTIES
"""The difficulties in the order of tables and figures."""
METRIC_KEYS = ("SR", "OSR", "SPL", "NE", "FD", "ASE", "ACG", "GVA", "GVA_support", "DS", "DS_UAV", "DS_UGV", "CErr")


class _Candidate(Protocol):
    # Read-only members (properties), so frozen dataclasses and structs fit too.
    @property
    def distance_to_polygon_m(self) -> float: ...
    @property
    def center_error_m(self) -> float: ...


class Episode(Protocol):
    """What the metrics read: :class:`EpisodeSummary` and :class:`EpisodeRecord` both fit.

    Members are read-only (properties): the metrics never assign, and frozen summaries fit."""

    @property
    def difficulty(self) -> str: ...
    @property
    def status(self) -> str: ...
    @property
    def success(self) -> bool: ...
    @property
    def ground_observed(self) -> bool: ...
    @property
    def n_confirm(self) -> int: ...
    @property
    def ugv_path_length_m(self) -> float: ...
    @property
    def shortest_path_length_m(self) -> float | None: ...
    @property
    def final_distance_m(self) -> float | None: ...
    @property
    def uav_budget(self) -> int: ...
    @property
    def uav_first_visible_step(self) -> int | None: ...
    @property
    def candidates(self) -> Sequence[_Candidate]: ...
    @property
    def decisions_uav(self) -> int: ...
    @property
    def decisions_ugv(self) -> int: ...
    @property
    def candidate_tools(self) -> bool:
        """The policy could annotate candidates (ACG is undefined without)."""
        ...


# ----- episode-level metrics -------------------------------------------------------------------
def success(e: Episode) -> float:
    """SR_e = C_e in {0, 1}: the episode ended with a CONFIRM accepted by the checker."""
    return 1.0 if e.success else 0.0


def oracle_success(e: Episode) -> float:
    """OSR_e = O_e in {0, 1}: at some STOP_OBSERVE the checker would have accepted a CONFIRM."""
    return 1.0 if e.ground_observed else 0.0


def spl(e: Episode) -> float:
    """SPL_e = C_e * L_e / max(P_e, L_e).

    Edge cases: a failure scores 0; L_e = P_e = 0 (the start already verifies) scores 1;
    a success whose L_e is unknown (null) uses L_e = P_e, i.e. scores 1.
    """
    if not e.success:
        return 0.0
    shortest = e.shortest_path_length_m if e.shortest_path_length_m is not None else e.ugv_path_length_m
    longest = max(e.ugv_path_length_m, shortest)
    return 1.0 if longest == 0 else shortest / longest


def final_distance(e: Episode) -> float | None:
    """D_e: horizontal distance (m) from the UGV's final position to the target; None if unknown.
    Its mean over every scored episode is FD (all-episode final distance)."""
    return e.final_distance_m


def navigation_error(e: Episode) -> float | None:
    """NE_e = D_e of a successful episode; None for a failed one, so that NE, the mean of NE_e,
    averages the final distance over successful episodes only and is undefined without any (the
    paper's "--")."""
    return e.final_distance_m if e.success else None


def ase(e: Episode) -> float:
    """ASE_e = (T_e - tau_e + 1) / T_e if the target became oracle-visible from the air, else 0.

    tau_e is 1-based, so seeing the target at the first UAV step scores 1. A tau_e beyond T_e
    (not possible with a shared budget) is clamped to score 0.
    """
    if e.uav_first_visible_step is None:
        return 0.0
    return max(0.0, (e.uav_budget - e.uav_first_visible_step + 1) / e.uav_budget)


def acg(e: Episode, r_m: float = R_M) -> float:
    """ACG_e = max_j [ 1/log2(j+1) * R/(R + d_{e,j}) ] over the candidates in order (j = 1, 2, ...);
    0 without candidates. d = 0 (target inside the polygon) and j = 1 give 1."""
    return max((r_m / (r_m + c.distance_to_polygon_m) / math.log2(j + 1)
                for j, c in enumerate(e.candidates, start=1)), default=0.0)


def false_confirm(e: Episode) -> bool:
    """F_e = [C_e = 0 and n_conf_e > 0]: a CONFIRM was issued but the episode did not succeed."""
    return not e.success and e.n_confirm > 0


def gva_included(e: Episode) -> bool:
    """V_e = [O_e = 1 or F_e = 1]: the episode counts in the GVA denominator."""
    return e.ground_observed or false_confirm(e)


def decision_steps(e: Episode) -> float:
    """K_e = K_e^UAV + K_e^UGV (logical decisions; fallbacks count, retries and repairs do not)."""
    return float(e.decisions_uav + e.decisions_ugv)


def candidate_errors(e: Episode) -> list[float]:
    """Centre errors (m) of the episode's candidates, for CErr."""
    return [c.center_error_m for c in e.candidates]


# ----- aggregation -----------------------------------------------------------------------------
@dataclass(frozen=True)
class Summary:
    """Dataset-level metrics of a set of episodes (rates are fractions in [0, 1])."""

    n: int
    SR: float | None
    OSR: float | None
    SPL: float | None
    NE: float | None
    """Mean final distance over successful episodes; None without one."""
    FD: float | None
    """Mean final distance over every scored episode whose distance is known."""
    ASE: float | None
    ACG: float | None
    GVA: float | None
    """sum V_e C_e / sum V_e; None when GVA_support is 0."""
    GVA_support: int
    DS: float | None
    DS_UAV: float | None
    DS_UGV: float | None
    CErr: float | None
    """Mean centre error over all candidates of the episodes (candidate-level pooling)."""
    excluded: int = 0
    """Episodes not scored (status other than ``finished``)."""
    infra_errors: int = 0
    """Of those, episodes whose model endpoint gave no answer in every attempt (status ``infra_error``):
    neither successes nor failures of the model, counted so a table shows the outage."""

    def as_dict(self) -> dict[str, Any]:
        out = {k: getattr(self, k) for k in METRIC_KEYS}
        out["n"], out["not_scored"], out["infra_error"] = self.n, self.excluded, self.infra_errors
        return out


def _mean(values: Iterable[float | None]) -> float | None:
    vals = [v for v in values if v is not None]
    return sum(vals) / len(vals) if vals else None


def summarize(episodes: Sequence[Episode]) -> Summary:
    """All metrics of a set of episodes in one pass (each episode-level function called once)."""
    n = excluded = infra = support = verified = 0
    sr = osr = spl_sum = ase_sum = acg_sum = ds_uav = ds_ugv = ne_sum = fd_sum = err_sum = 0.0
    ne_n = fd_n = err_n = acg_n = 0
    for e in episodes:
        if e.status != "finished":
            excluded += 1
            infra += e.status == "infra_error"
            continue
        n += 1
        sr += success(e)
        osr += oracle_success(e)
        spl_sum += spl(e)
        ase_sum += ase(e)
        if e.candidate_tools:  # without candidate tools (Baseline) ACG is undefined, not 0
            acg_sum += acg(e)
            acg_n += 1
        ds_uav += e.decisions_uav
        ds_ugv += e.decisions_ugv
        fd = final_distance(e)
        if fd is not None:
            fd_sum += fd
            fd_n += 1
            if e.success:  # NE_e (navigation_error) without calling it twice
                ne_sum += fd
                ne_n += 1
        if gva_included(e):
            support += 1
            verified += e.success
        errors = candidate_errors(e)
        err_sum += sum(errors)
        err_n += len(errors)
    if n == 0:
        return Summary(0, None, None, None, None, None, None, None, None, 0, None, None, None, None, excluded, infra)
    return Summary(
        n=n, SR=sr / n, OSR=osr / n, SPL=spl_sum / n, NE=ne_sum / ne_n if ne_n else None,
        FD=fd_sum / fd_n if fd_n else None, ASE=ase_sum / n,
        ACG=acg_sum / acg_n if acg_n else None, GVA=verified / support if support else None, GVA_support=support,
        DS=(ds_uav + ds_ugv) / n, DS_UAV=ds_uav / n, DS_UGV=ds_ugv / n, CErr=err_sum / err_n if err_n else None,
        excluded=excluded, infra_errors=infra)


def macro(groups: Sequence[Summary]) -> Summary:
    """The paper's overall figures ("macro-averaged" SR and DS, stage metrics "macro-averaged across
    difficulty levels"): the unweighted mean over groups of each metric (groups where it is undefined
    are left out); GVA_support, n, excluded and infra_errors are summed."""
    values = {k: _mean(getattr(g, k) for g in groups if g.n) for k in METRIC_KEYS if k != "GVA_support"}
    return Summary(n=sum(g.n for g in groups), GVA_support=sum(g.GVA_support for g in groups),
                   excluded=sum(g.excluded for g in groups), infra_errors=sum(g.infra_errors for g in groups), **values)


POOLED_IN_TOTAL = ("GVA", "NE", "FD", "CErr")
"""Metrics whose ablation-table Total pools episodes (or candidates) instead of averaging levels."""


def ablation_total(episodes: Sequence[Episode]) -> Summary:
    """The Total row of the paper's ablation table: GVA (sum V_e C_e / sum V_e), NE, FD and CErr
    computed on all scored episodes of every level at once, so a level weighs by its support,
    successes or candidates; every other metric is the :func:`macro` mean of the levels (with equal
    episodes per level, as in the paper, the same as pooling)."""
    overall = aggregate(episodes, "difficulty")["overall"]
    pooled = summarize(episodes)
    return replace(overall, **{k: getattr(pooled, k) for k in POOLED_IN_TOTAL})


def group_key(by: str) -> Callable[[Any], str]:
    if by == "difficulty":
        return lambda e: e.difficulty
    if by == "town":
        return lambda e: getattr(e, "town_id", None) or "unknown"
    raise ValueError(f"cannot group by {by!r}; use difficulty or town")


def aggregate(episodes: Sequence[Episode], by: str = "difficulty") -> dict[str, Summary]:
    """Per group (difficulty levels in easy, mid, hard order; towns sorted) plus ``overall``."""
    key = group_key(by)
    groups: dict[str, list[Episode]] = {}
    for e in episodes:
        groups.setdefault(key(e), []).append(e)
    order = [d for d in DIFFICULTY_ORDER if d in groups] if by == "difficulty" else sorted(groups)
    out = {name: summarize(groups[name]) for name in order}
    out["overall"] = macro(list(out.values()))
    return out


def by_difficulty(episodes: Sequence[Episode]) -> dict[str, Summary]:
    return aggregate(episodes, "difficulty")


def as_json(summaries: dict[str, Summary]) -> dict[str, dict[str, Any]]:
    return {name: s.as_dict() for name, s in summaries.items()}

