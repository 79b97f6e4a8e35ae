"""What ``agos eval``'s flags make of a run before anything starts: a resumed run directory or a new
one (and where it is), its caps and prices, and how many world workers play it. Whatever is wrong with
the command is raised here (:data:`agos.deploy.run.exits.REFUSED`), before any process starts."""

from __future__ import annotations

from collections.abc import Iterable
from pathlib import Path

from agos.deploy.run import plan as run_plan
from agos.deploy.run.budget import Caps
from agos.deploy.run.plan import RunPlan
from agos.evaluator.cost import PriceTable, price_table
from agos.runtime.settings import AgosConfig


def caps_of(max_cost_usd: float | str | None, max_tokens: int | str | None) -> Caps:
    """``--max-cost-usd`` and ``--max-tokens`` as caps: ``none`` or not given is no cap."""
    return Caps(None if isinstance(max_cost_usd, str) else max_cost_usd,
                None if isinstance(max_tokens, str) else max_tokens)


def locate_here(policies: Iterable[str], *, attach: bool) -> None:
    """A run that starts its agents here (not attached): their policies' modules must be found here,
    before any process starts (agents/registry.py::locate_policy; raises ValueError)."""
    if not attach:
        from agos.agents.registry import locate_policy

        for name in policies:
            locate_policy(name)


def run_dir_for(cfg: AgosConfig, run_dir: Path | None, *, attach: bool, run_id: str | None) -> Path | None:
    """A new run's directory: ``--run-dir``; attached with ``--run R``, ``<runs-dir>/R``; else None
    (:func:`~agos.deploy.run.plan.new_plan` names one ``<runs-dir>/<run>-<UTC time>``)."""
    if run_dir is None and attach and run_id:
        return cfg.run.runs_dir / run_id
    return run_dir


def eval_plan(cfg: AgosConfig, *, resume: Path | None, run_dir: Path | None, run_id: str | None, attach: bool,
              comm: str, timing_mode: str, vlm_standin: str | None, workers: int | str | None,
              model_link: str | None, pose_error: str | None, max_cost_usd: float | str | None,
              max_tokens: int | str | None, prices_file: Path | None, price_in: float | None,
              price_out: float | None) -> RunPlan:
    """``agos eval``'s plan: ``resume``'s run directory with the caps and prices given now (its agents'
    endpoint checked first when they start here, as a new run's), or a new run directory. ``attach``:
    ``--connect``, processes started by hand."""
    prices: PriceTable | None = price_table(prices_file=prices_file, price_in=price_in, price_out=price_out)
    caps = caps_of(max_cost_usd, max_tokens)
    if resume:
        plan = run_plan.resume_plan(resume)
        if not attach:  # its agents start here: their endpoint is checked first, as a new run's
            plan.endpoint = run_plan.check_endpoint(cfg.vlm, plan.vlm)
        locate_here(plan.policies.values(), attach=attach)
        run_plan.resume_with(plan, max_cost_usd=max_cost_usd, max_tokens=max_tokens, prices=prices)
        return plan
    locate_here((cfg.run.policy_uav, cfg.run.policy_ugv), attach=attach)
    return run_plan.new_plan(cfg, run_dir=run_dir_for(cfg, run_dir, attach=attach, run_id=run_id), comm=comm,
                             timing_mode=timing_mode, stamp=True, vlm_standin=vlm_standin, workers=workers,
                             check_vlm=not attach, caps=caps, prices=prices, model_link=model_link,
                             pose_error=pose_error)


def eval_workers(cfg: AgosConfig, plan: RunPlan, workers: int | str | None, *, attach: bool,
                 model_latency_s: float | None) -> tuple[int, str | None]:
    """How many world workers play the run, and why when ``auto`` chose (None otherwise): ``--workers``
    (a resumed run keeps the count it was started with when none is given), else ``[run] workers``;
    ``auto``, when the workers start here, sizes it to the episodes still to play
    (deploy/run/concurrency.py)."""
    if plan.resumed and workers is None:
        workers = plan.workers
    if workers == "auto" and not attach:
        from agos.agents.names import needs_vlm
        from agos.deploy.run.concurrency import choose_workers

        to_run = len(plan.episodes) - len(run_plan.stored_episodes(plan.run_dir))
        asks_model = any(needs_vlm(p) for p in plan.policies.values())  # at most [vlm] concurrency requests at once
        choice = choose_workers(plan.policies, to_run, model_latency_s=model_latency_s,
                                model_concurrency=cfg.vlm.concurrency if asks_model else None)
        return choice.workers, choice.why
    return (workers if isinstance(workers, int) else cfg.run.workers), None
