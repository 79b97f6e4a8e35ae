"""The processes of a local run (``agos eval``/``demo`` without ``--connect``), started as children
in the order a run needs them: router, recorder, evaluator, VLM stand-in, human consoles, agents,
world workers.

Each child's settings are an :class:`~agos.runtime.settings.AgosConfig` (deploy/run/children.py):
what every child reads (the command's ``--config`` file, then the environment) with what that
child is told: the router's endpoint, the run id, its identity's credentials on a secured bus (the
run's throwaway CA), the model endpoint of VLM agents. They reach it as environment variables; its
command line holds only the command's own arguments.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from rich.console import Console

from agos.deploy.ops.certs import RunCredentials
from agos.deploy.run.card_writer import models_answer, record_models_answer
from agos.deploy.run.children import AGENT_CONCURRENCY, shared_settings, with_settings
from agos.deploy.run.human import start_console
from agos.deploy.run.launcher import ROUTER_START_S, SERVER_START_S, Launcher, free_port, wait_listening
from agos.deploy.run.plan import STANDIN_MODEL, RunPlan
from agos.runtime.keys import ROLES
from agos.runtime.settings import AgosConfig, load_config

STANDIN_PORT = 8000
"""The port a run's VLM stand-in prefers (the usual OpenAI-compatible server's), else a free one."""
STANDIN_RETRY_AFTER_S = 0.2
"""The ``Retry-After`` a run's stand-in sends with an injected 429."""
STANDIN_HANG_S = 5.0
"""How long a run's stand-in hangs on an injected timeout."""
STANDIN_ATTEMPT_TIMEOUT_S = 2.0
STANDIN_MAX_RETRIES = 10
"""The agents' ``[vlm]`` timeout and retries against a run's stand-in: injected timeouts hang
``STANDIN_HANG_S``; a 2 s attempt timeout makes the client retry them quickly, and ten retries
make a decision that never gets an answer rare even at high injected fault rates."""
RECORDER_START_S = 30.0
"""How long a run waits for its recorder to subscribe before it goes on without it."""


@dataclass(frozen=True)
class Recording:
    """``--record DIR [--record-full] [--record-format F]``: a recorder process writes one rerun (``rrd``) or
    MCAP (``mcap``) file per episode to ``out_dir``."""

    out_dir: Path
    full: bool = False
    fmt: str = "rrd"


@dataclass(frozen=True)
class ChildSettings:
    """The settings of the run's children, each a client of ``endpoint`` (see the module docstring)."""

    shared: AgosConfig
    """What every child reads before it is told anything: :func:`~agos.deploy.run.children.shared_settings`."""
    endpoint: str
    run_id: str
    creds: RunCredentials | None = None

    def client(self, identity: str, **sections: dict[str, Any]) -> AgosConfig:
        """A client of the run's router as ``identity`` (its credentials on a secured bus), told the run
        id. The evaluator too, though it stores every run it hears: it then declares its token under
        the run as it starts, so a slow start that misses the run's first manifest is never reported
        as no evaluator (deploy/run/presence.py)."""
        zenoh = {"connect": self.endpoint, **(self.creds.files(identity) if self.creds else {})}
        run = {"run_id": self.run_id} | sections.pop("run", {})
        return with_settings(self.shared, zenoh=zenoh, run=run, **sections)


def evaluator_settings(children: ChildSettings, plan: RunPlan) -> AgosConfig:
    """The settings of the run's evaluator: a client of the run's router, told the run (its token is up
    from its start) and storing beside the run directory."""
    return children.client("evaluator", run={"runs_dir": plan.run_dir.parent})


def start_recorder(launcher: Launcher, recording: Recording, settings: AgosConfig) -> float:
    """Start ``agos record`` (its own process and zenoh session, the observer identity on a secured
    bus); returns when it started (epoch seconds), for :func:`agos.deploy.recording.recorder.wait_ready`."""
    since = time.time()
    launcher.start("recorder", ["record", "--out", str(recording.out_dir), *(["--full"] if recording.full else []),
                                "--format", recording.fmt], settings)
    return since


def recorder_ready(recording: Recording, since: float, launcher: Launcher, console: Console) -> None:
    """Wait (at most ``RECORDER_START_S``) until the recorder has subscribed, so it sees the first
    episode start; a recorder that does not come up is reported and the run goes on without it."""
    from agos.deploy.recording.recorder import wait_ready

    if wait_ready(recording.out_dir, RECORDER_START_S, since, alive=lambda: "recorder" not in launcher.dead()):
        console.print(f"recording to {recording.out_dir} ({'full resolution' if recording.full else 'thumbnails'})",
                      highlight=False)
    else:
        console.print(f"[yellow]the recorder did not come up; the run goes on; see {launcher.log_dir / 'recorder.log'}")


