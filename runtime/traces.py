"""Totals of the per-decision traces of model-backed policies (stored with every episode): per role
(``agent_stats``) and per model (``usage``, what cost is computed from)."""

from __future__ import annotations

from agos.runtime.keys import ROLES
from agos.runtime.schemas import EpisodeRecord, ModelUsage, RoleTraceStats, StoredTrace


def trace_stats(traces: list[StoredTrace]) -> dict[str, RoleTraceStats]:
    """Per role: decisions traced, HTTP attempts, re-asks, repairs, fallbacks, tokens, mean latency.

    Roles without traces (scripted policies) are absent."""
    out: dict[str, RoleTraceStats] = {}
    for role in ROLES:
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


def trace_usage(traces: list[StoredTrace]) -> list[ModelUsage]:
    """Per model, in the order each was first used: decisions, HTTP requests, prompt and completion
    tokens of ``traces`` (a missing token count, an endpoint that reported none, adds 0). Empty
    without traces (scripted policies)."""
    out: dict[str, ModelUsage] = {}
    for t in traces:
        u = out.get(t.model)
        if u is None:
            u = out[t.model] = ModelUsage(model=t.model, decisions=0, http_attempts=0, prompt_tokens=0, completion_tokens=0)
        u.decisions += 1
        u.http_attempts += t.http_attempts
        u.prompt_tokens += t.prompt_tokens or 0
        u.completion_tokens += t.completion_tokens or 0
    return list(out.values())


def record_usage(record: EpisodeRecord) -> list[ModelUsage]:
    """A record's ``usage``, or for a record written before it existed, its traces' totals."""
    return record.usage or trace_usage(record.decision_traces)
