"""Tokens, cost and latency of a run's model calls: the price table and the per-group figures that
``agos metrics``, ``agos report`` and ``agos eval``'s caps read (docs/METRICS.md, "Tokens, cost and
latency").

A price table maps a model name to two prices in USD per million tokens, one for prompt (input)
tokens and one for completion (output) tokens; ``*`` prices every model not named. It comes from
``--price-in``/``--price-out`` (one price for every model), from ``--prices FILE.toml``::

    ["gpt-4o-2024-08-06"]          # the model name as the endpoint reports it in each trace
    in_usd_per_mtok = 2.50
    out_usd_per_mtok = 10.00

    ["*"]                          # optional: any other model
    in_usd_per_mtok = 0.0
    out_usd_per_mtok = 0.0

or from the run's ``run.json`` (``prices``, what ``agos eval`` was given). An episode's cost is
sum over its models of (prompt tokens x in + completion tokens x out) / 1e6; it is undefined
(``None``, ``--`` in tables) when there is no price table or the table does not price one of its
models, never 0. Tokens are what the endpoint reported for the requests it answered (re-asks
included; a retried request that got no answer reported none); a replayed run (``--vlm-cache-mode
replay``) reports the recorded calls' tokens, so its cost is the cost of the calls it replays.

Per group, every stored episode counts (scored or not: an infrastructure failure's tokens were
spent too); cost per success divides the group's cost by its successful scored episodes.
Latency is each traced decision's wall-clock time (all its requests, re-asks and retries
included), pooled over the group's decisions; p50 and p95 interpolate linearly between order
statistics (numpy's default), and are undefined without a traced decision.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

from agos.runtime.textfiles import TextFileError, one_line, read_toml

ANY_MODEL = "*"
"""The price table's key for every model it does not name."""
PRICE_KEYS = ("in_usd_per_mtok", "out_usd_per_mtok")
TOTAL = "total"
"""The row of every episode of a run (tokens and cost summed, latency pooled), after its groups."""


class PriceError(ValueError):
    """A price table that cannot be used: one line naming the file or flag, the key and what to do."""


@dataclass(frozen=True)
class Price:
    in_usd_per_mtok: float
    """USD per million prompt (input) tokens."""
    out_usd_per_mtok: float
    """USD per million completion (output) tokens."""


@dataclass(frozen=True)
class PriceTable:
    """Model name -> :class:`Price`; ``source`` says where it came from (a file, the flags, run.json)."""

    models: Mapping[str, Price]
    source: str

    def price(self, model: str) -> Price | None:
        return self.models.get(model) or self.models.get(ANY_MODEL)

    def as_json(self) -> dict[str, Any]:
        """The table as ``run.json`` keeps it (:func:`prices_from_json` reads it back)."""
        return {"source": self.source,
                "models": {m: {"in_usd_per_mtok": p.in_usd_per_mtok, "out_usd_per_mtok": p.out_usd_per_mtok}
                           for m, p in self.models.items()}}

    def describe(self) -> str:
        """One line: each model's prices, e.g. ``gpt-4o $2.5/$10 per M tokens in/out (prices.toml)``."""
        parts = [f"{m} ${p.in_usd_per_mtok:g}/${p.out_usd_per_mtok:g}" for m, p in self.models.items()]
        return f"{', '.join(parts)} per M tokens in/out ({self.source})"


def _price_value(value: object, where: str) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value) or value < 0:
        raise PriceError(one_line(f"{where}: {value!r} is no price; give USD per million tokens, a number >= 0"))
    return float(value)


def flat_prices(price_in: float, price_out: float) -> PriceTable:
    """One price for every model (``--price-in``/``--price-out``)."""
    return PriceTable({ANY_MODEL: Price(_price_value(price_in, "--price-in"), _price_value(price_out, "--price-out"))},
                      "--price-in/--price-out")


def read_prices(path: Path) -> PriceTable:
    """The price table of a TOML file (the module's docstring shows one); :class:`PriceError` naming
    the file and the key otherwise."""
    try:
        data = read_toml(path)
    except FileNotFoundError:
        raise PriceError(f"--prices {path}: no such file") from None
    except TextFileError as exc:
        raise PriceError(f"--prices {path}: {exc}") from None
    return prices_from_json({"source": str(path), "models": data}, where=f"--prices {path}")


def prices_from_json(data: object, *, where: str) -> PriceTable:
    """A table as :meth:`PriceTable.as_json` writes it (or a TOML file's tables under ``models``)."""
    if not isinstance(data, dict) or not isinstance(data.get("models"), dict) or not data["models"]:
        raise PriceError(f"{where}: no prices; give one table per model with {' and '.join(PRICE_KEYS)}")
    models: dict[str, Price] = {}
    for model, entry in data["models"].items():
        here = one_line(f"{where}: model {model!r}")
        if not isinstance(entry, dict):
            raise PriceError(f"{here}: not a table; give [\"{one_line(model)}\"] with {' and '.join(PRICE_KEYS)}")
        unknown = sorted(set(entry) - set(PRICE_KEYS))
        if unknown:
            raise PriceError(one_line(f"{here}: unknown key {unknown[0]!r}; the keys are {' and '.join(PRICE_KEYS)}"))
        missing = [k for k in PRICE_KEYS if k not in entry]
        if missing:
            raise PriceError(f"{here}: no {missing[0]} (USD per million tokens)")
        models[model] = Price(*(_price_value(entry[k], f"{here}: {k}") for k in PRICE_KEYS))
    return PriceTable(models, str(data.get("source") or where))


