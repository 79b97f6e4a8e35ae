"""A run's plan and its directory: what ``agos eval`` (``demo``, ``dataset build``) runs, made new or
read back for ``--resume``.

A run directory holds ``run.json`` (policies, comm profile, timing mode, episode source, the whole
episode configuration, and the provenance: agos commit, uv.lock hash and package versions, outside the
configuration's hash: runtime/provenance.py; the run card, prices and caps: deploy/run/card_writer.py,
deploy/run/budget.py), ``episodes.jsonl`` (the exact episodes), ``prompts.txt`` (a VLM run's
prompts), ``results.sqlite`` (written by the evaluator) and ``logs/``. ``agos eval --resume DIR``
re-reads the first two and leases only the episodes not yet stored; caps and prices given to it
replace the stored ones (run.json keeps each resume's).
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from agos.agents.names import needs_vlm
from agos.deploy.run.budget import Caps, check_prices
from agos.deploy.run.card_writer import run_card
from agos.deploy.run.configure import run_episode_config
from agos.evaluator.cost import PriceError, PriceTable, prices_from_json
from agos.evaluator.store import ResultStore
from agos.runtime.episode_config import EpisodeConfig, StoredConfigError, read_config
from agos.runtime.provenance import provenance
from agos.runtime.schemas import EpisodeSpec
from agos.runtime.settings import AgosConfig, VlmOptions

RUN_FILE = "run.json"
STANDIN_MODEL = "agos-standin"
"""The model name of the stand-in VLM server a run starts itself (``--vlm-standin``)."""

PREFLIGHT_TIMEOUT_S = 10.0
"""The longest :func:`check_endpoint` waits for ``/models`` (``[vlm] timeout_s`` when shorter): a
listing answers at once on any live server, however slow its model."""


class RunDirError(ValueError):
    """A run directory that cannot be created or resumed; the message names it and why."""


class EndpointError(ValueError):
    """The run's model endpoint fails its preflight: one line saying what failed and what to change."""


@dataclass
class RunPlan:
    run_dir: Path
    episodes: list[EpisodeSpec]
    policies: dict[str, str]
    config: EpisodeConfig
    """Everything that shapes the run's episodes; sent whole in every job grant."""
    resumed: bool = False
    vlm: dict[str, Any] = field(default_factory=dict)
    """VLM policies: ``base_url`` and ``model``, or ``standin`` (its fault string) for a stand-in server
    the run starts itself. Stored in run.json (never an API key)."""
    workers: int | str | None = None
    """``--workers`` as the run was started with (a count or ``auto``): what ``--resume`` uses again."""
    dataset_out: Path | None = None
    """A dataset build (deploy/dataset/build.py): the agents it starts write every decision there."""
    endpoint: str | None = None
    """What :func:`check_endpoint` found (a line for the console); None when it did not run."""
    caps: Caps = field(default_factory=Caps)
    """``--max-cost-usd`` and ``--max-tokens`` (deploy/run/budget.py)."""
    prices: PriceTable | None = None
    """What the run's tokens cost (evaluator/cost.py); None: not given."""

    @property
    def run_id(self) -> str:
        return self.run_dir.name


def generated_episodes(cfg: AgosConfig) -> list[EpisodeSpec]:
    from agos.world.episodes.sampling import generate_episodes
    from agos.world.sim.scene import Scene
    from agos.world.towns.asset import open_town

    town = open_town(cfg.run.town)
    with Scene(town.layout, look=cfg.world.look) as scene:  # episodes are checked solvable by rendering, in the run's look
        return generate_episodes(town, scene, per_difficulty=cfg.run.per_difficulty, seed=cfg.run.episode_seed)


def vlm_plan(cfg: AgosConfig, policies: dict[str, str], standin: str | None) -> dict[str, Any]:
    """Where the run's VLM policies get their model; {} when no policy needs one. A replay of recorded
    calls (``--vlm-cache DIR --vlm-cache-mode replay``) needs no endpoint, only the model's name; the
    cache is checked here, before anything starts."""
    if not any(needs_vlm(p) for p in policies.values()):
        return {}
    cache = vlm_cache_plan(cfg, STANDIN_MODEL if standin is not None else cfg.vlm.model)
    if standin is not None:
        return {"standin": standin, "model": STANDIN_MODEL, **cache}
    if not cfg.vlm.model or not (cfg.vlm.base_url or cfg.vlm.replaying):
        names = ", ".join(sorted({p for p in policies.values() if needs_vlm(p)}))
        raise RunDirError(f"policy {names} asks a VLM: give --vlm-base-url URL --model NAME, or --vlm-standin for the "
                          "offline stand-in server" + (" (a replay needs only --model)" if cfg.vlm.replaying else ""))
    if cfg.vlm.replaying:  # no endpoint: none is asked, checked or stored
        return {"model": cfg.vlm.model, **cache}
    return {"base_url": cfg.vlm.base_url, "model": cfg.vlm.model, **cache}