def start_attached_recorder(launcher: Launcher, recording: Recording, cfg: AgosConfig, config_path: Path | None,
                            run_id: str, console: Console) -> None:
    """An attached run's recorder, connected as this command's settings say."""
    settings = with_settings(shared_settings(config_path), zenoh={"connect": cfg.zenoh.connect}, run={"run_id": run_id})
    recorder_ready(recording, start_recorder(launcher, recording, settings), launcher, console)


def launch_all(cfg: AgosConfig, plan: RunPlan, launcher: Launcher, endpoint: str, port: int, workers: int,
               config_path: Path | None, console: Console, creds: RunCredentials | None = None,
               recording: Recording | None = None) -> bool:
    """Start every process of the run; False (after saying why) when one that must listen did not."""
    children = ChildSettings(shared_settings(config_path), endpoint, plan.run_id, creds)
    router_files = creds.files("router") if creds else {}
    # The router never read the --config file: the environment, its endpoint and its credentials.
    launcher.start("router", ["router"], with_settings(load_config(), zenoh={"listen": endpoint, **router_files}))
    if not wait_listening("127.0.0.1", port, ROUTER_START_S):
        console.print(f"[red]router did not listen on {endpoint}; see {launcher.log_dir / 'router.log'}")
        return False
    console.print(f"zenoh endpoint: {endpoint}" + (" (mutual TLS, access control)" if creds else ""), highlight=False)
    recorder_since = None if recording is None else start_recorder(launcher, recording, children.client("observer"))
    launcher.start("evaluator", ["evaluator"], evaluator_settings(children, plan))
    model = _start_vlm(cfg, plan, launcher, console)
    if model is None:
        return False
    # Every episode in flight may wait on an agent at once: decisions answered at once >= workers.
    at_once = ["--concurrency", str(max(AGENT_CONCURRENCY, workers))]
    if plan.dataset_out is not None:
        at_once += ["--dataset-out", str(plan.dataset_out)]
    people = start_console(launcher, plan.policies, plan.config, console,  # the roles a person plays
                           settings=lambda role: children.client(f"agent-{role}"), secured=creds is not None)
    if people is None:
        return False
    policies = {"policy_uav": plan.policies["uav"], "policy_ugv": plan.policies["ugv"]}
    vlm = children.shared.vlm if not model else cfg.vlm.model_copy(update=model)
    for role in (r for r in ROLES if r not in people):
        launcher.start(f"agent-{role}", ["agent", "--role", role, *at_once],
                       children.client(f"agent-{role}", run=policies, vlm=vlm.model_dump()))
    if recording is not None and recorder_since is not None:
        recorder_ready(recording, recorder_since, launcher, console)
    for k in range(workers):
        launcher.start(f"world-{k}", ["world", "--worker-id", f"w{k}"], children.client("world"))
    return True


def _start_vlm(cfg: AgosConfig, plan: RunPlan, launcher: Launcher, console: Console) -> dict[str, Any] | None:
    """The ``[vlm]`` settings the run's agents get for its model endpoint ({}: none, the run asks no
    model); starts the stand-in server when the plan asks for it. None when the stand-in did not come up."""
    if not plan.vlm:
        return {}
    if cfg.vlm.replaying:  # every reply comes from the cache: no endpoint, no stand-in to start
        console.print(f"VLM calls replayed from {cfg.vlm.cache_dir} (model {plan.vlm['model']}; no endpoint)",
                      highlight=False)
        return {"base_url": None, "model": plan.vlm["model"]}
    if "standin" not in plan.vlm:
        return {"base_url": plan.vlm.get("base_url") or cfg.vlm.base_url, "model": plan.vlm["model"]}  # a replay: none kept
    port = free_port(STANDIN_PORT)
    faults = ["--faults", plan.vlm["standin"]] if plan.vlm["standin"] else []
    launcher.start("vlm-standin", ["vlm-standin", "--port", str(port), "--model", STANDIN_MODEL, *faults,
                                   "--retry-after-s", f"{STANDIN_RETRY_AFTER_S:g}", "--hang-s", f"{STANDIN_HANG_S:g}"])
    if not wait_listening("127.0.0.1", port, SERVER_START_S):
        console.print(f"[red]the VLM stand-in did not listen on port {port}; see {launcher.log_dir / 'vlm-standin.log'}")
        return None
    url = f"http://127.0.0.1:{port}/v1"
    console.print(f"VLM stand-in: {url} (faults: {plan.vlm['standin'] or 'none'})", highlight=False)
    record_models_answer(plan.run_dir, models_answer(url))  # the run card's /models answer
    return {"base_url": url, "model": STANDIN_MODEL, "timeout_s": STANDIN_ATTEMPT_TIMEOUT_S,
            "max_retries": STANDIN_MAX_RETRIES}
