"""Timed steps of the deployment scripts (tests/deploy/compose_e2e.py, tests/deploy/slurm_e2e.py): each
step's name and wall time as it ends, and the table of them all at the end."""

from __future__ import annotations

import contextlib
import time
from collections.abc import Iterator


class Failed(Exception):
    """A step that could not be done, or a check that did not hold; the message says which and why."""


PHASES: list[tuple[str, float]] = []
"""(step, seconds) in the order the steps ended."""


@contextlib.contextmanager
def phase(name: str) -> Iterator[None]:
    print(f"\n== {name}", flush=True)
    start = time.monotonic()
    try:
        yield
    finally:
        took = time.monotonic() - start
        PHASES.append((name, took))
        print(f"-- {name}: {took:.1f} s", flush=True)


def print_phases(title: str, total_s: float, width: int = 70) -> None:
    """The table of every step and the ``total``."""
    PHASES.append(("total", total_s))
    print(f"\n{title} phases:")
    for name, took in PHASES:
        print(f"  {name:<{width}} {took:7.1f} s")
