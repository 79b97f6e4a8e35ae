"""Totals of the per-decision traces of model-backed policies (stored with every episode)."""

from __future__ import annotations

from agos.runtime.schemas import RoleTraceStats, StoredTrace


def trace_stats(traces: list[StoredTrace]) -> dict[str, RoleTraceStats]:
    """Per role: decisions traced, HTTP attempts, re-asks, repairs, fallbacks, tokens, mean latency.

    Roles without traces (scripted policies) are absent."""
    out: dict[str, RoleTraceStats] = {}
    for role in ("uav", "ugv"):
        mine = [t for t in traces if t.role == role]
        if not mine:
            continue
        out[role] = RoleTraceStats(
            decisions=len(mine), http_attempts=sum(t.http_attempts for t in mine), reasks=sum(t.reasks for t in mine),
            repaired=sum(t.repaired for t in mine), fallbacks=sum(t.fallback for t in mine),
            prompt_tokens=sum(t.prompt_tokens or 0 for t in mine),
            completion_tokens=sum(t.completion_tokens or 0 for t in mine),
            mean_latency_s=round(sum(t.latency_s for t in mine) / len(mine), 4))
    return out
