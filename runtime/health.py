"""Health on the bus: is this process's liveliness token up? (``agos health``, compose healthchecks)

Each long-running process, once its token is declared, writes which token it is to a small file
(``announce``); ``agos health KIND`` run beside it (same container or host) reads that file and asks
the router, by a liveliness query, whether the token is alive. So a healthcheck passes only when
the process is connected to the router and has declared itself, not merely when a port answers.

Files live in ``$AGOS_HEALTH_DIR`` (default ``<tmp>/agos-health``), one per kind: several
processes of one kind on one host (outside containers) each overwrite it, so there name the
process with ``--id``.
"""

from __future__ import annotations

import json
import os
import secrets
import socket
import time
from pathlib import Path
from typing import Literal

from agos.runtime import keys
from agos.runtime.bus import ZenohBus
from agos.runtime.settings import ZenohSettings, local_dirs

HealthKind = Literal["router", "world", "agent", "evaluator", "orchestrator"]
HEALTH_KINDS: tuple[HealthKind, ...] = ("router", "world", "agent", "evaluator", "orchestrator")
"""The kinds ``agos health`` can ask about (its argument choices)."""


def unique_id(prefix: str) -> str:
    """A process id that stays unique where hosts share a name and pids repeat (containers on the
    host network all see the host's name, and each is pid 1): prefix, pid and 4 random hex digits."""
    return keys.check_chunk(f"{prefix}-{os.getpid()}-{secrets.token_hex(2)}".replace(".", "-"), what="process id")


def host_prefix() -> str:
    return socket.gethostname().replace(".", "-")


def health_dir() -> Path:
    return local_dirs().health_dir


def announce(kind: HealthKind, ident: str, run: str | None = None) -> None:
    """Record which token this process declared (atomic write: a reader never sees half a file)."""
    folder = health_dir()
    folder.mkdir(parents=True, exist_ok=True)
    tmp = folder / f".{kind}.{os.getpid()}.tmp"
    tmp.write_text(json.dumps({"kind": kind, "id": ident, "run": run, "pid": os.getpid()}))
    tmp.replace(folder / f"{kind}.json")


def token_key(kind: HealthKind, ident: str, run: str | None) -> str:
    if kind == "router":
        return keys.router_live(ident)
    if run is None:
        raise ValueError(f"a {kind}'s token is under its run: give --run")
    return keys.live(run, kind, ident)


def announced(kind: HealthKind) -> dict[str, str | None] | None:
    """What the process of ``kind`` beside us announced, or None."""
    path = health_dir() / f"{kind}.json"
    try:
        data = json.loads(path.read_text())
    except (FileNotFoundError, json.JSONDecodeError):
        return None
    return {"id": data.get("id"), "run": data.get("run")}


def token_alive(z: ZenohSettings, key: str, timeout_s: float) -> bool:
    """Whether a liveliness token matching ``key`` is up, asked of the router until ``timeout_s``."""
    with ZenohBus.from_settings(z) as bus:
        deadline = time.monotonic() + timeout_s
        while not bus.alive_tokens(key, max(0.1, min(1.0, deadline - time.monotonic()))):
            if time.monotonic() >= deadline:
                return False
            time.sleep(0.2)
        return True