def price_table(*, prices_file: Path | None, price_in: float | None, price_out: float | None) -> PriceTable | None:
    """The table the flags give (None: none given). Refused: only one of ``--price-in``/``--price-out``,
    or both a file and flat prices."""
    flat = price_in is not None or price_out is not None
    if flat and prices_file is not None:
        raise PriceError("give --prices FILE or --price-in/--price-out, not both")
    if flat:
        if price_in is None or price_out is None:
            raise PriceError(f"--price-{'out' if price_in is not None else 'in'} is missing: give both --price-in and "
                             "--price-out (USD per million prompt and completion tokens)")
        return flat_prices(price_in, price_out)
    return read_prices(prices_file) if prices_file is not None else None


class Usage(Protocol):
    """One model's tokens in an episode (``EpisodeRecord.usage`` entries and summaries both fit)."""

    @property
    def model(self) -> str: ...
    @property
    def prompt_tokens(self) -> int: ...
    @property
    def completion_tokens(self) -> int: ...


class Costed(Protocol):
    """What the cost figures read of an episode summary."""

    @property
    def status(self) -> str: ...
    @property
    def success(self) -> bool: ...
    @property
    def usage(self) -> Sequence[Usage]: ...
    @property
    def decision_latencies_s(self) -> Sequence[float]: ...


def tokens_of(usage: Iterable[Usage]) -> int:
    """Prompt plus completion tokens."""
    return sum(u.prompt_tokens + u.completion_tokens for u in usage)


def cost_of(usage: Iterable[Usage], prices: PriceTable | None) -> float | None:
    """USD of these tokens at ``prices``; 0 without tokens; None without a table or when it does not
    price a model that has tokens."""
    total = 0.0
    for u in usage:
        if not (u.prompt_tokens or u.completion_tokens):
            continue
        price = prices.price(u.model) if prices is not None else None
        if price is None:
            return None
        total += (u.prompt_tokens * price.in_usd_per_mtok + u.completion_tokens * price.out_usd_per_mtok) / 1e6
    return total


def unpriced(models: Iterable[str], prices: PriceTable | None) -> list[str]:
    """The models among ``models`` that ``prices`` gives no price (all of them without a table)."""
    return sorted({m for m in models if prices is None or prices.price(m) is None})


def percentile(values: Sequence[float], q: float) -> float | None:
    """The ``q``-th percentile (0-100) with linear interpolation between order statistics (numpy's
    default); None for no values."""
    if not values:
        return None
    ordered = sorted(values)
    rank = (len(ordered) - 1) * q / 100.0
    low = math.floor(rank)
    high = min(low + 1, len(ordered) - 1)
    return ordered[low] + (ordered[high] - ordered[low]) * (rank - low)


@dataclass(frozen=True)
class CostSummary:
    """Tokens, cost and decision latency of a group of episodes (every stored episode counts)."""

    episodes: int
    successes: int
    """Successful scored episodes."""
    decisions: int
    """Traced decisions (decisions a model answered; scripted policies trace none)."""
    prompt_tokens: int
    completion_tokens: int
    cost_usd: float | None
    """None without a price for every model with tokens."""
    latency_p50_s: float | None
    latency_p95_s: float | None

    @property
    def tokens(self) -> int:
        return self.prompt_tokens + self.completion_tokens

    @property
    def tokens_per_decision(self) -> float | None:
        return self.tokens / self.decisions if self.decisions else None

    @property
    def tokens_per_episode(self) -> float | None:
        return self.tokens / self.episodes if self.episodes else None

    @property
    def cost_per_success_usd(self) -> float | None:
        """The group's whole cost (failures included) over its successes; None without one."""
        return self.cost_usd / self.successes if self.cost_usd is not None and self.successes else None

    def as_dict(self) -> dict[str, Any]:
        return {"episodes": self.episodes, "decisions_traced": self.decisions, "prompt_tokens": self.prompt_tokens,
                "completion_tokens": self.completion_tokens, "tokens_per_decision": self.tokens_per_decision,
                "tokens_per_episode": self.tokens_per_episode, "cost_usd": self.cost_usd,
                "cost_per_success_usd": self.cost_per_success_usd, "latency_p50_s": self.latency_p50_s,
                "latency_p95_s": self.latency_p95_s}


def cost_summary(episodes: Iterable[Costed], prices: PriceTable | None) -> CostSummary:
    """The figures of one group (see the module's docstring for what counts)."""
    n = successes = prompt = completion = 0
    latencies: list[float] = []
    cost: float | None = 0.0
    for e in episodes:
        n += 1
        successes += e.status == "finished" and e.success
        prompt += sum(u.prompt_tokens for u in e.usage)
        completion += sum(u.completion_tokens for u in e.usage)
        latencies.extend(e.decision_latencies_s)
        episode_cost = cost_of(e.usage, prices)
        cost = None if cost is None or episode_cost is None else cost + episode_cost
    return CostSummary(n, successes, len(latencies), prompt, completion, cost, percentile(latencies, 50),
                       percentile(latencies, 95))


def cost_by_group(episodes: Sequence[Any], prices: PriceTable | None, groups: Sequence[str],
                  key: Any) -> dict[str, CostSummary]:
    """:func:`cost_summary` per group named in ``groups`` (``key(e)`` gives an episode's group), then
    :data:`TOTAL` over every episode."""
    members: dict[str, list[Any]] = {g: [] for g in groups}
    for e in episodes:
        members.setdefault(key(e), []).append(e)
    out = {g: cost_summary(members[g], prices) for g in members}
    out[TOTAL] = cost_summary(episodes, prices)
    return out