def vlm_cache_plan(cfg: AgosConfig, model: str | None) -> dict[str, Any]:
    """``--vlm-cache``'s directory and mode as run.json keeps them ({} without a cache); RunDirError
    when the cache cannot be used (not a cache, a replay of a missing one or of another model)."""
    from agos.agents.vlm.cache import CacheError, ReplyCache

    o = cfg.vlm
    if o.cache_dir is None:
        if o.cache_mode == "replay":
            raise RunDirError("--vlm-cache-mode replay replays a cache: give its directory with --vlm-cache DIR")
        return {}
    if o.cache_mode != "off":
        try:
            cache = ReplyCache(o.cache_dir, o.cache_mode)
        except CacheError as exc:
            raise RunDirError(str(exc)) from None
        try:
            models = cache.models()
        finally:
            cache.close()
        if o.cache_mode == "replay" and model not in models:
            raise RunDirError(f"--vlm-cache {o.cache_dir} holds no call of model {model!r} to replay "
                              f"(it holds: {', '.join(models) or 'nothing'}); give --model as recorded")
    return {"cache_dir": str(Path(o.cache_dir).resolve()), "cache_mode": o.cache_mode}


def check_endpoint(options: VlmOptions, vlm: dict[str, Any]) -> str | None:
    """Before any process starts: the model endpoint of a run's plan (``vlm``, :func:`vlm_plan`) answers
    ``/models`` and lists the model, with the key of ``options.api_key_env`` when it asks for one.
    Raises :class:`EndpointError` with the line of agents/vlm/endpoint.py (refused, unreachable,
    timeout, 401/403 naming the key variable and whether it is set, a model not served); returns the
    line to print (what was checked, where the key comes from), or None when the plan names no
    endpoint (no VLM policy, or the stand-in the run starts itself).

    A key variable is *needed* when the endpoint answers 401/403 without it: then an unset one is
    refused here. An unset variable is accepted, and said so, when the endpoint answers without a key
    (a local vLLM, SGLang or Ollama server usually asks for none, on loopback or not)."""
    checked = _endpoint_check(options, vlm)
    return None if checked is None else checked[0]


def _endpoint_check(options: VlmOptions, vlm: dict[str, Any]) -> tuple[str, list[dict[str, Any]]] | None:
    """:func:`check_endpoint`'s line and the ``/models`` answer's entries (for the run card)."""
    if "base_url" not in vlm or options.replaying:  # a replay (--vlm-cache-mode replay) asks no endpoint
        return None
    import asyncio

    from agos.agents.vlm.client import VlmClient, VlmError

    checked = options.model_copy(update={"base_url": vlm["base_url"], "model": vlm["model"]})
    timeout_s = min(checked.timeout_s, PREFLIGHT_TIMEOUT_S)

    async def listing() -> list[dict[str, Any]]:
        client = VlmClient(str(checked.base_url), str(checked.model), api_key_env=checked.api_key_env, timeout_s=timeout_s)
        try:
            await client.preflight()
            return client.listing or []
        finally:
            await client.close()

    try:
        answer = asyncio.run(listing())
    except VlmError as exc:
        raise EndpointError(f"VLM endpoint {exc}") from None
    key = (f"API key from {checked.api_key_env}" if os.environ.get(checked.api_key_env)
           else f"no API key: {checked.api_key_env} is not set and the endpoint answered without one")
    return f"VLM endpoint: {checked.base_url} serves {checked.model} ({key})", answer


