"""The in-memory bus fake matches zenoh key expressions like the real one, and keeps the ``Bus`` contract."""

import threading
import time

from agos.runtime import keys
from agos.runtime.bus import BUSES, Bus, Inbox, MemoryBus, Sample, _matches
from agos.runtime.codec import decode
from agos.runtime.schemas import ResultAck


def test_key_expression_matching() -> None:
    assert _matches("agos/*/ep/*/obs/uav", "agos/r1/ep/e1/obs/uav")
    assert not _matches("agos/*/ep/*/obs/uav", "agos/r1/ep/e1/obs/ugv")
    assert not _matches("agos/*/ep/*/obs/uav", "agos/r1/x/ep/e1/obs/uav")
    assert _matches("agos/**", "agos/r1/ep/e1/coord/view/ugv")
    assert _matches("agos/r1/**", "agos/r1/ctl/manifest")


def test_memory_bus_delivers_encoded_messages() -> None:
    bus = MemoryBus()
    inbox = Inbox()
    bus.subscribe(keys.result_ack("*", "*"), inbox)
    assert bus.wait_for_subscriber(keys.result_ack("r", "e"), 0.0)
    bus.publish(keys.result_ack("r", "e"), ResultAck(run_id="r", episode_id="e", newly_stored=True))
    bus.publish(keys.result("r", "e"), b"ignored")
    sample = inbox.get(0.1)
    assert sample is not None and sample.key == "agos/r/slot/e/ack"
    assert decode(sample.payload) == ResultAck(run_id="r", episode_id="e", newly_stored=True)
    assert inbox.get(0.0) is None


def test_memory_bus_visualisation_stream() -> None:
    bus = MemoryBus()
    key = keys.viz_events("r", "e")
    assert not bus.watched(key)
    inbox = Inbox()
    bus.subscribe(keys.viz_all(), inbox)
    assert bus.watched(key) and not bus.watched(keys.events("r", "e"))
    bus.publish_viz(key, ResultAck(run_id="r", episode_id="e", newly_stored=False))
    sample = inbox.get(0.1)
    assert sample is not None and sample.key == "agos/r/viz/e/events"


def test_memory_bus_liveliness_tokens() -> None:
    bus = MemoryBus()
    first = bus.declare_token(keys.slot_live("r", "w1"))
    inbox = Inbox()
    bus.watch_liveliness(keys.slot_live("r", "*"), inbox)
    assert inbox.drain() == [Sample("agos/r/slot/w1/live", b"+")]  # history: alive before watching
    # As zenoh 1.10 through a router: a second token on a key already alive is not announced, and
    # the key is reported gone when its last token goes.
    second = bus.declare_token(keys.slot_live("r", "w1"))
    bus.declare_token(keys.live("r", "world", "w1"))  # not watched
    bus.undeclare_token(first)
    bus.undeclare_token(first)  # twice: nothing more
    assert inbox.drain() == []
    bus.undeclare_token(second)
    assert inbox.drain() == [Sample("agos/r/slot/w1/live", b"-")]


def test_both_buses_have_every_method_of_the_protocol() -> None:
    members = {name for name in vars(Bus) if not name.startswith("_")}
    assert {"publish", "forget", "serve", "request", "close"} <= members
    for cls in BUSES:
        assert all(callable(getattr(cls, name, None)) for name in members), cls


def test_memory_bus_queries_are_answered_by_the_queryable() -> None:
    with MemoryBus() as bus:
        assert bus.request(keys.jobs("r"), b"nobody serves", timeout_s=1.0) == []
        queries = bus.serve(keys.asset("*"))

        def answer_one() -> None:
            query = queries.get(1.0)
            if query is not None:
                query.reply(b"<" + query.payload + b">")

        answering = threading.Thread(target=answer_one)
        answering.start()
        assert bus.request(keys.asset("abc"), b"q", timeout_s=1.0) == [b"<q>"]
        answering.join()
        hang_bound_s = 10.0  # a hang, not a speed (200x the timeout): the request's timeout is kept, not ignored
        started = time.monotonic()
        assert bus.request(keys.asset("abc"), b"q", timeout_s=0.05) == []  # queued, never answered: times out
        assert time.monotonic() - started < hang_bound_s
        assert [q.key for q in queries.drain()] == ["agos/assets/abc"]


def test_memory_bus_unsubscribe_forget_and_close() -> None:
    bus = MemoryBus()
    inbox, payloads = Inbox(), list[bytes]()
    handle = bus.subscribe(keys.events("r", "*"), inbox)
    bus.subscribe_payloads(keys.events("r", "*"), payloads.append)
    bus.forget(keys.slot_prefix("r", "e"))  # subscriptions outlive it
    bus.publish(keys.events("r", "e"), b"one")
    bus.unsubscribe(handle)
    bus.unsubscribe(handle)  # twice: nothing more
    bus.publish(keys.events("r", "e"), b"two")
    assert [s.payload for s in inbox.drain()] == [b"one"] and payloads == [b"one", b"two"]
    bus.declare_token(keys.live("r", "world", "w"))
    with bus:
        pass
    bus.close()  # idempotent
    bus.publish(keys.events("r", "e"), b"three")
    assert payloads == [b"one", b"two"] and bus.alive_tokens(keys.live("r", "world", "*")) == []
