"""Paired comparison of two runs on the episodes they share.

For each metric: the difference A - B of the overall value (macro mean over difficulty levels,
as in the tables), a 95 % percentile bootstrap interval that resamples episodes *within* each
difficulty level (pairs stay together; seeded; 10,000 resamples by default), and a two-sided
paired permutation test (each episode's A/B labels swapped with probability 1/2). For SR, an
exact sign test on the discordant episodes and the outcome matrix are given as well.

Ratio metrics are resampled as ratios: GVA = sum(V*C)/sum(V), CErr = sum(errors)/count. NE is a
mean over each run's successful episodes (a failure's NE_e is undefined), so a resample without a
success in some level leaves that level out of NE's overall, as the tables do.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from agos.evaluator.metrics import (
    DIFFICULTY_ORDER,
    acg,
    ase,
    candidate_errors,
    final_distance,
    gva_included,
    navigation_error,
    oracle_success,
    spl,
    success,
)
from agos.evaluator.summary import EpisodeSummary

MEAN_METRICS = {
    "SR": success, "OSR": oracle_success, "SPL": spl, "NE": navigation_error, "FD": final_distance, "ASE": ase,
    "ACG": lambda e: acg(e) if e.candidate_tools else None,
    "DS": lambda e: float(e.decisions_uav + e.decisions_ugv),
    "DS_UAV": lambda e: float(e.decisions_uav), "DS_UGV": lambda e: float(e.decisions_ugv),
}
RATIO_METRICS = {
    "GVA": (lambda e: float(gva_included(e) and e.success), lambda e: float(gva_included(e))),
    "CErr": (lambda e: float(sum(candidate_errors(e))), lambda e: float(len(e.candidates))),
}
COMPARED = ("SR", "OSR", "SPL", "NE", "FD", "ASE", "ACG", "GVA", "DS", "DS_UAV", "DS_UGV", "CErr")


@dataclass(frozen=True)
class MetricComparison:
    metric: str
    a: float | None
    b: float | None
    diff: float | None
    ci_low: float | None
    ci_high: float | None
    p_value: float | None


@dataclass(frozen=True)
class Comparison:
    n_pairs: int
    per_level: dict[str, int]
    metrics: list[MetricComparison]
    outcomes: dict[str, int]
    """both_succeed, only_a, only_b, neither."""
    sign_test_p: float | None
    resamples: int
    seed: int
    warnings: list[str] = field(default_factory=list)
    """Why some intervals mean little (too few paired episodes in a difficulty level)."""


MIN_PAIRS_PER_LEVEL = 10
"""Below this many paired episodes in a difficulty level, its bootstrap resamples hardly vary (with
one, not at all): the interval looks narrow because it cannot be wide, so compare says so."""


def few_pairs_warnings(per_level: dict[str, int]) -> list[str]:
    return [f"{level} has only {n} paired episode{'s' if n != 1 else ''}: its bootstrap cannot vary much, so "
            f"intervals involving it are too narrow to mean anything (use at least {MIN_PAIRS_PER_LEVEL} per difficulty)"
            for level, n in per_level.items() if n < MIN_PAIRS_PER_LEVEL]


def pair(a: Sequence[EpisodeSummary], b: Sequence[EpisodeSummary]) -> list[tuple[EpisodeSummary, EpisodeSummary]]:
    """Episodes scored in both runs, matched by episode id (sorted for determinism)."""
    bmap = {e.episode_id: e for e in b if e.status == "finished"}
    pairs = [(e, bmap[e.episode_id]) for e in a if e.status == "finished" and e.episode_id in bmap]
    for x, y in pairs:
        if x.difficulty != y.difficulty:
            raise ValueError(f"episode {x.episode_id} is {x.difficulty} in one run and {y.difficulty} in the other")
    return sorted(pairs, key=lambda p: p[0].episode_id)


def _columns(pairs, fn) -> tuple[np.ndarray, np.ndarray]:
    a = np.array([np.nan if (v := fn(x)) is None else v for x, _ in pairs], dtype=float)
    b = np.array([np.nan if (v := fn(y)) is None else v for _, y in pairs], dtype=float)
    return a, b


def _level_stat(num: np.ndarray, den: np.ndarray | None, idx: np.ndarray) -> np.ndarray:
    """Statistic of each resample (rows of ``idx``) within one level."""
    with np.errstate(invalid="ignore", divide="ignore"):
        if den is None:
            values = num[idx]
            counts = np.sum(~np.isnan(values), axis=-1)
            return np.where(counts > 0, np.nansum(values, axis=-1) / np.maximum(counts, 1), np.nan)
        d = den[idx].sum(axis=-1)
        return np.where(d > 0, num[idx].sum(axis=-1) / np.where(d > 0, d, 1), np.nan)


def _macro(level_values: list[np.ndarray]) -> np.ndarray:
    stacked = np.stack(level_values)
    with np.errstate(invalid="ignore"):
        counts = np.sum(~np.isnan(stacked), axis=0)
        return np.where(counts > 0, np.nansum(stacked, axis=0) / np.maximum(counts, 1), np.nan)


def compare(a: Sequence[EpisodeSummary], b: Sequence[EpisodeSummary], *, resamples: int = 10_000,
            seed: int = 0, chunk: int = 1000) -> Comparison:
    if resamples < 1:
        raise ValueError(f"resamples must be at least 1, not {resamples}")
    pairs = pair(a, b)
    if not pairs:
        raise ValueError("the two runs share no scored episode")
    levels = {lvl: np.array([i for i, (x, _) in enumerate(pairs) if x.difficulty == lvl])
              for lvl in DIFFICULTY_ORDER}
    levels = {k: v for k, v in levels.items() if len(v)}
    rng = np.random.default_rng(seed)
    boot_idx = {lvl: [rng.integers(0, len(ix), size=(min(chunk, resamples - s), len(ix)))
                      for s in range(0, resamples, chunk)] for lvl, ix in levels.items()}
    swaps = [rng.random((min(chunk, resamples - s), len(pairs))) < 0.5 for s in range(0, resamples, chunk)]

    results = []
    for name in COMPARED:
        if name in MEAN_METRICS:
            na, nb = _columns(pairs, MEAN_METRICS[name])
            da = db = None
        else:
            num_fn, den_fn = RATIO_METRICS[name]
            na, nb = _columns(pairs, num_fn)
            da, db = _columns(pairs, den_fn)
        results.append(_compare_metric(name, na, nb, da, db, levels, boot_idx, swaps))

    both = sum(x.success and y.success for x, y in pairs)
    only_a = sum(x.success and not y.success for x, y in pairs)
    only_b = sum(y.success and not x.success for x, y in pairs)
    outcomes = {"both_succeed": both, "only_a": only_a, "only_b": only_b, "neither": len(pairs) - both - only_a - only_b}
    per_level = {k: len(v) for k, v in levels.items()}
    return Comparison(len(pairs), per_level, results, outcomes, sign_test(only_a, only_b), resamples, seed,
                      few_pairs_warnings(per_level))


def _compare_metric(name, na, nb, da, db, levels, boot_idx, swaps) -> MetricComparison:
    def overall(num, den, rows: np.ndarray | None = None) -> float:
        vals = [_level_stat(num, den, ix[None, :] if rows is None else rows)[0] for ix in levels.values()]
        return float(_macro([np.array([v]) for v in vals])[0])

    a_val, b_val = overall(na, da), overall(nb, db)
    observed = a_val - b_val
    if math.isnan(observed):
        return MetricComparison(name, _none(a_val), _none(b_val), None, None, None, None)

    diffs = []
    for k in range(len(swaps)):
        per_a = [_level_stat(na, da, ix[boot_idx[lvl][k]]) for lvl, ix in levels.items()]
        per_b = [_level_stat(nb, db, ix[boot_idx[lvl][k]]) for lvl, ix in levels.items()]
        diffs.append(_macro(per_a) - _macro(per_b))
    boot = np.concatenate(diffs)
    boot = boot[~np.isnan(boot)]
    low, high = (np.percentile(boot, [2.5, 97.5]) if len(boot) else (np.nan, np.nan))

    extreme = total = 0
    for swap in swaps:
        sa, sb = np.where(swap, nb, na), np.where(swap, na, nb)
        sda = None if da is None else np.where(swap, db, da)
        sdb = None if db is None else np.where(swap, da, db)
        d = _swap_stat(sa, sda, levels, swap) - _swap_stat(sb, sdb, levels, swap)
        d = d[~np.isnan(d)]
        extreme += int(np.sum(np.abs(d) >= abs(observed) - 1e-12))
        total += len(d)
    p_value = (extreme + 1) / (total + 1)
    return MetricComparison(name, a_val, b_val, observed, float(low), float(high), float(p_value))


def _swap_stat(num: np.ndarray, den: np.ndarray | None, levels: dict[str, np.ndarray], swap: np.ndarray) -> np.ndarray:
    """Overall statistic per permutation; ``num``/``den`` are (P, n) after swapping."""
    per_level = []
    with np.errstate(invalid="ignore", divide="ignore"):
        for ix in levels.values():
            v = num[:, ix]
            if den is None:
                counts = np.sum(~np.isnan(v), axis=1)
                per_level.append(np.where(counts > 0, np.nansum(v, axis=1) / np.maximum(counts, 1), np.nan))
            else:
                d = den[:, ix].sum(axis=1)
                per_level.append(np.where(d > 0, v.sum(axis=1) / np.where(d > 0, d, 1), np.nan))
    return _macro(per_level)


def sign_test(only_a: int, only_b: int) -> float | None:
    """Two-sided exact sign test on discordant pairs (McNemar's exact test); None without any."""
    n = only_a + only_b
    if n == 0:
        return None
    k = min(only_a, only_b)
    tail = sum(math.comb(n, i) for i in range(k + 1)) / 2 ** n
    return min(1.0, 2 * tail)


def _none(v: float) -> float | None:
    return None if math.isnan(v) else v


WILSON_Z = 1.959963984540054
"""The normal quantile of a two-sided 95 % interval."""


def wilson_interval(successes: int, n: int, z: float = WILSON_Z) -> tuple[float, float] | None:
    """The Wilson score interval of a success rate (95 % by default), as fractions in [0, 1]; None
    for n = 0. Unlike the normal approximation it stays inside [0, 1] and is not empty at 0 or n
    successes (0 of 10 gives [0, 0.278]), which is where small benchmark cells live.

    (p + z²/2n ± z·sqrt(p(1-p)/n + z²/4n²)) / (1 + z²/n), with p = successes / n."""
    if n <= 0:
        return None
    if not 0 <= successes <= n:
        raise ValueError(f"{successes} successes of {n} episodes")
    if successes == 0:
        return 0.0, z * z / (n + z * z)
    if successes == n:
        return n / (n + z * z), 1.0
    p = successes / n
    z2 = z * z
    centre = p + z2 / (2 * n)
    half = z * math.sqrt(p * (1 - p) / n + z2 / (4 * n * n))
    denominator = 1 + z2 / n
    return max(0.0, (centre - half) / denominator), min(1.0, (centre + half) / denominator)
