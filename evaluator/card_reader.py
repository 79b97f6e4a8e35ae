"""A run's card: what produced its numbers, read from its ``run.json`` and shown by ``agos report``
above its tables (and written to ``card.md``).

``agos eval`` writes the card (deploy/run/card_writer.py): ``provenance`` (agos version, commit and whether
the tree was dirty, uv.lock's sha256, Python and package versions), ``card`` (the prompts' sha256 and
the ``prompts.txt`` copied beside it, the model, its endpoint and that endpoint's ``/models`` answer,
the sampling parameters, the cache mode, the split file's and the run's ``episodes.jsonl``'s sha256),
``prices`` and ``caps``. A run made before cards existed shows what its run.json has.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from agos.evaluator.cost import PriceError, PriceTable, prices_from_json

RUN_FILE = "run.json"


def run_meta(path: Path) -> dict[str, Any] | None:
    """The ``run.json`` of the run at ``path`` (a run directory, or a file inside one); None when there
    is none or it is not a JSON object (a JSONL of summaries, a copied results file)."""
    run_json = path / RUN_FILE if path.is_dir() else path.parent / RUN_FILE
    try:
        meta = json.loads(run_json.read_text())
    except (OSError, ValueError):
        return None
    return meta if isinstance(meta, dict) else None


def run_prices(meta: dict[str, Any] | None, *, where: str) -> PriceTable | None:
    """The price table ``agos eval`` was given for the run (run.json's ``prices``); None without one.
    :class:`PriceError` for a table that cannot be read."""
    data = (meta or {}).get("prices")
    return None if data is None else prices_from_json(data, where=f"{where}: prices")


def _short(sha: object, n: int = 12) -> str:
    return str(sha)[:n] if sha else "-"


def _listing(answer: object) -> str:
    if isinstance(answer, dict) and "error" in answer:
        return f"no answer ({answer['error']})"
    if isinstance(answer, list):
        ids = [str(m.get("id")) for m in answer if isinstance(m, dict)]
        return ", ".join(ids) or "no models"
    return "not asked"


def card_lines(meta: dict[str, Any] | None, *, label: str) -> list[str]:
    """The card as lines of text (no markup), first line the run's label and id."""
    if meta is None:
        return [f"{label}: no run.json (a file of records): no card"]
    lines = [f"{label}: run {meta.get('run_id', '?')}, created {meta.get('created_utc', '?')}, "
             f"{meta.get('episodes', '?')} episodes"]
    prov = meta.get("provenance") or {}
    if prov:
        commit = prov.get("commit")
        dirty = " (dirty tree)" if prov.get("dirty") else ""
        packages = ", ".join(f"{k} {v}" for k, v in sorted((prov.get("packages") or {}).items()))
        lines.append(f"  agos {prov.get('agos', '?')}, commit {_short(commit) if commit else 'unknown (not a checkout)'}"
                     f"{dirty}, uv.lock {_short(prov.get('lock_sha256'))}, Python {prov.get('python', '?')}; {packages}")
    policies = meta.get("policies") or {}
    lines.append(f"  policies: UAV {policies.get('uav', '?')}, UGV {policies.get('ugv', '?')}; comm {meta.get('comm', '?')}, "
                 f"pose error {meta.get('pose_error', 'exact')}, "
                 f"timing {meta.get('timing_mode', '?')}, configuration {meta.get('config_hash', '?')}")
    card = meta.get("card")
    if not isinstance(card, dict):
        lines.append("  (no run card: the run was made before agos recorded one)")
        return lines
    model = card.get("model")
    if model:
        endpoint = card.get("endpoint") or "none (replayed from the cache)"
        lines.append(f"  model: {model} at {endpoint}; /models: {_listing(card.get('models_answer'))}")
        sampling = card.get("sampling") or {}
        lines.append("  sampling: " + (", ".join(f"{k} {v}" for k, v in sampling.items()) or "-"))
        prompts = card.get("prompts") or {}
        lines.append(f"  prompts: sha256 {_short(prompts.get('sha256'), 16)} ({prompts.get('file', '-')})")
        cache = card.get("cache")
        lines.append(f"  model-call cache: {cache['mode']} {cache['dir']}" if isinstance(cache, dict)
                     else "  model-call cache: none")
        link = card.get("model_link")
        if isinstance(link, dict):  # cards since the link to the model (docs/COMMS.md)
            lines.append(f"  model placement: {link.get('placement', '?')}"
                         + (f" ({link['description']})" if link.get("description") else ""))
    else:
        lines.append("  model: none (scripted policies)")
    split = card.get("split")
    source = (f"{split.get('file')} sha256 {_short(split.get('sha256'), 16)}" if isinstance(split, dict)
              else f"{meta.get('episode_source', '?')}")
    lines.append(f"  episodes: {source}; episodes.jsonl sha256 {_short(card.get('episodes_sha256'), 16)}")
    try:
        prices = run_prices(meta, where=RUN_FILE)
    except PriceError as exc:
        prices, bad = None, str(exc)
    else:
        bad = ""
    caps = meta.get("caps") or {}
    cap_text = ", ".join(f"{k.replace('_', ' ')} {v:g}" for k, v in caps.items() if v is not None) or "none"
    lines.append(f"  prices: {prices.describe() if prices else bad or 'none given'}; caps: {cap_text}")
    return lines
