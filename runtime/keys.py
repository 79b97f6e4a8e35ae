"""The zenoh key space of agos, built in one place (a contract: docs/ARCHITECTURE.md §2).

No other module writes a key literal: every publisher, subscriber, queryable and liveliness
token asks this module for its key, so the layout can be read (and changed) here alone.

Layout::

    agos/<run>/ctl/manifest                  run description and status
    agos/<run>/ctl/jobs                      queryable: claim the next episode
    agos/<run>/ep/<ep>/obs/<role>            world -> agent observation
    agos/<run>/ep/<ep>/act/<role>            agent -> world action
    agos/<run>/ep/<ep>/coord/truth           authoritative coordination state
    agos/<run>/ep/<ep>/coord/view/<role>     coordination state as <role> received it
    agos/<run>/ep/<ep>/msg/<from>/<to>       inter-agent messages, as delivered
    agos/<run>/ep/<ep>/events                step records
    agos/<run>/ep/<ep>/result                the episode record
    agos/<run>/ep/<ep>/ack                   evaluator -> world: the record is stored
    agos/<run>/ep/<ep>/live/<worker>         liveliness: the episode runs on <worker> (agents subscribe to it)
    agos/<run>/ep/<ep>/ready/<role>/<agent>  liveliness: <agent> has subscribed to the episode's obs/<role>
    agos/<run>/live/<kind>/<id>              liveliness tokens
    agos/<run>/viz/<ep>/events               visualisation (lossy): episode start, step records
    agos/<run>/viz/<ep>/coord                visualisation (lossy): coordination truth
    agos/<run>/viz/<ep>/frame/<role>         visualisation (lossy): a small JPEG of each of the role's views
    agos/<run>/viz/<ep>/spec                 visualisation (lossy): the episode spec (region, target), at its start
    agos/<run>/viz/<ep>/result               visualisation (reliable): a copy of the episode record, at its end
    agos/<run>/viz/<ep>/full/<role>          visualisation (lossy): the role's views at full resolution, made
                                             only while someone subscribes there (``agos record --full``)
    agos/assets/<sha256>                     queryable: frozen town assets
    agos/routers/<zid>                       liveliness: a router agos started is up (``agos health router``)

Everything under ``viz/`` is published with congestion control DROP (runtime/bus.py): observers
subscribe there, so a slow one loses frames instead of slowing the world.
"""

from __future__ import annotations

import functools
import re
from typing import Literal

ROOT = "agos"
Role = Literal["uav", "ugv"]
ROLES: tuple[Role, Role] = ("uav", "ugv")
LiveKind = Literal["world", "agent", "evaluator", "orchestrator"]

# A chunk is one key segment: no '/', no zenoh wildcards or reserved characters. Ids are also
# directory and file names (runs/<run>/...): a chunk starts with a letter, digit or '_', so '.',
# '..' and option-like '-x' are refused, and is at most 128 characters.
_CHUNK = re.compile(r"^[A-Za-z0-9_][A-Za-z0-9_.\-]{0,127}$")


def check_chunk(value: str, *, what: str) -> str:
    """Return ``value`` if it is a legal single key segment, else raise ``ValueError``."""
    if not _CHUNK.fullmatch(value):
        raise ValueError(
            f"{what} {value!r} is not a valid name: letters, digits, '_', '-' and '.', starting with a letter, "
            "digit or '_', at most 128 characters"
        )
    return value


@functools.lru_cache(maxsize=4096)  # asked for on every decision; a bad id raises (not cached)
def _run(run: str) -> str:
    return f"{ROOT}/{run if run == '*' else check_chunk(run, what='run id')}"


@functools.lru_cache(maxsize=4096)
def _ep(run: str, episode: str) -> str:
    ep = episode if episode == "*" else check_chunk(episode, what="episode id")
    return f"{_run(run)}/ep/{ep}"


def episode_prefix(run: str, episode: str) -> str:
    """What every key of one episode starts with (to forget its publishers when it is over)."""
    return f"{_ep(run, episode)}/"


def manifest(run: str) -> str:
    return f"{_run(run)}/ctl/manifest"


def jobs(run: str) -> str:
    return f"{_run(run)}/ctl/jobs"


def obs(run: str, episode: str, role: str) -> str:
    return f"{_ep(run, episode)}/obs/{role}"


def act(run: str, episode: str, role: str) -> str:
    return f"{_ep(run, episode)}/act/{role}"


def coord_truth(run: str, episode: str) -> str:
    return f"{_ep(run, episode)}/coord/truth"


