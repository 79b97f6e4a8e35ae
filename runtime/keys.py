"""The zenoh key space of agos, built in one place (a contract: docs/ARCHITECTURE.md §2).

No other module writes a key literal: every publisher, subscriber, queryable and liveliness
token asks this module for its key, so the layout can be read (and changed) here alone; and none
takes a key apart by position: it asks :func:`parse_slot`, :func:`ready_of`, :func:`live_of`,
:func:`asset_of`, :func:`run_of` or :func:`leaf` for the part it needs.

The key space is bounded: no key names an episode. A router keeps a node in its routing tree for
every key a run ever used, and routes a sample on a key without a node of its own by scanning its
siblings (docs/ARCHITECTURE.md §2, "Why no key names an episode"), so keys that named episodes
made the router's work per episode grow with every episode the run had played. Keys name a
process instead (a world worker's *slot*: its worker id), and the episode id and lease attempt
travel in every payload; a receiver drops what is not its slot's current episode and attempt.

Layout::

    agos/<run>/ctl/manifest                      run description and status
    agos/<run>/ctl/jobs                          queryable: claim the next episode
    agos/<run>/ctl/lease                         orchestrator -> evaluator: who holds which episode
    agos/<run>/slot/<worker>/live                liveliness: <worker> serves this slot (agents subscribe to it)
    agos/<run>/slot/<worker>/ready/<role>/<agent>  liveliness: <agent> has subscribed to the slot's obs/<role>
    agos/<run>/slot/<worker>/obs/<role>          world -> agent observation
    agos/<run>/slot/<worker>/act/<role>          agent -> world action
    agos/<run>/slot/<worker>/coord/truth         authoritative coordination state
    agos/<run>/slot/<worker>/coord/view/<role>   coordination state as <role> received it
    agos/<run>/slot/<worker>/msg/<from>/<to>     inter-agent messages, as delivered
    agos/<run>/slot/<worker>/events              episode starts and step records
    agos/<run>/slot/<worker>/result              the episode record (world, or the orchestrator's failure record)
    agos/<run>/slot/<worker>/ack                 evaluator -> world, orchestrator: the record is stored
    agos/<run>/live/<kind>/<id>                  liveliness tokens
    agos/<run>/viz/<worker>/events               visualisation (lossy): episode start, step records
    agos/<run>/viz/<worker>/coord                visualisation (lossy): coordination truth
    agos/<run>/viz/<worker>/frame/<role>         visualisation (lossy): a small JPEG of each of the role's views
    agos/<run>/viz/<worker>/spec                 visualisation (lossy): the episode spec (region, target), at its start
    agos/<run>/viz/<worker>/result               visualisation (reliable): a copy of the episode record, at its end
    agos/<run>/viz/<worker>/full/<role>          visualisation (lossy): the role's views at full resolution, made
                                                 only while someone subscribes there (``agos record --full``)
    agos/assets/<sha256>                         queryable: frozen town assets
    agos/routers/<zid>                           liveliness: a router agos started is up (``agos health router``)

Everything under ``viz/`` is published with congestion control DROP (runtime/bus.py): observers
subscribe there, so a slow one loses frames instead of slowing the world. Every payload on a slot
or viz key names its episode (``episode_id``): a viewer follows one episode by that field.
"""

from __future__ import annotations

import functools
import re
from typing import Literal, NamedTuple

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
def _slot(run: str, worker: str) -> str:
    return f"{_run(run)}/slot/{worker if worker == '*' else check_chunk(worker, what='worker id')}"


def _name(ident: str, what: str) -> str:
    return ident if ident == "*" else check_chunk(ident, what=what)


def manifest(run: str) -> str:
    return f"{_run(run)}/ctl/manifest"


def jobs(run: str) -> str:
    return f"{_run(run)}/ctl/jobs"


def lease(run: str) -> str:
    """Who holds which episode's current lease (orchestrator -> evaluator; the episode is in the payload)."""
    return f"{_run(run)}/ctl/lease"


