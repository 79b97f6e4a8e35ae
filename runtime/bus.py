"""The transport: :class:`Bus`, the few operations agos needs (the protocol every component takes),
:class:`ZenohBus`, a zenoh session that has them, and :class:`MemoryBus`, an in-memory fake.

Every process is a client of a router (multicast scouting off unless asked). Two kinds of QoS:

* ``publish``: control traffic (observations, actions, coordination, events, results, acks),
  reliable with congestion control BLOCK: DROP loses messages under load even over TCP
  (ZENOH_NOTES.md), and none of these may be lost.
* ``publish_viz``: the visualisation stream (``agos/<run>/viz/...``), congestion control DROP,
  express (not batched), priority DATA_LOW, best effort. A router whose queue towards a slow observer is
  full drops these instead of waiting, so an observer can never slow the world; control traffic
  goes first. ``watched`` says whether anyone subscribes, so costly samples (frames) are made
  only for someone.

Subscriber callbacks only hand ``(key, bytes)`` to a queue; all work happens in the caller's
thread (a slow callback stalls every other key of the session).
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import queue
import random
import re
import threading
import time
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Generic, Protocol, TypeVar

import zenoh

from agos.runtime import keys
from agos.runtime.codec import encode
from agos.runtime.process import Interrupted, stop_requested
from agos.runtime.settings import ZenohSettings

log = logging.getLogger(__name__)

T = TypeVar("T")


@dataclass(slots=True)  # not frozen: a frozen dataclass costs three times as much to build, per received sample
class Sample:
    key: str
    payload: bytes


class Query(Protocol):
    """A query a :meth:`Bus.serve` queryable received: answer it with :meth:`reply` (from any thread)."""

    key: str
    payload: bytes

    def reply(self, payload: bytes) -> None: ...


class _Queue(Generic[T]):
    """A thread-safe queue (what subscriber callbacks hand their items to)."""

    def __init__(self) -> None:
        self._queue: queue.Queue[T] = queue.Queue()

    def put(self, item: T) -> None:
        self._queue.put(item)

    def get(self, timeout_s: float | None = None) -> T | None:
        try:
            return self._queue.get(timeout=timeout_s)
        except queue.Empty:
            return None

    def drain(self) -> list[T]:
        out = []
        while True:
            try:
                out.append(self._queue.get_nowait())
            except queue.Empty:
                return out


class Inbox(_Queue[Sample]):
    """A thread-safe queue of samples from one or more subscriptions."""


class QueryInbox(_Queue[Query]):
    """A thread-safe queue of the queries a queryable received (:meth:`Bus.serve`)."""


class SampleSink(Protocol):
    """Where a subscription hands its samples: an :class:`Inbox`, or anything with ``put``."""

    def put(self, sample: Sample) -> None: ...


class Bus(Protocol):
    """The transport every component talks through: :class:`ZenohBus` in a process, :class:`MemoryBus`
    in unit tests (STYLE.md item 9). Keys come from runtime/keys.py; a ``message`` is a wire message
    (encoded with runtime/codec.py) or bytes sent as they are. Callbacks and inboxes are fed from the
    transport's threads; every method may be called from any thread."""

    def publish(self, key: str, message: Any, *, once: bool = False) -> None:
        """Control traffic on ``key``: reliable, never dropped (zenoh: congestion control BLOCK, so
        it may wait for a slow receiver). Every subscription matching ``key`` gets the sample,
        once, in publishing order. ``once``: a key this process publishes on once or a few times
        (an episode's record, its ack, its lease notice), sent without declaring a publisher for it:
        zenoh keeps what a declared publisher's key made in the session for the session's life, even
        after :meth:`forget`, and every sample the session receives then costs time in proportion
        (1.6 ms instead of 9 us with 6,000 such keys: bench/bench_control_plane.py)."""
        ...

    def publish_viz(self, key: str, message: Any) -> None:
        """Visualisation traffic on ``key``: best effort, never waits (zenoh: DROP, express, low
        priority); a sample nobody can take now is lost."""
        ...

    def watched(self, key: str) -> bool:
        """Whether anyone subscribes to ``key`` now, cheaply (asked every decision), so costly
        visualisation samples are made only for someone. May say False for a round trip after the
        key's first use."""
        ...

    def forget(self, key_prefix: str) -> None:
        """Release what publishing kept per key under ``key_prefix`` (publishers, matching
        listeners: an episode that is over). Subscriptions and tokens are untouched; publishing
        on such a key again works as the first time did."""
        ...

    def subscribe(self, key_expr: str, inbox: SampleSink) -> Any:
        """Hand every sample published under ``key_expr`` (``*``: one chunk, ``**``: any number)
        to ``inbox.put`` as a :class:`Sample`, from the transport's thread, until
        :meth:`unsubscribe`. Returns the handle."""
        ...

    def subscribe_payloads(self, key_expr: str, callback: Callable[[bytes], None]) -> Any:
        """As :meth:`subscribe`, but call ``callback(payload)`` with the payload alone (a hot path
        needing neither the key nor a queue). Returns a handle for :meth:`unsubscribe`."""
        ...

    def unsubscribe(self, handle: Any) -> None:
        """End a subscription (:meth:`subscribe`, :meth:`subscribe_payloads`,
        :meth:`watch_liveliness`); an unknown or already ended handle is ignored."""
        ...

    def serve(self, key_expr: str) -> QueryInbox:
        """Declare a queryable on ``key_expr`` for as long as the bus is open; each query to a key
        it matches is queued in the returned inbox for the caller to answer with
        ``query.reply(bytes)`` (never inside a transport callback)."""
        ...

    def request(self, key: str, message: Any, timeout_s: float) -> list[bytes]:
        """Query ``key`` and return every reply's payload (all queryables' answers, none merged
        away), waiting at most ``timeout_s``; no queryable, or none answering in time: fewer or none."""
        ...

    def wait_for_subscriber(self, key: str, timeout_s: float) -> bool:
        """Wait until some subscription matches ``key`` (the start-up race guard); False if none
        did within ``timeout_s`` (0: answer at once)."""
        ...

    def declare_token(self, key: str) -> Any:
        """A liveliness token on ``key`` until :meth:`undeclare_token` or the bus closes (or the
        process dies); returns its handle. Two tokens on one key are two handles."""
        ...

    def undeclare_token(self, handle: Any) -> None:
        """Withdraw a token of :meth:`declare_token`; an unknown or withdrawn handle is ignored."""
        ...

    def watch_liveliness(self, key_expr: str, inbox: SampleSink) -> Any:
        """Hand ``Sample(key, b"+")`` to ``inbox`` when a token's key under ``key_expr`` becomes
        alive (also at once for those alive now) and ``Sample(key, b"-")`` when its last token
        goes. Returns a handle for :meth:`unsubscribe`."""
        ...

    def alive_tokens(self, key_expr: str, timeout_s: float = 1.0) -> list[str]:
        """The keys under ``key_expr`` with a token alive now, sorted, each once."""
        ...

    def close(self) -> None:
        """End every subscription, queryable and token of this bus and release the transport.
        Idempotent."""
        ...


