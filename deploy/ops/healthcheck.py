"""``agos health KIND``: exit 0 when that process's liveliness token is up on the bus, else 1.

Used by the compose healthchecks: it connects to the router as the process's own settings say
(TLS credentials included), asks for the token the process announced (runtime/health.py) and
prints one line either way.
"""

from __future__ import annotations

import sys

from agos.runtime.bus import RouterUnreachable
from agos.runtime.health import HealthKind, announced, token_alive, token_key
from agos.runtime.settings import AgosConfig


def main(cfg: AgosConfig, kind: HealthKind, *, ident: str | None, run: str | None, timeout_s: float) -> int:
    note = announced(kind)
    if ident is None:
        if note is None or not note.get("id"):
            print(f"health: no {kind} has announced itself here yet (starting?); or name one with --id", file=sys.stderr)
            return 1
        ident = note["id"]
    run = run or (note or {}).get("run") or cfg.run.run_id
    assert ident is not None
    key = token_key(kind, ident, None if kind == "router" else run)
    try:
        # A healthcheck must answer within its own timeout, also when the router is down.
        alive = token_alive(cfg.zenoh.model_copy(update={"connect_timeout_s": timeout_s}), key, timeout_s)
    except RouterUnreachable as exc:
        print(f"health: {exc}", file=sys.stderr)
        return 1
    if not alive:
        print(f"health: {kind} {ident} is not on the bus ({key} not alive at {cfg.zenoh.connect})", file=sys.stderr)
        return 1
    print(f"health: {kind} {ident} is up ({key})")
    return 0
