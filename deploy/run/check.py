"""``agos check agent``: a short conformance episode against attached agent services.

    agos check agent --connect tcp/HOST:PORT --run RUN [--budget 16] [--town grid-s7]

Before a long evaluation, the author of a remote agent runs one real episode (the world simulated
in this process by an ``agos.Env``, decisions asked over zenoh exactly as a world worker asks them)
and gets a verdict per check:

* ``subscribed``: an agent service of each role listens for the run (else: which role is missing);
* ``answered``: every decision answered before the deadline, with the right decision index;
* ``legal``: every action is one of the observation's legal actions;
* ``arguments``: waypoint ids among the options, cells A1..E5, known candidate ids (the world
  accepted the action instead of turning it into a fallback);
* ``model``: model-backed agents got a usable answer from their model (no fallback in the trace);
* ``message``: messages to the teammate are at most 500 characters;
* ``finished``: the episode ran to its end (confirm, false confirm or budget).

The episode's budget is cut short (``--budget``); ``--policy`` (or ``--policy-uav``/``--policy-ugv``)
sets the world's tools to what that policy expects (Baseline: no candidates; ablations; a policy
of one's own, ``package.module:Class``: every tool). The policy's code is not needed here. The
check episode's record is not published, so no evaluator stores it. The exit status is 0 when
every check passed.
"""

from __future__ import annotations

import os
import statistics
import time
from dataclasses import dataclass, field

import msgspec
from rich.console import Console
from rich.table import Table

from agos.deploy.run.presence import elsewhere_line, who_is_here
from agos.runtime.bus import ZenohBus
from agos.runtime.keys import ROLES
from agos.runtime.process import install_stop_handlers
from agos.runtime.schemas import Action, EpisodeRecord, Observation, Role, StepEvent
from agos.runtime.settings import DEFAULT_POLICY, AgosConfig

MESSAGE_LIMIT = 500
CHECKS = ("subscribed", "answered", "legal", "arguments", "model", "message", "finished")


@dataclass
class Verdicts:
    failures: dict[str, list[str]] = field(default_factory=lambda: {c: [] for c in CHECKS})
    passes: dict[str, int] = field(default_factory=lambda: dict.fromkeys(CHECKS, 0))
    latency_s: dict[str, list[float]] = field(default_factory=lambda: {"uav": [], "ugv": []})

    def check(self, name: str, ok: bool, why: str = "") -> None:
        if ok:
            self.passes[name] += 1
        else:
            self.failures[name].append(why)

    @property
    def ok(self) -> bool:
        return not any(self.failures.values())


class CheckingSource:
    """Asks the agents through a world worker's decision source and checks every answer."""

    def __init__(self, inner, verdicts: Verdicts) -> None:
        self.inner, self.v = inner, verdicts

    def decide(self, observations: dict[Role, Observation]) -> dict[Role, Action | None]:
        started = time.monotonic()
        actions = self.inner.decide(observations)
        for role, obs in observations.items():
            action = actions.get(role)
            where = f"{role} decision {obs.decision_index}"
            self.v.check("answered", action is not None, f"{where}: no answer within the deadline")
            if action is None:
                continue
            self.v.latency_s[role].append(action.agent_wall_latency_s or (time.monotonic() - started))
            self.v.check("legal", action.action in obs.legal_actions,
                         f"{where}: {action.action} is not legal (legal: {', '.join(obs.legal_actions)})")
            if action.trace is not None:
                self.v.check("model", not action.trace.fallback, f"{where}: {action.trace.fallback_reason}")
            self.v.check("message", len(action.message or "") <= MESSAGE_LIMIT,
                         f"{where}: message of {len(action.message or '')} characters (limit {MESSAGE_LIMIT})")
        return actions


class StepChecks:
    """The world's verdict on each action: a fallback on a legal action means bad arguments."""

    def __init__(self, inner, verdicts: Verdicts) -> None:
        self.inner, self.v = inner, verdicts

    def step(self, event: StepEvent) -> None:
        if event.requested is not None:  # an illegal action was already counted by the "legal" check
            reason = event.fallback_reason or ""
            bad = bool(reason) and "is not legal now" not in reason
            self.v.check("arguments", not bad, f"{event.role} decision {event.decision_index}: {reason}")
        self.inner.step(event)

    def coordination(self, truth, views) -> None:
        self.inner.coordination(truth, views)

    def message(self, message) -> None:
        self.inner.message(message)