def new_plan(cfg: AgosConfig, *, run_dir: Path | None, comm: str, timing_mode: str, stamp: bool,
             vlm_standin: str | None = None, workers: int | str | None = None, dataset_out: Path | None = None,
             check_vlm: bool = False, caps: Caps | None = None, prices: PriceTable | None = None,
             model_link: str | None = None, pose_error: str | None = None) -> RunPlan:
    """A new run directory with its run.json (the run card among it: deploy/run/card_writer.py),
    episodes.jsonl and, for a VLM run, prompts.txt. ``workers``: the command's ``--workers`` (a count or
    ``auto``), stored for ``--resume``; ``dataset_out``: see :class:`RunPlan`. ``check_vlm``: the run
    starts its agents here, so its model endpoint is checked (:func:`check_endpoint`) before episodes
    are read or generated and anything is written. ``caps`` and ``prices``: a cost cap needs a price
    for the run's model (ValueError before anything is written)."""
    from agos.world.episodes.files import read_split, write_episodes

    # Everything that can be wrong with the command fails before episodes are generated.
    if run_dir is None:
        run_id = f"{cfg.run.run_id}-{datetime.now(UTC).strftime('%Y%m%d-%H%M%S')}" if stamp else cfg.run.run_id
        run_dir = cfg.run.runs_dir / run_id
    if (run_dir / "results.sqlite").exists():
        raise RunDirError(f"{run_dir}: already holds results; resume it with: agos eval --resume {run_dir}")
    policies = {"uav": cfg.run.policy_uav, "ugv": cfg.run.policy_ugv}
    config = run_episode_config(cfg, policies=policies, comm=comm, timing_mode=timing_mode,  # bad names fail here
                                model_link=model_link, pose_error=pose_error)
    vlm = vlm_plan(cfg, policies, vlm_standin)
    caps = caps or Caps()
    check_prices(caps, prices, vlm.get("model"))
    checked = _endpoint_check(cfg.vlm, vlm) if check_vlm else None
    endpoint, models_answer = checked if checked is not None else (None, None)
    if cfg.run.episodes_file:  # checked as a whole: ids, towns, waypoints, the run's look (world/episodes/files.py)
        episodes = read_split(cfg.run.episodes_file, look=config.look)
    else:
        episodes = generated_episodes(cfg)
    run_dir.mkdir(parents=True, exist_ok=True)
    write_episodes(run_dir / "episodes.jsonl", episodes)
    plan = RunPlan(run_dir, episodes, policies, config, vlm=vlm, workers=workers, dataset_out=dataset_out,
                   endpoint=endpoint, caps=caps, prices=prices)
    card = run_card(run_dir, vlm=vlm, options=cfg.vlm, models_answer=models_answer, split=cfg.run.episodes_file,
                    model_link=config.model_link)
    (run_dir / RUN_FILE).write_text(json.dumps({
        "run_id": plan.run_id, "created_utc": datetime.now(UTC).isoformat(timespec="seconds"),
        "policies": plan.policies, "comm": config.comm.name, "pose_error": config.pose_error.name,
        "timing_mode": config.timing_mode, "episodes": len(episodes),
        "vlm": vlm, "workers": workers, "config_hash": config.config_hash(),
        **({"dataset_out": str(dataset_out)} if dataset_out is not None else {}),
        "episode_config": config.model_dump(mode="json"),
        "episode_source": str(cfg.run.episodes_file or f"generated: {cfg.run.town}, {cfg.run.per_difficulty}/difficulty, "
                                                         f"seed {cfg.run.episode_seed}"),
        "provenance": provenance(),  # what made this run's numbers; not part of config_hash
        "card": card, "prices": prices.as_json() if prices is not None else None, "caps": caps.as_json(),
    }, indent=2) + "\n")
    return plan


def resume_plan(run_dir: Path) -> RunPlan:
    """The plan of a run directory made by :func:`new_plan`; its episodes are checked again against this
    agos's towns (another version may build them otherwise) before anything starts."""
    from agos.world.episodes.files import read_split

    path = run_dir / RUN_FILE
    if not path.exists():
        raise RunDirError(f"{run_dir}: no {RUN_FILE}; not an agos run directory")
    meta = json.loads(path.read_text())
    if "episode_config" not in meta:
        raise RunDirError(f"{path}: made by an agos without episode configurations; start a new run")
    try:
        config = read_config(meta["episode_config"], where=str(path))
    except StoredConfigError as exc:
        raise RunDirError(str(exc)) from None
    try:
        prices = prices_from_json(meta["prices"], where=f"{path}: prices") if meta.get("prices") else None
    except PriceError as exc:
        raise RunDirError(str(exc)) from None
    return RunPlan(run_dir, read_split(run_dir / "episodes.jsonl", look=config.look), meta["policies"], config, resumed=True,
                   vlm=meta.get("vlm", {}), workers=meta.get("workers"),
                   dataset_out=Path(meta["dataset_out"]) if meta.get("dataset_out") else None,
                   caps=Caps.from_json(meta.get("caps")), prices=prices)


def resume_with(plan: RunPlan, *, max_cost_usd: float | str | None, max_tokens: int | str | None,
                prices: PriceTable | None) -> None:
    """A resumed plan with the caps and prices its command gives: a cap given replaces the stored one
    (``"none"`` lifts it; None keeps it); given prices replace the stored ones. A cost cap still needs a
    price (ValueError). run.json keeps the new values and, under ``resumes``, when and with which caps
    and commit each resume ran."""
    def pick(given: float | int | str | None, stored: float | int | None) -> Any:
        return stored if given is None else None if given == "none" else given

    plan.caps = Caps(pick(max_cost_usd, plan.caps.max_cost_usd), pick(max_tokens, plan.caps.max_tokens))
    if prices is not None:
        plan.prices = prices
    check_prices(plan.caps, plan.prices, plan.vlm.get("model"))
    path = plan.run_dir / RUN_FILE
    meta = json.loads(path.read_text())
    meta["caps"] = plan.caps.as_json()
    meta["prices"] = plan.prices.as_json() if plan.prices is not None else None
    meta.setdefault("resumes", []).append({"utc": datetime.now(UTC).isoformat(timespec="seconds"),
                                           "caps": plan.caps.as_json(), "commit": provenance()["commit"]})
    tmp = path.with_suffix(".json.tmp")
    tmp.write_text(json.dumps(meta, indent=2) + "\n")
    tmp.replace(path)


def stored_episodes(run_dir: Path) -> set[str]:
    """Episodes of a run directory with a ``finished`` record: a resume skips them and plays the rest,
    including episodes stored as infrastructure failures (a missing agent, a crashed world)."""
    path = run_dir / "results.sqlite"
    if not path.exists():
        return set()
    with ResultStore(path, create=False) as store:
        return store.finished_ids()

