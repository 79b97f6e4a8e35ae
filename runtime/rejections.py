"""Counting what a process refuses to act on: unreadable, malformed or forged bus messages.

Every process that reads the bus validates what it receives (schema version, type, finite
numbers, names, the episode and lease it claims) and hands each refusal to one
:class:`Rejections`: the first few per key kind and reason are logged, then every 100th, so a
flood cannot fill the disk or drown the log, and the totals are logged when the process ends
(``rejected 1234 messages: result/not the lease holder=...``), which is how a run's owner, and the
fuzz test, learn how much was refused. A refusal never raises and never ends the process.
"""

from __future__ import annotations

import logging
import math
from collections import Counter
from typing import Any

import msgspec

LOG_FIRST = 5
LOG_EVERY = 100


class Rejections:
    """Per-process counts of refused messages by ``(key kind, reason)``; logs rate-limited."""

    def __init__(self, log: logging.Logger) -> None:
        self.log = log
        self.counts: Counter[tuple[str, str]] = Counter()

    def reject(self, key: str, reason: str, detail: object = "") -> None:
        """Count one refused message on ``key`` (its last segment is the kind) under ``reason`` (a
        short fixed phrase: the counts' category) and maybe log it with ``detail``."""
        kind = key.rsplit("/", 1)[-1]
        self.counts[(kind, reason)] += 1
        n = self.counts[(kind, reason)]
        if n <= LOG_FIRST or n % LOG_EVERY == 0:
            self.log.warning("refused a message on %s: %s%s (%d so far)", key, reason, f": {detail}" if detail else "", n)

    @property
    def total(self) -> int:
        return sum(self.counts.values())

    def summary(self) -> str:
        """``rejected N messages: kind/reason=n, ...`` (most frequent first), or '' when none."""
        if not self.counts:
            return ""
        parts = ", ".join(f"{kind}/{reason}={n}" for (kind, reason), n in self.counts.most_common())
        return f"rejected {self.total} messages: {parts}"

    def log_summary(self) -> None:
        if self.counts:
            self.log.warning("%s", self.summary())


def non_finite_field(value: Any, path: str = "$") -> str | None:
    """The path of the first NaN or infinite float inside ``value`` (a message struct, list, tuple
    or dict of them), or None when every number is finite. Bytes and strings are not entered."""
    if isinstance(value, float):
        return None if math.isfinite(value) else path
    if isinstance(value, msgspec.Struct):
        for name in value.__struct_fields__:
            found = non_finite_field(getattr(value, name), f"{path}.{name}")
            if found:
                return found
    elif isinstance(value, (list, tuple)):
        for i, item in enumerate(value):
            found = non_finite_field(item, f"{path}[{i}]")
            if found:
                return found
    elif isinstance(value, dict):
        for k, item in value.items():
            found = non_finite_field(item, f"{path}.{k}")
            if found:
                return found
    return None
