"""How the run commands end when they fail: which errors each maps to which exit status, and the
line it prints (the command's name first: ``eval error: ...``)."""

from __future__ import annotations

import sys

from rich.console import Console

from agos.agents.contract import EndpointOutage, FatalPolicyError
from agos.deploy.run.plan import RunDirError
from agos.runtime.deaths import ChildDied
from agos.runtime.links import ProfileError

EXIT_REFUSED = 2
"""A command refused before anything started: a bad flag, name, profile, file or run directory."""
REFUSED: tuple[type[Exception], ...] = (RunDirError, ProfileError, ValueError)  # bad profiles of every kind are ValueErrors
"""What ``agos eval`` and ``agos sweep`` refuse with one line and :data:`EXIT_REFUSED`."""
EXIT_SWEEP_WORKER_DIED = 1
EXIT_SWEEP_OUTAGE = 6
"""As ``agos eval``'s ``EXIT_INFRA``: the model endpoint gave no answer."""
SWEEP_STOPS: tuple[type[Exception], ...] = (*REFUSED, FatalPolicyError, EndpointOutage, ChildDied)
"""What stops ``agos sweep``: :func:`sweep_exit` says it and gives the exit status."""


def refused(command: str, exc: Exception) -> int:
    """``COMMAND error: ...`` on stderr; :data:`EXIT_REFUSED`."""
    print(f"{command} error: {exc}", file=sys.stderr)
    return EXIT_REFUSED


def sweep_exit(exc: Exception) -> int:
    """What stopped ``agos sweep`` (one of :data:`SWEEP_STOPS`), said on stderr; its exit status."""
    if isinstance(exc, REFUSED):
        return refused("sweep", exc)
    if isinstance(exc, FatalPolicyError):  # a replay (--vlm-cache-mode replay) that lacks a recorded call
        print(f"sweep error: {exc}", file=sys.stderr)
        return exc.exit_code
    if isinstance(exc, EndpointOutage):  # never scored as the model's WAIT: the sweep stops
        print(f"sweep error: the model endpoint gave no answer: {exc}; finished episodes are kept, the same sweep "
              "plays the rest once it answers", file=sys.stderr)
        return EXIT_SWEEP_OUTAGE
    if isinstance(exc, ChildDied):  # a worker process died (a signal, an exit): which, how, its log's last lines
        from agos.deploy.run.launcher import print_death

        print_death(Console(stderr=True, soft_wrap=True), exc.name, exc.returncode, exc.log, exc.tail,
                    note="; the sweep stops (its finished episodes are kept: the same command plays the rest)")
        return EXIT_SWEEP_WORKER_DIED
    raise exc