def slot_prefix(run: str, worker: str) -> str:
    """What every key of one world worker's slot starts with (to forget its publishers when it is gone)."""
    return f"{_slot(run, worker)}/"


def slot_live(run: str, worker: str) -> str:
    """The liveliness token a world worker (or ``agos check agent``) declares for its session: agent
    services subscribe to the slot's observation key exactly while one exists (agents/agent_service.py)."""
    return f"{_slot(run, worker)}/live"


def slot_ready(run: str, worker: str, role: str, agent: str) -> str:
    """The liveliness token an agent service declares once it has subscribed to ``worker``'s
    observations for ``role``: what the world waits for before an episode's first observation (any
    subscriber, an observer of ``agos/**`` for one, would not do)."""
    return f"{_slot(run, worker)}/ready/{role}/{_name(agent, 'agent id')}"


def obs(run: str, worker: str, role: str) -> str:
    return f"{_slot(run, worker)}/obs/{role}"


def act(run: str, worker: str, role: str) -> str:
    return f"{_slot(run, worker)}/act/{role}"


def coord_truth(run: str, worker: str) -> str:
    return f"{_slot(run, worker)}/coord/truth"


def coord_view(run: str, worker: str, role: str) -> str:
    return f"{_slot(run, worker)}/coord/view/{role}"


def message(run: str, worker: str, sender: str, receiver: str) -> str:
    return f"{_slot(run, worker)}/msg/{sender}/{receiver}"


def events(run: str, worker: str) -> str:
    return f"{_slot(run, worker)}/events"


def result(run: str, worker: str) -> str:
    """Records of the episodes leased to ``worker``: its own, and the orchestrator's failure records
    for them (``worker`` is the record's ``worker_id``)."""
    return f"{_slot(run, worker)}/result"


def result_ack(run: str, worker: str) -> str:
    return f"{_slot(run, worker)}/ack"


def live(run: str, kind: LiveKind, ident: str) -> str:
    return f"{_run(run)}/live/{kind}/{_name(ident, 'id')}"


def live_all(run: str = "*") -> str:
    """Every liveliness token of a run's processes (of all runs by default)."""
    return f"{_run(run)}/live/**"


def router_live(ident: str) -> str:
    """The liveliness token ``agos router`` declares in its own session (not under a run: one router
    serves every run)."""
    return f"{ROOT}/routers/{_name(ident, 'router id')}"


def _viz(run: str, worker: str) -> str:
    return f"{_run(run)}/viz/{_name(worker, 'worker id')}"


def viz_events(run: str, worker: str) -> str:
    return f"{_viz(run, worker)}/events"


def viz_coord(run: str, worker: str) -> str:
    return f"{_viz(run, worker)}/coord"


def viz_frame(run: str, worker: str, role: str) -> str:
    return f"{_viz(run, worker)}/frame/{role}"


def viz_spec(run: str, worker: str) -> str:
    return f"{_viz(run, worker)}/spec"


def viz_result(run: str, worker: str) -> str:
    return f"{_viz(run, worker)}/result"


def viz_full(run: str, worker: str, role: str) -> str:
    """Full-resolution views: the world makes them only while something subscribes to this key."""
    return f"{_viz(run, worker)}/full/{role}"


def viz_light(run: str = "*", *, full: bool = False) -> tuple[str, ...]:
    """The visualisation stream with its thumbnails (``frame/*``) or, ``full``, with its full-resolution
    frames (``full/*``) instead: what ``agos watch`` and ``agos record [--full]`` subscribe to.
    (``viz_all`` matches both, and a subscriber on ``full/<role>`` makes every world send them.)"""
    frames = viz_full(run, "*", "*") if full else viz_frame(run, "*", "*")
    return (viz_events(run, "*"), viz_coord(run, "*"), frames, viz_spec(run, "*"), viz_result(run, "*"))