VIZ_QUEUE_BATCHES = 16
"""zenoh TX queue of the visualisation priority (DATA_LOW), in 64 KiB batches: see :func:`zenoh_config`."""
ALIVE_TOKENS_ROOM = 1 << 20
"""Replies :meth:`ZenohBus.alive_tokens` can take (the channel grows as they come, up to this)."""
ROUTER_MAX_SESSIONS = 10_000
"""Client sessions one router accepts (zenoh's default, 1,000, is less than 1,000 world workers and the
services of their run; each costs the router about 0.1 MB: bench/bench_control_plane.py)."""


CONNECT_RETRY = {"period_init_ms": 1000, "period_max_ms": 1000, "period_increase_factor": 1.0}
"""How a session tries its routers again: every second, no back-off."""


def zenoh_config(*, mode: str = "client", connect: list[str] | None = None, listen: list[str] | None = None,
                 multicast_scouting: bool = False, connect_timeout_s: float = 10.0,
                 tls: dict[str, Any] | None = None, access_control: dict[str, Any] | None = None) -> zenoh.Config:
    """A zenoh config for agos processes (JSON5 inserts; no file needed). ``tls``: zenoh's
    ``transport/link/tls`` section (runtime/tls.py); ``access_control``: the router's rules
    (runtime/access_control.py)."""
    conf = zenoh.Config()
    conf.insert_json5("mode", json.dumps(mode))
    conf.insert_json5("scouting/multicast/enabled", json.dumps(multicast_scouting))
    if connect:
        conf.insert_json5("connect/endpoints", json.dumps(connect))
        # A client started before its router waits this long instead of failing at once. Given several
        # routers, zenoh (1.10) would retry the first until then and never try the others, so it tries
        # each once, in order, and open_session(retry_for_s=) tries the list again. A router keeps
        # trying its peers in the background (-1), also after losing one.
        client_ms = int(connect_timeout_s * 1000) if len(connect) == 1 else 0
        conf.insert_json5("connect/timeout_ms", json.dumps({"client": client_ms, "peer": -1, "router": -1}))
        # A session that lost its router tries again every second (zenoh's default backs off to 1, 3, 7,
        # 11 s): back within about a second of the router, inside the orchestrator's reconnection grace
        # ([run] reconnect_grace_s, 10 s) even for a router down 8 s.
        conf.insert_json5("connect/retry", json.dumps(CONNECT_RETRY))
    if listen:
        conf.insert_json5("listen/endpoints", json.dumps(listen))
    # The visualisation stream (DATA_LOW, DROP) comes in bursts: six full-resolution views at a
    # STOP_OBSERVE are about 0.5 MB, and zenoh's default of 2 batches (128 KiB) a priority dropped one
    # now and then on an idle loopback. 16 batches (zenoh's maximum; allocated lazily, per link) hold
    # a burst; a subscriber that falls behind still loses samples instead of slowing anyone.
    conf.insert_json5("transport/link/tx/queue/size/data_low", json.dumps(VIZ_QUEUE_BATCHES))
    # agos sends plain bytes, never zenoh shared-memory buffers, so the shared-memory transport only
    # costs: a router on the clients' host refused every session past about 350 ("No available SHM
    # counters"), and 1,000 world workers need more (bench/bench_control_plane.py).
    conf.insert_json5("transport/shared_memory/enabled", "false")
    if mode == "router":
        conf.insert_json5("transport/unicast/max_sessions", json.dumps(ROUTER_MAX_SESSIONS))
        # Read-only admin space (@/<zid>/router/...): the sessions and the key expressions declared, for
        # operators and for bench_control_plane.py's key census. On the secured bus no identity is
        # granted @/**, so only plain-TCP clients (which may say anything anyway) can read it.
        conf.insert_json5("adminspace", json.dumps({"enabled": True, "permissions": {"read": True, "write": False}}))
    if tls is not None:
        conf.insert_json5("transport/link/tls", json.dumps(tls))
    if access_control is not None:
        conf.insert_json5("access_control", json.dumps(access_control))
    return conf


def session_config(z: ZenohSettings, *, mode: str = "client", access_control: dict[str, Any] | None = None) -> zenoh.Config:
    """The zenoh config of a process from its ``[zenoh]`` settings: a client of ``z.connect`` (the
    nearest router first), or the router on ``z.listen`` connecting to its ``z.peers``; TLS (mutual,
    with this process's credentials) when the endpoints say ``tls/`` (the settings allow all or none)."""
    from agos.runtime.tls import tls_section

    router = mode == "router"
    endpoints = [z.listen, *z.peers] if router else z.connect_endpoints
    tls = tls_section(z, listening=router) if endpoints[0].startswith("tls/") else None
    return zenoh_config(mode=mode, connect=z.peers if router else z.connect_endpoints,
                        listen=[z.listen] if router else None, multicast_scouting=z.multicast_scouting,
                        connect_timeout_s=z.connect_timeout_s, tls=tls, access_control=access_control)


def connect_retry_s(z: ZenohSettings) -> float:
    """How long :func:`open_session` itself tries again for a client of ``z``: ``connect_timeout_s`` with
    several routers (zenoh tries each once: :func:`zenoh_config`), 0 with one (zenoh waits for it)."""
    return z.connect_timeout_s if len(z.connect_endpoints) > 1 else 0.0


