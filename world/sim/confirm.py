"""The CONFIRM checker (paper §AGOS-Agent "Verify" and Appendix B.3).

A CONFIRM is accepted only if every enabled condition holds:

* fresh: the UGV's previous action was STOP_OBSERVE and it has not moved since;
* visible: the target covers at least ``min_target_pixels`` in one of the six views;
* near: the UGV-to-target horizontal distance is at most ``max_distance_m`` (50 m);
* line of sight: a ray from the UGV camera reaches the target before any other body.

A rejected CONFIRM ends the episode as a failure.
"""

from __future__ import annotations

from dataclasses import dataclass

from agos.runtime.episode_config import ConfirmConfig


@dataclass(frozen=True)
class ConfirmEvidence:
    fresh_stop: bool
    max_target_pixels: int
    """The largest target pixel count over the six views."""
    distance_m: float
    line_of_sight: bool


def check_confirm(evidence: ConfirmEvidence, settings: ConfirmConfig) -> list[str]:
    """Return the reasons a CONFIRM fails; an empty list means it is accepted."""
    reasons = []
    if settings.require_fresh_stop and not evidence.fresh_stop:
        reasons.append("no fresh STOP_OBSERVE")
    if evidence.max_target_pixels < settings.min_target_pixels:
        reasons.append(f"target not visible ({evidence.max_target_pixels} < {settings.min_target_pixels} px)")
    if evidence.distance_m > settings.max_distance_m:
        reasons.append(f"target {evidence.distance_m:.1f} m away (> {settings.max_distance_m:.0f} m)")
    if settings.require_line_of_sight and not evidence.line_of_sight:
        reasons.append("no clear line of sight")
    return reasons
