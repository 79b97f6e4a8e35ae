"""Machine-readable benchmark figures for ``make bench`` (bench/run_all.py).

A bench run with ``--json`` prints, beside its usual output, one line per figure it measured::

    BENCH-FIGURE {"figure": "...", "measured": 1.31, "shown": "1.31x (...)", "goal": "<= 1.3x", "met": false}

``met`` is None for a figure printed for information (no goal). ``run_all.py`` reads these lines
from each bench's output and prints one table; a missed goal never changes an exit status there.
"""

from __future__ import annotations

import json
from typing import Any

PREFIX = "BENCH-FIGURE "


class Figures:
    """Prints figure lines when enabled (``--json``); a no-op otherwise."""

    def __init__(self, enabled: bool) -> None:
        self.enabled = enabled

    def add(self, figure: str, measured: float, shown: str, goal: str = "", met: bool | None = None) -> None:
        if self.enabled:
            line = {"figure": figure, "measured": measured, "shown": shown, "goal": goal, "met": met}
            print(PREFIX + json.dumps(line), flush=True)


def parse(output: str) -> list[dict[str, Any]]:
    """The figure lines in a bench's output, in order."""
    return [json.loads(line[len(PREFIX):]) for line in output.splitlines() if line.startswith(PREFIX)]
