"""Who is here, and is the run getting anywhere? ``agos eval``'s watch over a run (no silent waits).

While nothing progresses (:class:`Stall`), ``agos eval`` asks the router which processes of the run
hold their liveliness tokens (world workers, the evaluator, an agent service per role) and prints,
for each one missing, the exact command that starts it, or, for one it started itself that has not
joined yet, where its log is; when agent services are serving other runs,
it names them (a mistyped ``--run`` is the usual cause). Episodes lost in a row to one
infrastructure cause (:class:`LossStreak`) stop the run.
"""

from __future__ import annotations

import time
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path

from agos.agents.names import is_human
from agos.runtime import keys
from agos.runtime.bus import Bus
from agos.runtime.schemas import EpisodeRecord


@dataclass(frozen=True)
class Presence:
    worlds: int
    evaluator: bool
    agents: dict[str, int]
    """role -> agent services of that role serving the run."""
    agents_elsewhere: dict[str, list[str]] = field(default_factory=dict)
    """Other runs with agent services: run -> roles."""


def who_is_here(bus: Bus, run_id: str, timeout_s: float = 1.0) -> Presence:
    """Ask the router for the run's liveliness tokens (and agents of other runs)."""
    worlds = bus.alive_tokens(keys.live(run_id, "world", "*"), timeout_s)
    evaluator = bus.alive_tokens(keys.live(run_id, "evaluator", "*"), timeout_s)
    agents: dict[str, int] = dict.fromkeys(keys.ROLES, 0)
    elsewhere: dict[str, list[str]] = {}
    for key in bus.alive_tokens(keys.live("*", "agent", "*"), timeout_s):
        token = keys.live_of(key)
        run, role = token.run, token.ident.split("-", 1)[0]  # an agent id starts with its role
        if run == run_id and role in agents:
            agents[role] += 1
        elif run != run_id:
            elsewhere.setdefault(run, []).append(role)
    return Presence(len(worlds), bool(evaluator), agents, {r: sorted(set(v)) for r, v in elsewhere.items()})


STARTED_KINDS = {"evaluator": "evaluator", "agent-uav": "uav", "agent-ugv": "ugv"}
"""``agos eval``'s children (deploy/run/local.py) by the kind :func:`missing_lines` knows them as;
``world-<k>`` are ``world``."""


def started_kinds(alive_children: Iterable[str]) -> frozenset[str]:
    """The kinds of process (``world``, ``evaluator``, ``uav``, ``ugv``) among children still running."""
    return frozenset("world" if name.startswith("world") else STARTED_KINDS[name]
                     for name in alive_children if name.startswith("world") or name in STARTED_KINDS)


def missing_lines(p: Presence, run_id: str, endpoint: str, policies: dict[str, str],
                  started: frozenset[str] = frozenset(), logs: Path | None = None) -> list[str]:
    """One line per missing process, with the command that starts it; for a kind in ``started`` (this
    command started one and it still runs: :func:`started_kinds`), that it has not joined yet and where
    its log is, since starting another would be the wrong advice."""
    lines = []

    def joining(kind: str, what: str, log: str) -> bool:
        if kind in started:
            lines.append(f"{what} this command started has not joined run {run_id} yet; see {(logs or Path('.')) / log}")
        return kind in started

    if not p.worlds and not joining("world", "the world worker", "world-0.log"):
        lines.append(f"no world worker serves run {run_id}: start one with `agos world --connect {endpoint} --run {run_id}`")
    if not p.evaluator and not joining("evaluator", "the evaluator", "evaluator.log"):
        lines.append(f"no evaluator stores run {run_id}: start one with `agos evaluator --connect {endpoint} --run {run_id}` "
                     "(where this run directory's runs folder is)")
    for role, n in p.agents.items():
        if not n and joining(role, f"the {role.upper()} agent", f"agent-{role}.log"):
            continue
        if not n and is_human(policies.get(role, "heuristic")):
            lines.append(f"no person plays the {role.upper()} of run {run_id}: start a console with `agos human --role "
                         f"{role} --connect {endpoint} --run {run_id}` and open the page it names")
        elif not n:
            lines.append(f"no {role.upper()} agent serves run {run_id}: start one with `agos agent --role {role} "
                         f"--policy {policies.get(role, 'heuristic')} --connect {endpoint} --run {run_id}`")
    if any(not n and role not in started for role, n in p.agents.items()) and (line := elsewhere_line(p, run_id)):
        lines.append(line)
    return lines


def elsewhere_line(p: Presence, run_id: str) -> str | None:
    """Which other runs have agent services (a mistyped ``--run`` is the usual cause), or None."""
    if not p.agents_elsewhere:
        return None
    others = ", ".join(f"{run} ({'+'.join(roles)})" for run, roles in sorted(p.agents_elsewhere.items()))
    return f"agent services are serving other runs: {others}; is --run {run_id} the run they were started with?"


class Stall:
    """Says when a run has made no progress for another ``every_s`` seconds."""

    def __init__(self, every_s: float) -> None:
        self.every_s = every_s
        self.progress = -1
        self.since = time.monotonic()

    def due(self, progress: int) -> bool:
        now = time.monotonic()
        if progress != self.progress:
            self.progress, self.since = progress, now
            return False
        if now - self.since >= self.every_s:
            self.since = now
            return True
        return False


LOST_IN_A_ROW = 3
"""Episodes lost in a row to one infrastructure cause after which ``agos eval`` stops (exit 3): a
missing agent or a broken endpoint would otherwise cost every remaining episode its wait. Also the
presence checks in a row (``[run] presence_check_s`` apart) that find no world worker, or records that no
evaluator stores, after which it stops the same way (``--resume`` goes on once they are up)."""


class LossStreak:
    """Counts consecutive episodes lost to the same infrastructure cause (status and error)."""

    def __init__(self, limit: int) -> None:
        self.limit, self.cause, self.count = limit, "", 0

    def add(self, record: EpisodeRecord) -> str | None:
        """The cause, once ``limit`` episodes in a row were lost to it; else None."""
        if record.status == "finished":
            self.cause, self.count = "", 0
            return None
        cause = f"{record.status}: {record.error or 'no error message'}"
        self.count = self.count + 1 if cause == self.cause else 1
        self.cause = cause
        return cause if self.count >= self.limit else None