class _ZenohQuery:
    def __init__(self, query: zenoh.Query) -> None:
        self._query = query
        self.key = str(query.key_expr)
        self.payload = query.payload.to_bytes() if query.payload is not None else b""

    def reply(self, payload: bytes) -> None:
        with contextlib.suppress(zenoh.ZError):  # the session it came through closed (the bus moved home): no answer
            self._query.reply(self.key, payload)


class _MatchingFlag:
    """Whether a publisher has matching subscribers, kept current by a matching listener."""

    def __init__(self, publisher: zenoh.Publisher) -> None:
        self._listener = publisher.declare_matching_listener(self._update)
        # After declaring: no change is missed. zenoh's stub types matching_status as bool; at run
        # time (zenoh-python 1.x) it is a MatchingStatus.
        self.matching = publisher.matching_status.matching  # type: ignore[attr-defined]

    def _update(self, status: zenoh.MatchingStatus) -> None:
        self.matching = status.matching

    def close(self) -> None:
        self._listener.undeclare()


class RouterUnreachable(RuntimeError):
    """No session: the router is not there, the port is wrong, or (TLS) the credentials were refused."""


OPEN_POLL_S = 0.1
"""How often a process waiting for its zenoh session looks whether it was asked to stop."""
OPEN_RETRY_S = 0.25
"""Pause between two tries of a list of routers none of which answered (:func:`open_session`)."""


def _open_once(config: zenoh.Config) -> zenoh.Session | BaseException:
    """One ``zenoh.open`` on a thread of its own while this one looks for a stop request."""
    outcome: list[zenoh.Session | BaseException] = []

    def connect() -> None:
        try:
            outcome.append(zenoh.open(config))
        except BaseException as exc:  # handed to the waiting thread
            outcome.append(exc)

    thread = threading.Thread(target=connect, name="zenoh-open", daemon=True)
    thread.start()
    while thread.is_alive():
        thread.join(OPEN_POLL_S)
        if stop_requested():
            raise Interrupted("stopped while connecting to the zenoh router")
    return outcome[0]


def open_session(config: zenoh.Config, *, retry_for_s: float = 0.0) -> zenoh.Session:
    """``zenoh.open``, failing with one line that names the endpoint and what to check.

    The connection is made on a thread of its own while this one waits, so a stop signal during the
    wait (up to ``[zenoh] connect_timeout_s`` when no router answers) is heard at once: Ctrl-C raises
    ``KeyboardInterrupt`` here, a process with a stop flag (runtime/process.py) gets
    :class:`~agos.runtime.process.Interrupted`. A session that opens after that is left to the exit.
    ``retry_for_s``: try again every :data:`OPEN_RETRY_S` until then while no router answers (a list
    of routers, which zenoh tries once each: :func:`connect_retry_s`)."""
    deadline = time.monotonic() + retry_for_s
    while True:
        outcome = _open_once(config)
        if isinstance(outcome, zenoh.Session):
            return outcome
        if not isinstance(outcome, zenoh.ZError) or time.monotonic() + OPEN_RETRY_S > deadline:
            break
        again_at = time.monotonic() + OPEN_RETRY_S
        while time.monotonic() < again_at:
            time.sleep(OPEN_POLL_S)
            if stop_requested():
                raise Interrupted("stopped while connecting to the zenoh router")
    exc = outcome
    if isinstance(exc, zenoh.ZError):
        try:
            endpoints = ", ".join(json.loads(config.get_json("connect/endpoints"))) or "?"
        except Exception:  # the config has no connect endpoints (a router): say what zenoh said
            endpoints = "?"
        tls = " (TLS: are the CA, certificate and key the router's CA signed?)" if "tls/" in endpoints else ""
        raise RouterUnreachable(
            f"cannot reach the zenoh router at {endpoints}: is `agos router` running there and is the port "
            f"right? (--connect or AGOS_ZENOH__CONNECT){tls} [{str(exc).split(' at ')[0]}]") from None
    raise exc


FAILBACK_POLL_S = 1.0
"""How often a process given several routers looks whether it is on its own (the first) router and,
away from it, whether that router is back: at home a look costs a few microseconds; away, a session
opened to it, refused in 0.2 ms of CPU while it is down (:meth:`ZenohBus._back_home`)."""
FAILBACK_OVERLAP_S = 0.25
"""Moving home, how long the new session holds every declaration before it takes over (they reach the
routers of the mesh meanwhile), and how long the old one stays open after (what it had on the way arrives)."""
FAILBACK_HANDOVER_S = 2.0
"""Moving home, how long the old session stays open at most for the new one to hear each source of
samples it delivered (one that went quiet never is), and the move lasts at most after for the new one
to catch up with what was delivered (:class:`_Move`)."""


def _client_endpoints(config: zenoh.Config) -> list[str]:
    """The routers a client config names, in order ([] for a router or peer)."""
    try:
        mode, endpoints = json.loads(config.get_json("mode")), json.loads(config.get_json("connect/endpoints"))
    except Exception:  # no such setting
        return []
    return endpoints if mode == "client" and isinstance(endpoints, list) else []


class _Declared:
    """What :class:`ZenohBus` hands out as a handle (a subscription, liveliness watch, queryable or token):
    declared on the bus's session, and on the new one too while the bus moves home (:class:`_Move`),
    so the handle outlives the session it was first declared on. ``make(session, handle)`` declares it."""

    __slots__ = ("key", "make", "on")

    def __init__(self, make: Callable[[zenoh.Session, Any], Any], key: str | None = None) -> None:
        self.make = make
        self.on: list[tuple[zenoh.Session, Any]] = []  # (session, what zenoh declared there)
        self.key = key  # a token's key

    def attach(self, session: zenoh.Session) -> None:
        self.on.append((session, self.make(session, self)))

    def take(self, session: zenoh.Session | None = None) -> list[Any]:
        """What was declared on ``session`` (None: on every one), forgotten here for the caller to undeclare."""
        taken = [d for s, d in self.on if session is None or s is session]
        self.on = [(s, d) for s, d in self.on if not (session is None or s is session)]
        return taken


