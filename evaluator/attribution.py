"""Failure attribution: one outcome per episode along search -> handoff -> verify.

Rules, first match wins (the episode summary is all they read):

1. ``agent_failure`` / ``infrastructure_failure``: status ``agent_crashed`` / any other
   status but ``finished``. Kept apart from task failures (STYLE.md item 7).
2. ``success``.
3. ``false_confirm``: a CONFIRM the checker refused (typically on a look-alike).
4. ``never_seen_from_air``: no candidate and the target never oracle-visible from the UAV.
5. ``seen_not_annotated``: visible from the air at some step, but no candidate.
6. ``candidate_lost_on_link``: every candidate message was dropped or arrived too late
   (needs the link ledger: ``link.candidates_lost`` > 0 with no candidate delivered).
7. ``candidate_too_far``: every candidate polygon is more than R = 50 m from the target.
8. ``no_verifying_view``: a good candidate existed, but no STOP_OBSERVE could have verified.
9. ``wrong_reject``: the target was verifiable from the ground and a candidate within R was rejected.
10. ``budget_exhausted``: everything else (verifiable, not rejected, out of decisions).
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Sequence
from typing import Any

from agos.evaluator.metrics import R_M, Episode, false_confirm

OUTCOMES = (
    "success", "never_seen_from_air", "seen_not_annotated", "candidate_lost_on_link", "candidate_too_far",
    "no_verifying_view", "wrong_reject", "false_confirm", "budget_exhausted", "agent_failure",
    "infrastructure_failure",
)


def attribute(e: Episode) -> str:
    if e.status == "agent_crashed":
        return "agent_failure"
    if e.status != "finished":
        return "infrastructure_failure"
    if e.success:
        return "success"
    if false_confirm(e):
        return "false_confirm"
    if not e.candidates:
        return "never_seen_from_air" if e.uav_first_visible_step is None else "seen_not_annotated"
    link: Any = getattr(e, "link", None)
    if isinstance(link, dict) and link.get("candidates_lost", 0) > 0 and not link.get("candidates_delivered", 1):
        return "candidate_lost_on_link"
    if min(c.distance_to_polygon_m for c in e.candidates) > R_M:
        return "candidate_too_far"
    if not e.ground_observed:
        return "no_verifying_view"
    if any(getattr(c, "status", None) == "rejected" and c.distance_to_polygon_m <= R_M for c in e.candidates):
        return "wrong_reject"
    return "budget_exhausted"


def outcome_counts(episodes: Sequence[Episode]) -> dict[str, int]:
    counts = Counter(attribute(e) for e in episodes)
    return {name: counts.get(name, 0) for name in OUTCOMES}
