"""Caps on what a run's model calls may spend: ``agos eval --max-cost-usd USD`` and ``--max-tokens N``.

A cap is on the whole run: what it spent is the sum over every record it has, those stored before
this invocation (a resumed run) and each record this invocation has seen from a lease holder,
acknowledged or not; tokens are prompt plus completion tokens (``EpisodeRecord.usage``), cost is
their price (evaluator/cost.py). So ``--resume DIR`` with a higher cap goes on where the last cap
stopped.

**Could cross.** Before each lease the orchestrator asks :meth:`Budget.refusal` with the number of
episodes in flight (leased, no record yet). With ``m`` the mean spending of the run's finished
episodes so far, another episode may start unless

    spent + (in_flight + 1) x m > cap

i.e. unless the episodes in flight and the next one, each spending an average episode, could take
the run past the cap. Before the first finished record there is no ``m``: episodes then start one
at a time (a probe), so the first overshoot is at most one episode. A run whose spending reached a
cap starts nothing more. The estimate is a mean: an episode that spends more than the mean can still
carry the run past its cap, by at most what the episodes in flight spend above their mean (the
stop line says what was spent); tokens of an attempt that was lost (a crashed world) are in no
record and not counted.

When the gate refuses and nothing is leased any more (every played episode stored), the run stops:
one console line (the cap, what was spent, the estimate, how many episodes did not run, the command
that resumes), exit :data:`EXIT_CAPPED`.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass
from typing import Any

from agos.evaluator.cost import PriceTable, cost_of, tokens_of, unpriced
from agos.runtime.schemas import EpisodeRecord
from agos.runtime.traces import record_usage

EXIT_CAPPED = 5
"""``agos eval``'s exit status when a cap stopped the run (3 is every other stop ``--resume`` continues)."""


@dataclass(frozen=True)
class Caps:
    """``--max-cost-usd`` and ``--max-tokens`` (None: no cap)."""

    max_cost_usd: float | None = None
    max_tokens: int | None = None

    def __bool__(self) -> bool:
        return self.max_cost_usd is not None or self.max_tokens is not None

    def as_json(self) -> dict[str, Any]:
        return {"max_cost_usd": self.max_cost_usd, "max_tokens": self.max_tokens}

    @classmethod
    def from_json(cls, data: object) -> Caps:
        if not isinstance(data, dict):
            return cls()
        cost, tokens = data.get("max_cost_usd"), data.get("max_tokens")
        return cls(float(cost) if isinstance(cost, int | float) else None, tokens if isinstance(tokens, int) else None)


@dataclass(frozen=True)
class Spending:
    """What a run's records spent: all of them, and the finished ones the estimate averages."""

    episodes: int
    tokens: int
    cost_usd: float | None
    """None when a model with tokens has no price."""
    finished: int
    finished_tokens: int
    finished_cost_usd: float | None

    def per_episode(self, what: str) -> float | None:
        """Mean ``tokens`` or ``cost`` of a finished episode; None before the first one."""
        if not self.finished:
            return None
        total = self.finished_tokens if what == "tokens" else self.finished_cost_usd
        return None if total is None else total / self.finished


def spending(records: Iterable[EpisodeRecord], prices: PriceTable | None) -> Spending:
    n = tokens = done = done_tokens = 0
    cost: float | None = 0.0
    done_cost: float | None = 0.0
    for r in records:
        usage = record_usage(r)
        t, c = tokens_of(usage), cost_of(usage, prices)
        n, tokens = n + 1, tokens + t
        cost = None if cost is None or c is None else cost + c
        if r.status == "finished":
            done, done_tokens = done + 1, done_tokens + t
            done_cost = None if done_cost is None or c is None else done_cost + c
    return Spending(n, tokens, cost, done, done_tokens, done_cost)


def check_prices(caps: Caps, prices: PriceTable | None, model: str | None) -> None:
    """Before anything starts: a cost cap needs a price for the run's model (ValueError, one line)."""
    if caps.max_cost_usd is None or model is None:
        return
    if prices is None:
        raise ValueError(f"--max-cost-usd needs the price of model {model}: give --price-in/--price-out (USD per million "
                         "prompt and completion tokens) or --prices FILE.toml")
    if unpriced([model], prices):
        raise ValueError(f"--max-cost-usd: {prices.source} has no price for model {model}; add [\"{model}\"] or [\"*\"]")


def _usd(value: float) -> str:
    return f"${value:.4f}" if value < 100 else f"${value:,.2f}"


def _episodes(n: int) -> str:
    return f"{n} episode" if n == 1 else f"{n} episodes"


class Budget:
    """The caps of a run and what its records spent, for the orchestrator's gate and the stop line."""

    def __init__(self, caps: Caps, prices: PriceTable | None, before: Iterable[EpisodeRecord] = ()) -> None:
        """``before``: the run's records stored before this invocation (a resumed run)."""
        self.caps, self.prices = caps, prices
        self.before = list(before)
        self._seen: list[EpisodeRecord] = []
        self._spent = spending(self.before, prices)

    def see(self, records: Iterable[EpisodeRecord]) -> None:
        """The records this invocation has seen so far (all of them, each call)."""
        seen = list(records)
        if len(seen) != len(self._seen):
            self._seen = seen
            self._spent = spending([*self.before, *seen], self.prices)

    @property
    def spent(self) -> Spending:
        return self._spent

    def refusal(self, in_flight: int) -> tuple[str, str] | None:
        """None when another episode may start with ``in_flight`` episodes running; else the cap's flag
        and why not (the start of the stop line: which cap, what was spent, the estimate)."""
        s = self._spent
        caps: list[tuple[str, float | None, float | None, Any]] = [
            ("--max-tokens", self.caps.max_tokens, float(s.tokens), lambda v: f"{v:,.0f} tokens"),
            ("--max-cost-usd", self.caps.max_cost_usd, s.cost_usd, _usd)]
        for flag, cap, spent, show in caps:
            if cap is None:
                continue
            if spent is None:
                return flag, f"{flag} {cap:g} cannot be kept: a model of the run has no price"
            if spent >= cap:
                return flag, f"the run has spent {show(spent)} on {_episodes(s.episodes)}, reaching {flag} {cap:g}"
            mean = s.per_episode("tokens" if flag == "--max-tokens" else "cost")
            if mean is None:
                if in_flight:
                    return flag, "one episode at a time until the first one finishes and says what an episode spends"
                continue
            if spent + (in_flight + 1) * mean > cap:
                return flag, (f"the next episode could cross {flag} {cap:g}: the run spent {show(spent)} on "
                              f"{_episodes(s.episodes)} (about {show(mean)} a finished episode), {in_flight} in flight")
        return None

    def may_lease(self, in_flight: int) -> bool:
        """The orchestrator's gate (deploy/run/orchestrator.py)."""
        return self.refusal(in_flight) is None