class _Watch(_Declared):
    """A liveliness watch, which keeps the keys it told alive: it tells each change once (also where
    zenoh says one twice, or both of a move's sessions see it), never the end of a key this process
    holds a token on (zenoh reports a remote token's end on such a key as the key's end), and after a
    move what changed meanwhile."""

    __slots__ = ("alive", "inbox", "key_expr", "lock", "own")

    def __init__(self, make: Callable[[zenoh.Session, Any], Any], key_expr: str, inbox: SampleSink,
                 own: Counter[str]) -> None:
        super().__init__(make)
        self.key_expr, self.inbox, self.own = key_expr, inbox, own
        self.alive: set[str] = set()
        self.lock = threading.Lock()

    def change(self, key: str, alive: bool) -> None:
        with self.lock:
            if alive == (key in self.alive) or (not alive and self.own[key] > 0):
                return
            if alive:
                self.alive.add(key)
            else:
                self.alive.discard(key)
            self.inbox.put(Sample(key, b"+" if alive else b"-"))


class _Move:
    """A bus moving from ``old`` (its session on another router) to ``new`` (on its own router), make
    before break: ``new`` declares everything first; at the switch it takes over publishing and
    liveliness (changes are told by the session active when they arrive; at the switch each watch is
    told how ``new`` sees its keys); ``old`` closes last. A query is answered by the session it
    reaches first, for those of :meth:`ZenohBus.request`, which names each; others by the active one.

    Samples are handed over source by source, a source being one subscription's samples from one
    router where they entered the mesh, known by the timestamp that router gives each (every zenoh
    router does by default: its id, and a time that only grows). ``old`` hands on a source's samples
    until, after the switch, ``new`` has heard one that ``old`` has delivered too; ``new`` holds what
    it hears of the source until then and hands on the rest after, so each sample is delivered once
    and in order whichever session hears it first (a move given up before the switch leaves ``old``
    as it was). This process's own puts, delivered without a timestamp by the session they went
    through, carry that session's id: the other drops their copies."""

    def __init__(self, old: zenoh.Session, new: zenoh.Session, lock: threading.RLock) -> None:
        self.old, self.new, self.active = old, new, old
        self.marks = {id(old): str(old.info.zid()).encode(), id(new): str(new.info.zid()).encode()}
        self.lock = lock
        self.latest: dict[tuple[_Declared, str], Any] = {}  # source -> the time of the last sample delivered
        self.new_heard: dict[tuple[_Declared, str], Any] = {}  # source -> the time of the last sample new heard
        self.from_old: set[tuple[_Declared, str]] = set()  # sources old delivered from
        self.handed: set[tuple[_Declared, str]] = set()  # sources new delivers now
        self.held: dict[tuple[_Declared, str], list[tuple[Any, zenoh.Sample, Callable[[zenoh.Sample], None]]]] = {}
        self.last_at: dict[tuple[_Declared, str], float] = {}  # source -> when a sample of it was last delivered
        self.views: dict[_Watch, set[str]] = {}  # the keys each watch on new sees alive
        self.asked: set[bytes] = set()  # the names of the queries taken

    def sample(self, handle: _Declared, session: zenoh.Session, sample: zenoh.Sample,
               deliver: Callable[[zenoh.Sample], None]) -> None:
        stamp = sample.timestamp
        if stamp is None:  # this process's own put, handed on by the session it went through alone
            with self.lock:
                deliver(sample)
            return
        other = self.marks[id(self.new if session is self.old else self.old)]
        if sample.attachment is not None and sample.attachment.to_bytes() == other:
            return  # a copy of this process's own put through the other session, which delivered it
        source, time_ = (handle, str(stamp.get_id())), stamp.get_time_as_ntp64()
        with self.lock:
            if session is self.old:
                if source not in self.handed:
                    self._deliver(source, time_, sample, deliver)
                    self.from_old.add(source)
                    held = self.held.get(source)
                    if held and self.active is self.new and not time_ < held[0][0]:
                        self._hand_over(source)  # old has caught up with new: new goes on
                return
            self.new_heard[source] = time_
            if source in self.handed:
                self._deliver(source, time_, sample, deliver)
            else:
                self.held.setdefault(source, []).append((time_, sample, deliver))
                latest = self.latest.get(source)
                if latest is not None and self.active is self.new and not time_ > latest:
                    self._hand_over(source)  # old delivered this one: new goes on

    def _deliver(self, source: tuple[_Declared, str], time_: Any, sample: zenoh.Sample,
                 deliver: Callable[[zenoh.Sample], None]) -> None:
        latest = self.latest.get(source)
        if (latest is None or time_ > latest) and source[0].on:
            self.latest[source], self.last_at[source] = time_, time.monotonic()
            deliver(sample)

    def _settled(self, source: tuple[_Declared, str], now: float) -> bool:
        """A source no longer of concern: its subscription ended, or nothing of it came for a while
        (nothing of it is on the way)."""
        return not source[0].on or now - self.last_at.get(source, 0.0) > FAILBACK_OVERLAP_S

    def _hand_over(self, source: tuple[_Declared, str]) -> None:
        self.handed.add(source)
        for time_, sample, deliver in self.held.pop(source, []):
            self._deliver(source, time_, sample, deliver)

    def handed_over(self) -> bool:
        """Whether new delivers every source old delivered from that is still sending."""
        with self.lock:
            now = time.monotonic()
            return all(source in self.handed or self._settled(source, now) for source in self.from_old)

    def old_closed(self) -> None:
        """Old is gone: new delivers every source, first what it holds."""
        with self.lock:
            for source in list(self.held):
                self._hand_over(source)
            self.from_old.clear()

    def caught_up(self) -> bool:
        """Whether new has heard, of every source, as far as was delivered: nothing it hears from now on
        was delivered already."""
        with self.lock:
            now = time.monotonic()
            return all((source in self.new_heard and not self.new_heard[source] < time_) or self._settled(source, now)
                       for source, time_ in self.latest.items())

    def query(self, session: zenoh.Session, query: zenoh.Query, inbox: QueryInbox) -> None:
        """A query is answered by the session it reaches first, known by the name :meth:`ZenohBus.request`
        attaches (one without, by the active session); the other lets it end without a reply."""
        name = None if query.attachment is None else query.attachment.to_bytes()
        with self.lock:
            if name is None:
                if session is self.active:
                    inbox.put(_ZenohQuery(query))
            elif name not in self.asked:
                self.asked.add(name)
                inbox.put(_ZenohQuery(query))

    def change(self, watch: _Watch, session: zenoh.Session, key: str, alive: bool) -> None:
        with self.lock:
            if session is self.new and self.active is self.old:
                view = self.views.setdefault(watch, set())
                if alive:
                    view.add(key)
                else:
                    view.discard(key)
            elif session is self.active:
                watch.change(key, alive)

    def switch(self, watches: list[_Watch], own: list[str]) -> None:
        """``new`` takes over publishing, queries and liveliness (its views complete: a liveliness query
        on it has been answered since its watches were declared); ``own``: the keys this process holds
        tokens on."""
        with self.lock:
            self.active = self.new
            for source, held in list(self.held.items()):
                latest = self.latest.get(source)
                if latest is not None and not latest < held[0][0]:  # old has caught up with new
                    self._hand_over(source)
            for watch in watches:
                view = self.views.get(watch, set()) | {key for key in own if _matches(watch.key_expr, key)}
                for key in sorted(view - watch.alive):
                    watch.change(key, True)
                for key in sorted(watch.alive - view):
                    watch.change(key, False)