def coord_view(run: str, episode: str, role: str) -> str:
    return f"{_ep(run, episode)}/coord/view/{role}"


def message(run: str, episode: str, sender: str, receiver: str) -> str:
    return f"{_ep(run, episode)}/msg/{sender}/{receiver}"


def events(run: str, episode: str) -> str:
    return f"{_ep(run, episode)}/events"


def result(run: str, episode: str) -> str:
    return f"{_ep(run, episode)}/result"


def lease(run: str, episode: str) -> str:
    """Who holds the episode's current lease (orchestrator -> evaluator)."""
    return f"{_ep(run, episode)}/lease"


def result_ack(run: str, episode: str) -> str:
    return f"{_ep(run, episode)}/ack"


def episode_live(run: str, episode: str, worker: str) -> str:
    """The liveliness token a world declares while it runs ``episode``: agent services subscribe to
    that episode's observation key exactly while one exists (agents/service.py)."""
    return f"{_ep(run, episode)}/live/{worker if worker == '*' else check_chunk(worker, what='worker id')}"


def episode_ready(run: str, episode: str, role: str, agent: str) -> str:
    """The liveliness token an agent service declares once it has subscribed to ``episode``'s
    observations for ``role``: what the world waits for before the first one (any subscriber, an
    observer of ``agos/**`` for one, would not do)."""
    return f"{_ep(run, episode)}/ready/{role}/{agent if agent == '*' else check_chunk(agent, what='agent id')}"


def live(run: str, kind: LiveKind, ident: str) -> str:
    return f"{_run(run)}/live/{kind}/{ident if ident == '*' else check_chunk(ident, what='id')}"


def live_all(run: str = "*") -> str:
    """Every liveliness token of a run's processes (of all runs by default)."""
    return f"{_run(run)}/live/**"


def router_live(ident: str) -> str:
    """The liveliness token ``agos router`` declares in its own session (not under a run: one router
    serves every run)."""
    return f"{ROOT}/routers/{ident if ident == '*' else check_chunk(ident, what='router id')}"


def _viz(run: str, episode: str) -> str:
    return f"{_run(run)}/viz/{episode if episode == '*' else check_chunk(episode, what='episode id')}"


def viz_events(run: str, episode: str) -> str:
    return f"{_viz(run, episode)}/events"


def viz_coord(run: str, episode: str) -> str:
    return f"{_viz(run, episode)}/coord"


def viz_frame(run: str, episode: str, role: str) -> str:
    return f"{_viz(run, episode)}/frame/{role}"


def viz_spec(run: str, episode: str) -> str:
    return f"{_viz(run, episode)}/spec"


def viz_result(run: str, episode: str) -> str:
    return f"{_viz(run, episode)}/result"


def viz_full(run: str, episode: str, role: str) -> str:
    """Full-resolution views: the world makes them only while something subscribes to this key."""
    return f"{_viz(run, episode)}/full/{role}"


def viz_light(run: str = "*", *, full: bool = False) -> tuple[str, ...]:
    """The visualisation stream with its thumbnails (``frame/*``) or, ``full``, with its full-resolution
    frames (``full/*``) instead: what ``agos watch`` and ``agos record [--full]`` subscribe to.
    (``viz_all`` matches both, and a subscriber on ``full/<role>`` makes every world send them.)"""
    frames = viz_full(run, "*", "*") if full else viz_frame(run, "*", "*")
    return (viz_events(run, "*"), viz_coord(run, "*"), frames, viz_spec(run, "*"), viz_result(run, "*"))


def viz_prefix(run: str, episode: str) -> str:
    """What every visualisation key of one episode starts with."""
    return f"{_viz(run, episode)}/"


def viz_all(run: str = "*") -> str:
    """The whole visualisation stream of a run (of all runs by default): what observers watch."""
    return f"{_run(run)}/viz/**"


def asset(sha256: str) -> str:
    return f"{ROOT}/assets/{sha256 if sha256 == '*' else check_chunk(sha256, what='asset hash')}"


def episode_of(key: str) -> str:
    """The episode id inside a key under ``agos/<run>/ep/<ep>/...``."""
    parts = key.split("/")
    if len(parts) < 4 or parts[0] != ROOT or parts[2] != "ep":
        raise ValueError(f"key {key!r} is not an episode key")
    return parts[3]


def run_of(key: str) -> str:
    """The run id of any key under ``agos/<run>/...``."""
    parts = key.split("/")
    if len(parts) < 3 or parts[0] != ROOT or parts[1] == "assets":
        raise ValueError(f"key {key!r} is not an agos key under a run")
    return parts[1]