def run_check(cfg: AgosConfig, *, budget: int, town_name: str, policies: dict[str, str] | None = None,
              console: Console | None = None) -> int:
    """One check episode; 0 when every check passed, 1 otherwise. ``policies``: the policy each role's
    agent runs (default heuristic), for the world's tools; a name that names no policy raises
    ValueError before the bus is opened."""
    from agos.deploy.run.configure import run_episode_config
    from agos.env import Env
    from agos.world.episodes.sampling import generate_episodes
    from agos.world.sim.scene import Scene
    from agos.world.sim.worker import BusDecisionSource, BusSink, MissingAgent, ModelOutage, WorkerSlot
    from agos.world.towns.asset import open_town

    console = console or Console(soft_wrap=True)  # paths and commands it prints are never cut at the width
    config = run_episode_config(cfg, policies=policies or dict.fromkeys(ROLES, DEFAULT_POLICY), decision_budget=budget)
    stop = install_stop_handlers()
    v = Verdicts()
    run_id = cfg.run.run_id
    bus = ZenohBus.from_settings(cfg.zenoh)
    town = open_town(town_name)
    scene = Scene(town.layout, renderer=config.renderer, look=config.look)
    record: EpisodeRecord | None = None
    with bus, scene:
        # the first of the generated episodes; sampling only its difficulty gives the same episode
        spec = generate_episodes(town, scene, per_difficulty=1, seed=cfg.run.episode_seed, difficulties=("easy",))[0]
        spec = msgspec.structs.replace(spec, episode_id=f"check-{spec.episode_id}")
        console.print(f"checking the agents of run {run_id!r} on {cfg.zenoh.connect}: episode {spec.episode_id}, "
                      f"{budget} decisions (waiting up to {cfg.run.agent_wait_s:.0f} s for the agent services)")
        worker_id = f"check-{os.getpid()}"
        slot = WorkerSlot(bus, run_id, worker_id)
        source = BusDecisionSource(slot, spec.episode_id, timeout_s=config.decision_timeout_s, stop=stop,
                                   agent_wait_s=cfg.run.agent_wait_s)
        sink = StepChecks(BusSink(bus, run_id, worker_id), v)
        try:
            with Env(spec, config, illegal="wait", run_id=run_id, worker_id="check", scene=scene, town=town,
                     sink=sink) as env:  # the world's own fallbacks: the checks count illegal answers
                record = env.play(CheckingSource(source, v))
            v.check("subscribed", True)
        except MissingAgent as exc:
            v.check("subscribed", False, str(exc))
            console.print(f"[red]{exc}", highlight=False)  # whole: the table cell is cut to its width
            if line := elsewhere_line(who_is_here(bus, run_id), run_id):
                console.print(f"[yellow]{line}", highlight=False)
        except ModelOutage as exc:  # the agents are there, their model endpoint is not
            v.check("finished", False, f"the model endpoint gave no answer: {exc}")
            console.print(f"[red]the model endpoint gave no answer: {exc}", highlight=False)
        finally:
            slot.close()
        if record is not None:
            v.check("finished", record.status == "finished", f"episode status {record.status}")
    _report(console, v, record)
    return 0 if v.ok else 1


def _report(console: Console, v: Verdicts, record: EpisodeRecord | None) -> None:
    table = Table(title="agent conformance")
    for col in ("check", "passed", "failed", "first failure"):
        table.add_column(col)
    for name in CHECKS:
        fails = v.failures[name]
        table.add_row(name, str(v.passes[name]), str(len(fails)), fails[0] if fails else "",
                      style="red" if fails else None)
    console.print(table)
    for role, lat in v.latency_s.items():
        if lat:
            p95 = sorted(lat)[max(0, round(0.95 * len(lat)) - 1)]
            console.print(f"{role}: {len(lat)} decisions, latency median {statistics.median(lat):.3f} s, p95 {p95:.3f} s")
    if record is not None:
        console.print(f"episode: {record.termination}, {record.decisions_uav + record.decisions_ugv} decisions, "
                      f"{record.fallbacks} fallbacks")
    console.print("[green]PASS: the agents conform" if v.ok else "[red]FAIL: see the failed checks above")