def _on_a_thread_not_a_daemon(work: Callable[[], object]) -> None:
    """``work()`` on a thread of its own that is not a daemon, waited for. zenoh-python runs each Python
    callback on a thread it starts from the declaring thread, of that thread's kind: a daemon's (this
    bus's home thread's) die mid-call at the interpreter's exit, and the process aborts ("FATAL: exception
    not rethrown"), where others are joined."""
    failed: list[BaseException] = []

    def run() -> None:
        try:
            work()
        except BaseException as exc:  # raised again on the waiting thread
            failed.append(exc)

    thread = threading.Thread(target=run, name="zenoh-declare", daemon=False)
    thread.start()
    thread.join()
    if failed:
        raise failed[0]


class ZenohBus:
    """A real zenoh session (client of a router by default); a context manager that closes it.

    Given several routers (``[zenoh] connect``, the process's own first), zenoh moves the session to
    the next that answers when its router goes away, and leaves it there. So the bus looks every
    :data:`FAILBACK_POLL_S` whether it is away from its own router and that router is back and linked
    to the mesh again, and if so moves home, make before break (:class:`_Move`): a new session on its
    own router declares everything the bus declared (the handles it handed out stay valid), takes over
    publishing, and the old session closes. Tokens never vanish meanwhile; each sample reaches a
    subscription once, in order."""

    def __init__(self, config: zenoh.Config, *, retry_for_s: float = 0.0) -> None:
        """Open the session (:func:`open_session`: ``retry_for_s`` is its own)."""
        self.session = open_session(config, retry_for_s=retry_for_s)
        self._config = config
        self._publishers: dict[str, zenoh.Publisher] = {}
        self._watched: dict[str, _MatchingFlag] = {}
        self._keep: dict[_Declared, None] = {}
        self._own_tokens: Counter[str] = Counter()
        self._gets: Counter[int] = Counter()  # id(session) -> queries waiting on it
        self._move: _Move | None = None
        self._lock = threading.RLock()
        self._closed = False
        self._home_thread: threading.Thread | None = None
        self._stop_home = threading.Event()
        endpoints = _client_endpoints(config)
        if len(endpoints) > 1:
            self._home = endpoints[0]
            self._home_config = zenoh.Config.from_json5(str(config))
            self._home_config.insert_json5("connect/endpoints", json.dumps([self._home]))
            self._home_zid: str | None = None
            self._away_since: float | None = None
            self._home_thread = threading.Thread(target=self._home_loop, name="zenoh-home", daemon=True)
            self._home_thread.start()

    def __enter__(self) -> ZenohBus:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    @classmethod
    def connect(cls, endpoint: str, *, connect_timeout_s: float = 10.0) -> ZenohBus:
        return cls(zenoh_config(connect=[endpoint], connect_timeout_s=connect_timeout_s))

    @classmethod
    def from_settings(cls, z: ZenohSettings) -> ZenohBus:
        """A client session as the process's ``[zenoh]`` settings say (TLS included; with several
        routers, the first that answers, in their order, and back to the first when it can)."""
        return cls(session_config(z), retry_for_s=connect_retry_s(z))

    def _publisher(self, key: str, *, viz: bool = False) -> zenoh.Publisher:
        pub = self._publishers.get(key)  # the common case, without the lock
        if pub is not None:
            return pub
        with self._lock:
            pub = self._publishers.get(key)
            if pub is None:
                if viz:
                    pub = self.session.declare_publisher(
                        key, congestion_control=zenoh.CongestionControl.DROP, express=True,
                        priority=zenoh.Priority.DATA_LOW, reliability=zenoh.Reliability.BEST_EFFORT)
                else:
                    pub = self.session.declare_publisher(
                        key, congestion_control=zenoh.CongestionControl.BLOCK, reliability=zenoh.Reliability.RELIABLE)
                self._publishers[key] = pub
            return pub

    def _put(self, key: str, payload: bytes | bytearray, *, once: bool = False, viz: bool = False) -> None:
        session = self.session
        try:
            move = self._move
            if move is not None:
                self._put_moving(move, key, payload, once=once, viz=viz)
            elif once and key not in self._publishers:
                session.put(key, payload, congestion_control=zenoh.CongestionControl.BLOCK)
            else:
                self._publisher(key, viz=viz).put(payload)
        except zenoh.ZError:
            if session is self.session:
                raise
            self._put(key, payload, once=once, viz=viz)  # the bus moved home and closed the session it went to

    def _put_moving(self, move: _Move, key: str, payload: bytes | bytearray, *, once: bool, viz: bool) -> None:
        """A put while the bus moves home: through the active session, marked with its id (:class:`_Move`)."""
        with self._lock:  # the session and its publishers, as one
            session = self.session
            pub = None if once and key not in self._publishers else self._publisher(key, viz=viz)
        mark = move.marks[id(session)]
        if pub is None:
            session.put(key, payload, congestion_control=zenoh.CongestionControl.BLOCK, attachment=mark)
        else:
            pub.put(payload, attachment=mark)

    def publish(self, key: str, message: Any, *, once: bool = False) -> None:
        """Control traffic: reliable, congestion control BLOCK (never lost, may wait). ``once``: put
        from the session, no publisher declared (see :meth:`Bus.publish`)."""
        self._put(key, message if isinstance(message, (bytes, bytearray)) else encode(message), once=once)

    def watched(self, key: str) -> bool:
        """Whether anyone subscribes to the visualisation key ``key`` (known a round trip after the
        key's first use, so the first sample on a new key is not made). Asked every decision, so
        the answer is a flag a matching listener keeps current, not a query into zenoh."""
        flag = self._watched.get(key)
        if flag is None:
            with self._lock:  # one listener per key, even if two threads ask at once
                flag = self._watched.get(key)
                if flag is None:
                    flag = self._watched[key] = _MatchingFlag(self._publisher(key, viz=True))
        return flag.matching

    def publish_viz(self, key: str, message: Any) -> None:
        """Visualisation traffic: congestion control DROP, express, low priority, best effort.
        Never waits for a slow observer; a sample nobody can take is dropped."""
        self._put(key, message if isinstance(message, (bytes, bytearray)) else encode(message), viz=True)

    def forget(self, key_prefix: str) -> None:
        """Undeclare the publishers under a prefix (an episode that is over)."""
        with self._lock:
            for key in [k for k in self._watched if k.startswith(key_prefix)]:
                self._watched.pop(key).close()
            for key in [k for k in self._publishers if k.startswith(key_prefix)]:
                self._publishers.pop(key).undeclare()

    def _sessions(self) -> list[zenoh.Session]:
        """Where a new declaration goes: the session, or both while the bus moves and the old one is active."""
        move = self._move
        return [move.old, move.new] if move is not None and move.active is move.old else [self.session]

    def _declare(self, handle: _Declared) -> _Declared:
        with self._lock:
            for session in self._sessions():
                handle.attach(session)
            self._keep[handle] = None
            if handle.key is not None:
                self._own_tokens[handle.key] += 1
        return handle

    def _undeclare(self, handle: Any) -> None:
        with self._lock:
            if not isinstance(handle, _Declared) or self._keep.pop(handle, False) is False:
                return
            if handle.key is not None:
                self._own_tokens[handle.key] -= 1  # before zenoh says the key ended: see _Watch
            taken = handle.take()
        for declared in taken:
            with contextlib.suppress(Exception):
                declared.undeclare()

    def subscribe(self, key_expr: str, inbox: SampleSink) -> Any:
        """Queue every sample under ``key_expr`` into ``inbox``; returns a handle for
        :meth:`unsubscribe`."""

        def deliver(sample: zenoh.Sample) -> None:
            inbox.put(Sample(str(sample.key_expr), sample.payload.to_bytes()))

        def make(session: zenoh.Session, handle: _Declared) -> zenoh.Subscriber:
            def on_sample(sample: zenoh.Sample) -> None:
                move = self._move
                if move is None:
                    inbox.put(Sample(str(sample.key_expr), sample.payload.to_bytes()))
                else:
                    move.sample(handle, session, sample, deliver)

            return session.declare_subscriber(key_expr, on_sample)

        return self._declare(_Declared(make))

    def subscribe_payloads(self, key_expr: str, callback: Callable[[bytes], None]) -> Any:
        """Call ``callback(payload)`` on zenoh's thread for every sample under ``key_expr``: for a
        receiver that needs neither the key nor a queue (the agent service's hot path, where each
        layer costs microseconds in situ). Returns a handle for :meth:`unsubscribe`."""

        def deliver(sample: zenoh.Sample) -> None:
            callback(sample.payload.to_bytes())

        def make(session: zenoh.Session, handle: _Declared) -> zenoh.Subscriber:
            def on_sample(sample: zenoh.Sample) -> None:
                move = self._move
                if move is None:
                    callback(sample.payload.to_bytes())
                else:
                    move.sample(handle, session, sample, deliver)

            return session.declare_subscriber(key_expr, on_sample)

        return self._declare(_Declared(make))

    def unsubscribe(self, handle: Any) -> None:
        self._undeclare(handle)

    def serve(self, key_expr: str) -> QueryInbox:
        """Declare a queryable; its queries are queued in the returned inbox for the caller to
        answer with ``query.reply(bytes)`` (never inside the zenoh callback)."""
        inbox = QueryInbox()

        def make(session: zenoh.Session, handle: _Declared) -> zenoh.Queryable:
            def on_query(query: zenoh.Query) -> None:
                move = self._move
                if move is None:
                    inbox.put(_ZenohQuery(query))
                else:
                    move.query(session, query, inbox)

            return session.declare_queryable(key_expr, on_query)

        self._declare(_Declared(make))
        return inbox

    def _begin_get(self) -> zenoh.Session:
        """The session a query goes out on, kept open until :meth:`_end_get` (a move waits for it)."""
        with self._lock:
            session = self.session
            self._gets[id(session)] += 1
            return session

    def _end_get(self, session: zenoh.Session) -> None:
        with self._lock:
            self._gets[id(session)] -= 1

    def request(self, key: str, message: Any, timeout_s: float) -> list[bytes]:
        payload = message if isinstance(message, (bytes, bytearray)) else encode(message)
        session = self._begin_get()
        try:
            # Every reply, not zenoh's default "latest per key": a second queryable answering on the same
            # key (a stray or hostile client) must not replace the real answer. The attachment names the
            # query: a queryable's process moving home hears it on both its sessions and answers once.
            replies = session.get(key, payload=payload, timeout=timeout_s, consolidation=zenoh.ConsolidationMode.NONE,
                                  attachment=os.urandom(8))
            return [r.ok.payload.to_bytes() for r in replies if r.ok is not None]
        finally:
            self._end_get(session)

    def wait_for_subscriber(self, key: str, timeout_s: float) -> bool:
        """Start-up race guard: wait until someone subscribes to ``key`` (ZENOH_NOTES.md)."""
        deadline = time.monotonic() + timeout_s
        while True:
            try:  # the publisher asked again each time: the bus may move home meanwhile
                if self._publisher(key).matching_status.matching:  # type: ignore[attr-defined]  # stub says bool: see _MatchingFlag
                    return True
            except zenoh.ZError:
                pass  # its session closed under it: the bus moved
            if time.monotonic() > deadline:
                return False
            time.sleep(0.01)

    def declare_token(self, key: str) -> Any:
        """A liveliness token on ``key`` until :meth:`undeclare_token` or the session ends (which
        zenoh notices, also when the process dies); returns its handle."""
        return self._declare(_Declared(lambda session, handle: session.liveliness().declare_token(key), key=key))

    def undeclare_token(self, handle: Any) -> None:
        self._undeclare(handle)

    def watch_liveliness(self, key_expr: str, inbox: SampleSink) -> Any:
        """Queue ``Sample(key, b"+")`` when a token appears (also those alive now) and
        ``Sample(key, b"-")`` when it vanishes (process gone, or its session lost)."""

        def make(session: zenoh.Session, handle: _Watch) -> zenoh.Subscriber:
            def on_sample(sample: zenoh.Sample) -> None:
                key, alive = str(sample.key_expr), sample.kind == zenoh.SampleKind.PUT
                move = self._move
                if move is None:
                    handle.change(key, alive)
                else:
                    move.change(handle, session, key, alive)

            return session.liveliness().declare_subscriber(key_expr, on_sample, history=True)

        return self._declare(_Watch(make, key_expr, inbox, self._own_tokens))

    def alive_tokens(self, key_expr: str, timeout_s: float = 1.0) -> list[str]:
        """The liveliness tokens matching ``key_expr`` alive now (a liveliness query to the router).

        The replies go to a channel with room for ``ALIVE_TOKENS_ROOM``: a session that watches
        these tokens itself (``watch_liveliness``) is answered inside ``get``, on this thread, and
        zenoh's default channel (256 replies) then filled up with nobody reading it: ``agos eval``
        with more than 256 world workers hung there for good, at its first presence check."""
        session = self._begin_get()
        try:
            replies = session.liveliness().get(key_expr, zenoh.handlers.FifoChannel(ALIVE_TOKENS_ROOM), timeout=timeout_s)
            return sorted({str(r.ok.key_expr) for r in replies if r.ok is not None})
        finally:
            self._end_get(session)

    # Moving home: the thread that looks, and the move.

    def _home_loop(self) -> None:
        while not self._stop_home.wait(FAILBACK_POLL_S * random.uniform(0.75, 1.25)):  # not all processes at once
            try:
                new = self._back_home()
                if new is not None:
                    self._move_to(new)
            except Exception as exc:  # the bus stays where it is; the next look tries again
                if not self._closed:
                    log.warning("could not move back to the own zenoh router: %s", exc)

    @staticmethod
    def _alive(session: zenoh.Session, key: str, timeout_s: float = 2.0) -> bool | None:
        """Whether a token on ``key`` is alive as ``session`` sees it; None if its router did not answer in time."""
        started = time.monotonic()
        found = any(r.ok is not None for r in session.liveliness().get(key, timeout=timeout_s))
        return found or (None if time.monotonic() - started >= timeout_s else False)

    def _back_home(self) -> zenoh.Session | None:
        """A session on this process's own router if the bus is away from it and it is back, linked to
        the router the bus is on; None otherwise (and at home)."""
        here = self.session.info.routers_zid()
        if not here or str(here[0]) == self._home_zid:
            return None  # at home, or on no router (zenoh reconnects in the list's order itself)
        try:
            probe = zenoh.open(self._home_config)
        except zenoh.ZError:
            if self._away_since is None:
                self._away_since = time.monotonic()
                log.warning("own zenoh router %s is not answering: on router %s of the list until it is back",
                            self._home, here[0])
            return None
        try:
            home = probe.info.routers_zid()
            if not home:
                return None
            self._home_zid = str(home[0])
            if self._home_zid == str(here[0]):
                return None  # at home (the first look)
            token = keys.router_live(str(here[0]))
            if self._alive(self.session, token) and not self._alive(probe, token):
                return None  # back, but not linked to this router yet: the bus would be cut off there
        finally:
            probe.close()
        new = zenoh.open(self._config)  # the whole list, own router first: it fails over as the first one did
        moved = new.info.routers_zid()
        if not moved or str(moved[0]) != self._home_zid:
            new.close()
            return None
        return new

    def _move_to(self, new: zenoh.Session) -> None:
        """Move every declaration, publishing and queries from the session to ``new`` (:class:`_Move`)."""
        started = time.monotonic()
        old = self.session
        move = _Move(old, new, self._lock)
        with self._lock:
            if self._closed:
                new.close()
                return
            self._move = move

            def attach_all() -> None:
                for handle in self._keep:
                    handle.attach(new)

            _on_a_thread_not_a_daemon(attach_all)
        # Meanwhile new's declarations reach the routers; then a liveliness query new's router answers
        # after the watches' history, so their views are complete.
        if self._stop_home.wait(FAILBACK_OVERLAP_S) or self._alive(new, keys.router_live(str(self._home_zid))) is None:
            self._give_up(move)
            return
        with self._lock:
            if self._closed:
                return  # close() closes both
            move.switch([h for h in self._keep if isinstance(h, _Watch)], [k for k, n in self._own_tokens.items() if n > 0])
            self.session = new
            self._publishers, self._watched = {}, {}  # declared again on new as they are used
        self._stop_home.wait(FAILBACK_OVERLAP_S)
        self._wait(lambda: self._gets[id(old)] == 0, 120.0)  # a query out on old waits for its replies there
        self._wait(move.handed_over, FAILBACK_HANDOVER_S)
        with self._lock:
            taken = [d for handle in self._keep for d in handle.take(old)]
        for declared in taken:
            with contextlib.suppress(Exception):
                declared.undeclare()
        with contextlib.suppress(Exception):
            old.close()
        move.old_closed()
        self._wait(move.caught_up, FAILBACK_HANDOVER_S)
        self._move = None
        away = f" ({time.monotonic() - self._away_since:.1f} s away)" if self._away_since is not None else ""
        self._away_since = None
        log.info("back on the own zenoh router %s%s: moved in %.2f s", self._home_zid, away, time.monotonic() - started)

    def _wait(self, done: Callable[[], bool], timeout_s: float) -> None:
        """Until ``done()``, looked at every 10 ms, for at most ``timeout_s`` or until the bus closes."""
        deadline = time.monotonic() + timeout_s
        while not done() and time.monotonic() < deadline and not self._stop_home.wait(0.01):
            pass

    def _give_up(self, move: _Move) -> None:
        """Undo a move before its switch: new's declarations and new itself go."""
        with self._lock:
            taken = [d for handle in self._keep for d in handle.take(move.new)]
        for declared in taken:
            with contextlib.suppress(Exception):
                declared.undeclare()
        with contextlib.suppress(Exception):
            move.new.close()
        self._move = None  # after new closed: no callback of new is left to take the fast way

    def close(self) -> None:
        """Undeclare everything this bus declared and close the session; a second call does nothing."""
        with self._lock:
            if self._closed:
                return
            self._closed = True
            taken = [d for handle in self._keep for d in handle.take()]
            self._keep.clear()
            flags = list(self._watched.values())
            self._watched.clear()
            self._publishers.clear()
            move = self._move
        self._stop_home.set()
        for declared in taken:
            with contextlib.suppress(Exception):
                declared.undeclare()
        for flag in flags:
            with contextlib.suppress(Exception):
                flag.close()
        if move is not None:
            for other in (move.old, move.new):
                if other is not self.session:
                    with contextlib.suppress(Exception):
                        other.close()
        self.session.close()
        if self._home_thread is not None and self._home_thread is not threading.current_thread():
            self._home_thread.join(5.0)


