"""Liveliness at the scale of a large run, on a real zenoh router in this process (no process started)."""

from __future__ import annotations

import threading
import time

import pytest
import zenoh

from agos.deploy.run.launcher import free_port
from agos.runtime import keys
from agos.runtime.bus import Inbox, ZenohBus, zenoh_config

pytestmark = pytest.mark.loopback


def test_alive_tokens_answers_beyond_256_tokens_its_own_session_watches() -> None:
    """``agos eval`` watches the world workers' tokens and asks for them at each presence check; with
    more than 256 workers the query used to hang for good (zenoh answered it on the asking thread,
    into a 256-reply channel nobody read), and the orchestrator's session with it."""
    endpoint = f"tcp/127.0.0.1:{free_port(0)}"
    router = zenoh.open(zenoh_config(mode="router", listen=[endpoint]))
    workers = ZenohBus.connect(endpoint)
    orchestrator = ZenohBus.connect(endpoint)
    try:
        n = 300
        for i in range(n):
            workers.declare_token(keys.live("big", "world", f"w{i}"))
        seen = Inbox()
        orchestrator.watch_liveliness(keys.live("big", "world", "*"), seen)
        deadline = time.monotonic() + 10.0
        heard: set[str] = set()
        while len(heard) < n and time.monotonic() < deadline:
            sample = seen.get(0.5)
            if sample is not None:
                heard.add(sample.key)
        assert len(heard) == n
        answer: list[list[str]] = []

        def ask() -> None:  # a query right after the watch may find the router not yet done: asked again
            for _ in range(10):
                answer.append(orchestrator.alive_tokens(keys.live("big", "world", "*"), timeout_s=2.0))
                if len(answer[-1]) == n:
                    return
                time.sleep(0.2)

        asking = threading.Thread(target=ask, daemon=True)
        asking.start()
        asking.join(30.0)
        assert answer and not asking.is_alive(), "alive_tokens hung"
        assert len(answer[-1]) == n
    finally:
        orchestrator.close()
        workers.close()
        router.close()


def test_a_key_published_once_keeps_no_publisher() -> None:
    """Records, acks and lease notices (one key an episode) go out from the session: a declared
    publisher would stay in the session (and its router) for the session's life, and every sample
    received then costs more (runtime/bus.py, ``once``)."""
    endpoint = f"tcp/127.0.0.1:{free_port(0)}"
    router = zenoh.open(zenoh_config(mode="router", listen=[endpoint]))
    sender = ZenohBus.connect(endpoint)
    receiver = ZenohBus.connect(endpoint)
    try:
        inbox = Inbox()
        receiver.subscribe(keys.result_ack("r", "*"), inbox)
        key = keys.result_ack("r", "e1")
        deadline = time.monotonic() + 10.0
        got = None
        while got is None and time.monotonic() < deadline:  # until the subscription has reached the router
            sender.publish(key, b"ack", once=True)
            got = inbox.get(0.2)
        assert got is not None and got.key == key and got.payload == b"ack"
        assert key not in sender._publishers
    finally:
        receiver.close()
        sender.close()
        router.close()
