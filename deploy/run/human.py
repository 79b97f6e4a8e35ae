"""The human console in ``agos eval``: durations people type, and starting the console for a run.

``agos eval --policy human`` (or ``--policy-uav human``) starts one ``agos human`` process for the
roles a person plays, instead of ``agos agent`` processes, and prints the page's address;
``--decision-timeout 2h`` gives the person that long per decision (docs/HUMAN.md).
"""

from __future__ import annotations

import re
from collections.abc import Callable

from rich.console import Console

from agos.agents.names import is_human
from agos.deploy.run.launcher import SERVER_START_S, Launcher, free_port, wait_listening
from agos.runtime import keys
from agos.runtime.episode_config import EpisodeConfig
from agos.runtime.schemas import Role
from agos.runtime.settings import AgosConfig

CONSOLE_PORT = 8765
"""Where ``agos human`` serves its page unless told (or the next free port, in ``agos eval``)."""
SPECTATOR_PORT = 8766
CONSOLE_NAMES = ("human", "human-uav", "human-ugv")
"""The names the consoles run under in ``agos eval``'s launcher (stopped with the agents)."""
_DURATION = re.compile(r"^\s*(\d+(?:\.\d+)?)\s*(h|m|min|s)?\s*$")
_UNIT_S = {"h": 3600.0, "m": 60.0, "min": 60.0, "s": 1.0, None: 1.0}


def parse_duration(text: str) -> float:
    """``90``, ``90s``, ``30m``, ``2h``, ``1.5h`` -> seconds; ValueError for anything else."""
    match = _DURATION.match(text.lower())
    if match is None or float(match.group(1)) <= 0:
        raise ValueError(f"{text!r}: give a positive duration such as 90, 90s, 30m or 2h")
    return float(match.group(1)) * _UNIT_S[match.group(2)]


def human_roles(policies: dict[str, str]) -> tuple[Role, ...]:
    """The roles a person plays in a run with these policies."""
    return tuple(r for r in keys.ROLES if is_human(policies[r]))


def start_console(launcher: Launcher, policies: dict[str, str], config: EpisodeConfig, console: Console, *,
                  settings: Callable[[Role], AgosConfig], secured: bool) -> tuple[Role, ...] | None:
    """Start ``agos human`` for the roles a person plays (none: nothing started) and say where the
    page is: one console for both roles, or, on a ``secured`` bus, one per role, each with its role's
    certificate. ``settings(role)``: the settings of the console of ``role`` (deploy/run/local.py).
    Returns those roles, or None when a page did not come up."""
    roles = human_roles(policies)
    consoles = [(f"human-{r}", (r,)) for r in roles] if secured else [("human", roles)] if roles else []
    for name, played in consoles:
        port = free_port(CONSOLE_PORT)
        which = "both" if len(played) == 2 else played[0]
        launcher.start(name, ["human", "--role", which, "--port", str(port)], settings(played[0]))
        if not wait_listening("127.0.0.1", port, SERVER_START_S):
            console.print(f"[red]the human console did not listen on port {port}; see {launcher.log_dir / (name + '.log')}")
            return None
        console.print(f"human console: http://127.0.0.1:{port}/ ({' and '.join(r.upper() for r in played)}; each decision "
                      f"waits up to {config.decision_timeout_s:.0f} s, then the world applies WAIT"
                      + ("; give --decision-timeout 2h for longer" if config.decision_timeout_s <= 60 else "") + ")",
                      highlight=False, soft_wrap=True)
    return roles