class MemoryBus:
    """In-process fake with the same surface, for unit tests (STYLE.md item 9); a context manager."""

    def __init__(self) -> None:
        self.published: list[tuple[str, Any]] = []
        self._subs: list[tuple[str, SampleSink]] = []
        self._tokens: list[list[str]] = []  # handles: one-item lists, so equal keys stay distinct
        self._watchers: list[tuple[str, SampleSink]] = []
        self._queryables: list[tuple[str, QueryInbox]] = []

    def __enter__(self) -> MemoryBus:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def publish(self, key: str, message: Any, *, once: bool = False) -> None:
        # bytes of their own, as zenoh copies on put (a sender may reuse its buffer: world/sim/worker.py)
        payload = bytes(message) if isinstance(message, (bytes, bytearray)) else encode(message)
        self.published.append((key, message))
        for expr, inbox in list(self._subs):  # a copy: another thread may (un)subscribe meanwhile
            if _matches(expr, key):
                inbox.put(Sample(key, payload))

    def publish_viz(self, key: str, message: Any) -> None:
        self.publish(key, message)

    def watched(self, key: str) -> bool:
        return any(_matches(expr, key) for expr, _ in list(self._subs))

    def forget(self, key_prefix: str) -> None:
        pass

    def subscribe(self, key_expr: str, inbox: SampleSink) -> Any:
        handle = (key_expr, inbox)
        self._subs.append(handle)
        return handle

    def subscribe_payloads(self, key_expr: str, callback: Callable[[bytes], None]) -> Any:
        return self.subscribe(key_expr, _Calling(callback))

    def unsubscribe(self, handle: Any) -> None:
        for handles in (self._subs, self._watchers):
            if handle in handles:
                handles.remove(handle)

    def serve(self, key_expr: str) -> QueryInbox:
        inbox = QueryInbox()
        self._queryables.append((key_expr, inbox))
        return inbox

    def request(self, key: str, message: Any, timeout_s: float) -> list[bytes]:
        """Queue a query in each matching queryable's inbox and wait, at most ``timeout_s``, until
        each has replied (another thread answers); the replies so far, in queryable order."""
        payload = bytes(message) if isinstance(message, (bytes, bytearray)) else encode(message)
        queries = []
        for expr, inbox in list(self._queryables):
            if _matches(expr, key):
                queries.append(_MemoryQuery(key, payload))
                inbox.put(queries[-1])
        deadline = time.monotonic() + timeout_s
        for query in queries:
            query.answered.wait(max(0.0, deadline - time.monotonic()))
        return [reply for query in queries for reply in list(query.replies)]

    def wait_for_subscriber(self, key: str, timeout_s: float) -> bool:
        return any(_matches(expr, key) for expr, _ in list(self._subs))

    def declare_token(self, key: str) -> Any:
        """As zenoh: watchers hear of a key when its first token appears and when its last goes."""
        handle = [key]
        first = not self._alive(key)
        self._tokens.append(handle)
        if first:
            self._tell(key, b"+")
        return handle

    def undeclare_token(self, handle: Any) -> None:
        if any(token is handle for token in self._tokens):
            self._tokens = [token for token in self._tokens if token is not handle]
            if not self._alive(handle[0]):
                self._tell(handle[0], b"-")

    def alive_tokens(self, key_expr: str, timeout_s: float = 1.0) -> list[str]:
        return sorted({token[0] for token in self._tokens if _matches(key_expr, token[0])})

    def _alive(self, key: str) -> bool:
        return any(token[0] == key for token in self._tokens)

    def watch_liveliness(self, key_expr: str, inbox: SampleSink) -> Any:
        handle = (key_expr, inbox)
        self._watchers.append(handle)
        for key in dict.fromkeys(token[0] for token in self._tokens):  # history: the keys alive now, once each
            if _matches(key_expr, key):
                inbox.put(Sample(key, b"+"))
        return handle

    def _tell(self, key: str, change: bytes) -> None:
        for expr, inbox in list(self._watchers):
            if _matches(expr, key):
                inbox.put(Sample(key, change))

    def close(self) -> None:
        self._subs.clear()
        self._watchers.clear()
        self._tokens.clear()
        self._queryables.clear()


