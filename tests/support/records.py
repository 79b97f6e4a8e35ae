"""Comparing the episode records of two runs of the same episodes."""

from __future__ import annotations

VOLATILE = ("wall_time_s", "worker_id", "run_id")
"""What differs between two runs of the same episode however deterministic the run: how long it took,
which worker played it, under which run id."""


def by_episode(records: list[dict], *, also: tuple[str, ...] = ()) -> dict[str, dict]:
    """Each record (as stored: ``record_json``) by episode id, without :data:`VOLATILE` fields and
    ``also`` (e.g. ``provenance`` when the commit may have moved between the two runs)."""
    left_out = set(VOLATILE) | set(also)
    return {r["episode_id"]: {k: v for k, v in r.items() if k not in left_out} for r in records}
