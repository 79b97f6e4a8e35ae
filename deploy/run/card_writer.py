"""A run's card: what ``agos eval`` writes into ``run.json`` (key ``card``, beside ``provenance``,
``prices`` and ``caps``) so that a number can be traced to what produced it; ``agos report`` prints
it (evaluator/card_reader.py).

    "card": {
      "model": "Qwen/Qwen2.5-VL-7B-Instruct" | null,     # null: no policy asks a model
      "endpoint": "http://host:8000/v1" | null,         # null: the stand-in (see models_answer) or a replay
      "models_answer": [{"id": ..., ...}] | {"error": "..."} | null,   # the endpoint's GET /models entries
      "sampling": {"temperature": 0.0, "max_tokens": 512, "structured_output": true, "reasks": 2,
                   "max_retries": 4, "timeout_s": 60.0, "images": "all", "concurrency": 8,
                   "image_max_px": null, "jpeg_quality": null},   # null: images as rendered
      "model_link": {"placement": "lte", "description": "...", "profile": {...}} | {"placement": "onboard"},
      "prompts": {"sha256": "...", "file": "prompts.txt", "modules": ["agos.agents.vlm.agos_prompts", ...]},
      "cache": {"mode": "record", "dir": "/abs/cache"} | null,
      "split": {"file": "/abs/val.jsonl", "sha256": "..."} | null,      # null: generated episodes
      "episodes_sha256": "..."                                          # the run's own episodes.jsonl
    }

``prompts.txt`` (in the run directory, for VLM runs) is the source text of the modules that write
every request the policies send (system prompts, stage texts, the request's layout and reply
schema), one after the other under a header line each; its sha256 is ``prompts.sha256``, so any
change of wording, layout or schema changes it.
"""

from __future__ import annotations

import hashlib
import importlib.util
from pathlib import Path
from typing import Any

from agos.runtime.model_link import ONBOARD, ModelLinkProfile
from agos.runtime.settings import VlmOptions

PROMPTS_FILE = "prompts.txt"
PROMPT_MODULES = ("agos.agents.vlm.agos_prompts", "agos.agents.vlm.baseline_prompts", "agos.agents.vlm.request",
                  "agos.agents.vlm.protocol")
"""The modules whose text makes the requests of agos's VLM policies (AGOS-Agent, its ablations, the
Baseline): their prompts, the shared building blocks and the request layout with the reply schema."""


def file_sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def prompts_text() -> str:
    """The source of :data:`PROMPT_MODULES`, each under ``===== module (file name) =====``."""
    parts = []
    for name in PROMPT_MODULES:
        spec = importlib.util.find_spec(name)
        if spec is None or spec.origin is None:
            raise RuntimeError(f"cannot find the prompt module {name}")
        origin = Path(spec.origin)
        parts.append(f"===== {name} ({origin.name}) =====\n{origin.read_text(encoding='utf-8')}")
    return "\n".join(parts)


def write_prompts(run_dir: Path) -> dict[str, Any]:
    """Write ``prompts.txt`` into ``run_dir``; the card's ``prompts`` entry."""
    text = prompts_text().encode("utf-8")
    (run_dir / PROMPTS_FILE).write_bytes(text)
    return {"sha256": hashlib.sha256(text).hexdigest(), "file": PROMPTS_FILE, "modules": list(PROMPT_MODULES)}


def sampling(options: VlmOptions) -> dict[str, Any]:
    """What shapes each request besides the prompt: the client's sampling and its request settings."""
    from agos.agents.vlm.client import TEMPERATURE

    return {"temperature": TEMPERATURE, "max_tokens": options.max_tokens, "structured_output": options.structured,
            "reasks": options.reasks, "max_retries": options.max_retries, "timeout_s": options.timeout_s,
            "images": options.images, "concurrency": options.concurrency, "image_max_px": options.image_max_px,
            "jpeg_quality": options.jpeg_quality}


def run_card(run_dir: Path, *, vlm: dict[str, Any], options: VlmOptions, models_answer: list[dict[str, Any]] | None,
             split: Path | None, model_link: ModelLinkProfile | None = None) -> dict[str, Any]:
    """The card of a new run whose ``episodes.jsonl`` is written (``vlm``: the plan's, see
    deploy/run/plan.py::vlm_plan); writes ``prompts.txt`` for a run that asks a model. ``model_link``:
    the configuration's placement of the model (None: onboard)."""
    card: dict[str, Any] = {"model": vlm.get("model"), "model_link": model_link_card(model_link)}
    if vlm:
        endpoint = vlm.get("base_url")
        if "standin" in vlm:  # its address is the run's own; its /models answer is added once it listens
            endpoint = f"agos vlm-standin started by the run (faults: {vlm['standin'] or 'none'})"
        card |= {"endpoint": endpoint, "models_answer": models_answer, "sampling": sampling(options),
                 "prompts": write_prompts(run_dir),
                 "cache": {"mode": vlm["cache_mode"], "dir": vlm["cache_dir"]} if "cache_dir" in vlm else None}
    card["split"] = {"file": str(split.resolve()), "sha256": file_sha256(split)} if split is not None else None
    card["episodes_sha256"] = file_sha256(run_dir / "episodes.jsonl")
    return card


def model_link_card(profile: ModelLinkProfile | None) -> dict[str, Any]:
    """The card's ``model_link``: the placement's name, and for a link its description and profile."""
    if profile is None:
        return {"placement": ONBOARD}
    return {"placement": profile.name, "description": profile.description, "profile": profile.model_dump(mode="json")}


def models_answer(base_url: str, *, timeout_s: float = 5.0) -> list[dict[str, Any]] | dict[str, str]:
    """GET ``base_url``/models (no key: for the stand-in a run starts itself): the answer's entries,
    or ``{"error": why}``."""
    import httpx

    try:
        response = httpx.get(f"{base_url.rstrip('/')}/models", timeout=timeout_s)
        data = response.json().get("data")
    except (httpx.HTTPError, ValueError, AttributeError) as exc:
        return {"error": f"{type(exc).__name__}: {exc}"[:200]}
    if not isinstance(data, list):
        return {"error": f"HTTP {response.status_code}: no model list"}
    return [m for m in data if isinstance(m, dict)]


def record_models_answer(run_dir: Path, answer: list[dict[str, Any]] | dict[str, str]) -> None:
    """Put the ``/models`` answer of the stand-in a run started into its card (run.json, replaced whole)."""
    import json

    path = run_dir / "run.json"
    meta = json.loads(path.read_text())
    if isinstance(meta.get("card"), dict):
        meta["card"]["models_answer"] = answer
        tmp = path.with_suffix(".json.tmp")
        tmp.write_text(json.dumps(meta, indent=2) + "\n")
        tmp.replace(path)