def viz_all(run: str = "*") -> str:
    """The whole visualisation stream of a run (of all runs by default): what observers watch."""
    return f"{_run(run)}/viz/**"


def asset(sha256: str) -> str:
    return f"{ROOT}/assets/{sha256 if sha256 == '*' else check_chunk(sha256, what='asset hash')}"


class SlotKey(NamedTuple):
    """A key under ``agos/<run>/slot/<worker>/...`` or ``agos/<run>/viz/<worker>/...``, read back."""

    run: str
    worker: str
    kind: str
    """Its first part after ``<worker>/``: ``obs``, ``act``, ``coord``, ``msg``, ``events``, ``result``,
    ``ack``, ``live``, ``ready`` (slot); ``events``, ``coord``, ``frame``, ``full``, ``spec``, ``result`` (viz)."""
    args: tuple[str, ...]
    """The parts after the kind: ``(role,)`` of obs, act, frame and full; ``("truth",)`` or ``("view", role)``
    of a slot's coord; ``(sender, receiver)`` of msg; ``(role, agent)`` of ready; none for the others."""
    viz: bool
    """Under ``viz/`` (the visualisation stream), not ``slot/``."""


def parse_slot(key: str) -> SlotKey:
    """The parts of a slot or viz key; ``ValueError`` for any other key."""
    parts = key.split("/")
    if len(parts) < 5 or parts[0] != ROOT or parts[2] not in ("slot", "viz"):
        raise ValueError(f"key {key!r} is not a slot key")
    return SlotKey(parts[1], parts[3], parts[4], tuple(parts[5:]), parts[2] == "viz")


def slot_of(key: str) -> str:
    """The worker id of a key under ``agos/<run>/slot/<worker>/...`` or ``agos/<run>/viz/<worker>/...``."""
    return parse_slot(key).worker


def kind_of(key: str) -> str:
    """What a slot or viz key carries: its part after ``<worker>/`` (``obs/uav``, ``frame/ugv``, ``result``)."""
    parsed = parse_slot(key)
    return "/".join((parsed.kind, *parsed.args))


class Ready(NamedTuple):
    role: str
    agent: str


def ready_of(key: str) -> Ready:
    """The role and agent of a ready token (:func:`slot_ready`); ``ValueError`` for any other key."""
    parsed = parse_slot(key)
    if parsed.viz or parsed.kind != "ready" or len(parsed.args) != 2:
        raise ValueError(f"key {key!r} is not a ready token")
    return Ready(*parsed.args)


class LiveToken(NamedTuple):
    run: str
    kind: str
    ident: str


def live_of(key: str) -> LiveToken:
    """The run, kind and id of a process's liveliness token (:func:`live`); ``ValueError`` for any other key."""
    parts = key.split("/")
    if len(parts) != 5 or parts[0] != ROOT or parts[2] != "live":
        raise ValueError(f"key {key!r} is not a liveliness token of a run's process")
    return LiveToken(parts[1], parts[3], parts[4])


def asset_of(key: str) -> str:
    """The hash an asset key (:func:`asset`) names, checked as :func:`asset` checks it; ``ValueError`` for
    any other key."""
    parts = key.split("/")
    if len(parts) != 3 or parts[0] != ROOT or parts[1] != "assets":
        raise ValueError(f"key {key!r} is not an asset key")
    return check_chunk(parts[2], what="asset hash")


def leaf(key: str) -> str:
    """A key's last segment: what a ctl or slot key carries (``manifest``, ``lease``, ``result``,
    ``events``), the role of ``obs/<role>``."""
    return key.rsplit("/", 1)[-1]


def run_of(key: str) -> str:
    """The run id of any key under ``agos/<run>/...``."""
    parts = key.split("/")
    if len(parts) < 3 or parts[0] != ROOT or parts[1] == "assets":
        raise ValueError(f"key {key!r} is not an agos key under a run")
    return parts[1]
