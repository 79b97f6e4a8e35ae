"""The stand-in's fault model: which outcome each chat completion gets.

An outcome is ``ok`` or one of :data:`FAULT_KINDS`, drawn per valid request from a seeded RNG, the
faults' probabilities stacked on the unit interval in :data:`FAULT_KINDS` order; what each outcome
does to the answer is in :mod:`agos.agents.vlm.standin.replies` and the server
(:mod:`agos.agents.vlm.standin.server`).
"""

from __future__ import annotations

import random
from collections.abc import Mapping

OK = "ok"
FAULT_KINDS = ("429", "500", "timeout", "malformed", "fenced", "empty", "length", "garbage")
"""Injectable faults, in the order their probabilities are stacked on the unit interval."""
OUTCOMES = (OK, *FAULT_KINDS)


class FaultSpecError(ValueError):
    """A fault specification is wrong; the message names the bad entry."""


def check_faults(faults: Mapping[str, float] | None) -> dict[str, float]:
    """Validated fault probabilities: known kinds, each in [0, 1], summing to at most 1."""
    out: dict[str, float] = {}
    for kind, p in (faults or {}).items():
        kind = str(kind)
        if kind not in FAULT_KINDS:
            raise FaultSpecError(f"unknown fault {kind!r} (known: {', '.join(FAULT_KINDS)})")
        if not isinstance(p, int | float) or isinstance(p, bool) or not 0.0 <= float(p) <= 1.0:
            raise FaultSpecError(f"fault {kind!r}: probability {p!r} is not a number in [0, 1]")
        out[kind] = float(p)
    total = sum(out.values())
    if total > 1.0 + 1e-9:
        raise FaultSpecError(f"fault probabilities sum to {total:g}, more than 1")
    return out


def parse_faults(spec: str) -> dict[str, float]:
    """``"429=0.1,500=0.05,timeout=0.02"`` -> ``{"429": 0.1, ...}``; FaultSpecError names a bad entry."""
    faults: dict[str, float] = {}
    for entry in (e.strip() for e in spec.split(",")):
        if not entry:
            continue
        kind, sep, value = (s.strip() for s in entry.partition("="))
        if not sep:
            raise FaultSpecError(f"bad fault entry {entry!r}: expected KIND=PROBABILITY, e.g. 429=0.1")
        if kind in faults:
            raise FaultSpecError(f"bad fault entry {entry!r}: {kind!r} given twice")
        try:
            faults[kind] = float(value)
        except ValueError:
            raise FaultSpecError(f"bad fault entry {entry!r}: {value!r} is not a probability") from None
        try:
            check_faults({kind: faults[kind]})
        except FaultSpecError as exc:
            raise FaultSpecError(f"bad fault entry {entry!r}: {exc}") from None
    return check_faults(faults)


def draw_outcome(u: float, faults: Mapping[str, float]) -> str:
    """The outcome for a uniform draw ``u`` in [0, 1): faults stacked in ``FAULT_KINDS`` order, then ok."""
    edge = 0.0
    for kind in FAULT_KINDS:
        edge += faults.get(kind, 0.0)
        if u < edge:
            return kind
    return OK


def fault_rng(seed: int) -> random.Random:
    """The RNG of outcome draws for ``seed`` (the server's and :func:`fault_sequence`'s)."""
    return random.Random(f"agos-vlm-standin:{seed}:faults")


def fault_sequence(faults: Mapping[str, float], seed: int, n: int) -> list[str]:
    """The outcomes of the first ``n`` unscripted requests of a server with these faults and seed."""
    rng, checked = fault_rng(seed), check_faults(faults)
    return [draw_outcome(rng.random(), checked) for _ in range(n)]
