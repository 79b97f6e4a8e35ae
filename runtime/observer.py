"""Read-only observers of a run: ``agos watch`` and the base for recorders and consoles.

An :class:`Observer` watches the visualisation stream by default (``keys.viz_light()``: step events,
coordination truth, small frames, episode specs and records; runtime/viz.py; not the full-resolution
frames, which worlds make only while someone subscribes to them), which the world publishes with congestion
control DROP: a slow observer loses samples there and the world never waits for it. It may also
watch control traffic (``key_expr="agos/**"``), which is reliable with congestion control BLOCK:
a subscriber that stops reading back-pressures the router and slows every process. So an
Observer never works in the zenoh callback either way: samples go to a bounded ring buffer
(zenoh's ``RingChannel``, oldest dropped when full) and are processed on the observer's own
thread.

Keys of the stream name world workers (``agos/<run>/viz/<worker>/...``), not episodes: each payload
names its episode (``episode_id``), and ``agos watch --episode EP`` follows one episode by that field.
"""

from __future__ import annotations

import threading
from collections.abc import Callable

import msgspec
import zenoh

from agos.runtime import keys
from agos.runtime.bus import connect_retry_s, open_session, session_config
from agos.runtime.settings import ZenohSettings
from agos.runtime.viz import episode_of_payload


class Observer:
    def __init__(self, endpoint: str | ZenohSettings, handle: Callable[[str, bytes], None], *, key_expr: str | None = None,
                 capacity: int = 256) -> None:
        """``endpoint``: a router endpoint, or whole ``[zenoh]`` settings (a secured bus's credentials)."""
        key_exprs = (key_expr,) if key_expr else keys.viz_light()
        z = endpoint if isinstance(endpoint, ZenohSettings) else ZenohSettings(connect=endpoint)
        self.session = open_session(session_config(z), retry_for_s=connect_retry_s(z))
        self.subscribers = [self.session.declare_subscriber(k, zenoh.handlers.RingChannel(capacity)) for k in key_exprs]
        self.handle = handle
        self.seen = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._loop, name="observer", daemon=True)
        self._thread.start()

    def _loop(self) -> None:
        while not self._stop.is_set():
            idle = True
            for subscriber in self.subscribers:
                try:
                    sample = subscriber.handler.try_recv()
                except zenoh.ZError:
                    sample = None
                if sample is not None:
                    idle = False
                    self.seen += 1
                    self.handle(str(sample.key_expr), sample.payload.to_bytes())
            if idle:
                self._stop.wait(0.005)

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=2.0)
        for subscriber in self.subscribers:
            subscriber.undeclare()
        self.session.close()


def _seconds(value: object) -> str:
    """A time in seconds as ``agos watch`` prints it: to the hundredth (``t=47.27``)."""
    return f"{value:.2f}" if isinstance(value, float) else str(value)


def describe(key: str, payload: bytes) -> str:
    """One line for a sample: its key, the message's type and version, the episode it names, what
    tells it apart (role, decision, action, simulated time), its size."""
    try:
        data = msgspec.msgpack.decode(payload)
    except (ValueError, RecursionError):  # msgspec.DecodeError, a string that is not UTF-8, too deep
        return f"{key}  <{len(payload)} bytes, not msgpack>"
    if not isinstance(data, dict):
        return f"{key}  <{type(data).__name__}>"
    extra = f" ep={data['episode_id']}" if isinstance(data.get("episode_id"), str) else ""
    if data.get("type") == "step":
        extra += f" {data.get('role')}#{data.get('decision_index')} {data.get('applied')} t={_seconds(data.get('sim_time_s'))}"
    elif data.get("type") == "episode_record":
        extra += f" {data.get('termination')} success={data.get('success')}"
    elif data.get("type") == "viz_frame":
        extra += f" {data.get('role')}#{data.get('decision_index')} t={_seconds(data.get('sim_time_s'))}"
    elif data.get("type") == "coordination_state":
        extra += f" t={_seconds(data.get('sim_time_s'))} candidates={len(data.get('candidates') or [])}"
    return f"{key}  v{data.get('v')} {data.get('type')}{extra}  ({len(payload)} B)"


def printer(episode: str | None = None) -> Callable[[str, bytes], None]:
    """What ``agos watch`` does with a sample: print its line; with ``episode``, only if its payload
    names that episode (keys name world workers, whose episodes follow each other on the same keys)."""

    def show(key: str, payload: bytes) -> None:
        if episode is None or episode_of_payload(payload) == episode:
            print(describe(key, payload), flush=True)

    return show


def main(endpoint: str | ZenohSettings, key_expr: str | None = None, episode: str | None = None) -> int:
    """``agos watch``: print every sample of the visualisation stream (or of ``key_expr``), or only
    those of ``episode``."""
    import signal

    stop = threading.Event()
    signal.signal(signal.SIGINT, lambda *_: stop.set())
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    observer = Observer(endpoint, printer(episode), key_expr=key_expr)
    try:
        while not stop.wait(0.2):
            pass
    finally:
        observer.close()
    return 0