class _MemoryQuery:
    """A query of :meth:`MemoryBus.request`: its replies, and whether one came."""

    def __init__(self, key: str, payload: bytes) -> None:
        self.key, self.payload = key, payload
        self.replies: list[bytes] = []
        self.answered = threading.Event()

    def reply(self, payload: bytes) -> None:
        self.replies.append(bytes(payload))
        self.answered.set()


class _Calling:
    """An inbox that hands each payload to a callback (``MemoryBus.subscribe_payloads``)."""

    def __init__(self, callback: Callable[[bytes], None]) -> None:
        self.callback = callback

    def put(self, sample: Sample) -> None:
        self.callback(sample.payload)


BUSES: tuple[type[Bus], ...] = (ZenohBus, MemoryBus)
"""The implementations of :class:`Bus` (mypy checks here that each satisfies it; tests/test_bus.py
that each has its methods)."""


def _matches(expr: str, key: str) -> bool:
    """zenoh key-expression matching for '*' (one chunk) and '**' (any number of chunks)."""
    parts = [".*" if chunk == "**" else re.escape(chunk).replace(r"\*", "[^/]+") for chunk in expr.split("/")]
    pattern = "/".join(parts).replace("/.*", "(/.*)?") if parts[-1] == ".*" else "/".join(parts)
    return re.fullmatch(pattern, key) is not None
