"""Task metrics over episode records (paper §4.3, computed from the UGV trajectory and the
ground verification only). Pure functions; aggregation is a mean over episodes.

Only episodes whose status is ``finished`` are scored: infrastructure failures
(``world_crashed``, ``agent_crashed``, ``timeout``, ``invalid``) are counted apart and never
as agent failures (STYLE.md item 7).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

from agos.runtime.schemas import EpisodeRecord

DIFFICULTY_ORDER = ("easy", "mid", "hard")


def success(r: EpisodeRecord) -> float:
    """SR_e = C_e: the episode ended with a CONFIRM accepted by the checker."""
    return 1.0 if r.success else 0.0


def oracle_success(r: EpisodeRecord) -> float:
    """OSR_e = O_e: at some STOP_OBSERVE the checker would have accepted a CONFIRM."""
    return 1.0 if r.ground_observed else 0.0


def spl(r: EpisodeRecord) -> float:
    """SPL_e = S_e * L_e / max(P_e, L_e), with L_e the road distance from the UGV start to the
    nearest pose where CONFIRM succeeds and P_e the UGV's driven path length.

    Edge cases: a failed episode scores 0; L_e = P_e = 0 (start already verifying) scores 1;
    a success whose L_e could not be found (the world's search gave up) uses L_e = P_e.
    """
    if not r.success:
        return 0.0
    shortest = r.shortest_path_length_m if r.shortest_path_length_m is not None else r.ugv_path_length_m
    longest = max(r.ugv_path_length_m, shortest)
    return 1.0 if longest == 0 else shortest / longest


def navigation_error(r: EpisodeRecord) -> float:
    """NE_e: horizontal distance (m) from the UGV's final position to the target."""
    return r.final_distance_m


def decision_steps(r: EpisodeRecord) -> float:
    """DS_e = K_e^UAV + K_e^UGV: logical decisions of both roles (fallbacks included)."""
    return float(r.decisions_uav + r.decisions_ugv)


@dataclass(frozen=True)
class Summary:
    n: int
    SR: float | None
    OSR: float | None
    SPL: float | None
    NE: float | None
    DS: float | None
    excluded: int = 0
    """Episodes not scored because of an infrastructure status."""


def _mean(values: Sequence[float]) -> float | None:
    return sum(values) / len(values) if values else None


def summarize(records: Sequence[EpisodeRecord]) -> Summary:
    scored = [r for r in records if r.status == "finished"]
    return Summary(
        n=len(scored), SR=_mean([success(r) for r in scored]), OSR=_mean([oracle_success(r) for r in scored]),
        SPL=_mean([spl(r) for r in scored]), NE=_mean([navigation_error(r) for r in scored]),
        DS=_mean([decision_steps(r) for r in scored]), excluded=len(records) - len(scored))


def by_difficulty(records: Sequence[EpisodeRecord]) -> dict[str, Summary]:
    """Per difficulty, plus ``overall``: the macro mean over the difficulty levels present."""
    out: dict[str, Summary] = {}
    for level in DIFFICULTY_ORDER:
        subset = [r for r in records if r.difficulty == level]
        if subset:
            out[level] = summarize(subset)
    levels = [s for s in out.values() if s.n]

    def macro(name: str) -> float | None:
        vals = [getattr(s, name) for s in levels if getattr(s, name) is not None]
        return _mean(vals)

    out["overall"] = Summary(n=sum(s.n for s in out.values()), SR=macro("SR"), OSR=macro("OSR"), SPL=macro("SPL"),
                             NE=macro("NE"), DS=macro("DS"), excluded=sum(s.excluded for s in out.values()))
    return out
