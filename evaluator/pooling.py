"""Which records may be pooled into one number: only those made under one episode configuration.

Every record carries the short hash of its :class:`~agos.runtime.episode_config.EpisodeConfig`.
Records of one run with different hashes (workers of different builds or settings, a resume under
other settings) would mix, say, two image sizes or CONFIRM thresholds into one success rate;
``agos metrics``, ``compare`` and ``report`` refuse them, naming the fields that differ, unless told
``--allow-mixed``.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Sequence

from agos.evaluator.summary import EpisodeSummary, SummaryError
from agos.runtime.episode_config import differing_fields


def mixed_configurations(summaries: Sequence[EpisodeSummary]) -> str | None:
    """``None`` when every summary has the same configuration hash, else one line saying how many
    episodes ran under each hash and which fields differ (between the two most common)."""
    counts = Counter(s.config_hash for s in summaries)
    if len(counts) <= 1:
        return None
    (hash_a, n_a), (hash_b, n_b) = counts.most_common(2)
    config_a = next(s.config for s in summaries if s.config_hash == hash_a) or {}
    config_b = next(s.config for s in summaries if s.config_hash == hash_b) or {}
    fields = differing_fields(config_a, config_b) if config_a and config_b else ["(configuration not recorded)"]
    shown = ", ".join(fields[:6]) + (f" and {len(fields) - 6} more" if len(fields) > 6 else "")
    others = f" and {len(counts) - 2} more configurations" if len(counts) > 2 else ""
    return (f"episodes ran under different configurations: {n_a} under {hash_a}, {n_b} under {hash_b}{others}; "
            f"differing fields: {shown}")


def require_one_configuration(summaries: Sequence[EpisodeSummary], *, where: str, allow_mixed: bool) -> None:
    """Raise :class:`SummaryError` (naming ``where`` and the differing fields) for mixed summaries,
    unless ``allow_mixed``."""
    problem = mixed_configurations(summaries)
    if problem is not None and not allow_mixed:
        raise SummaryError(f"{where}: {problem}; pool them anyway with --allow-mixed")
