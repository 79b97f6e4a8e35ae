"""A mesh of routers: the settings (a list of routers to connect to, a router's peers), the zenoh
configs they make, the access control's grant to other routers, and (loopback) a secured mesh of
routers in this process relaying what each router allowed its own clients to say and nothing else.

The mesh with real processes, a router killed mid-run: tests/test_e2e_faults.py."""

from __future__ import annotations

import json
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
import zenoh

from agos.deploy.cli import main as agos
from agos.deploy.ops.certs import make_certs, zenohd_config
from agos.deploy.run.launcher import free_port
from agos.runtime import bus as bus_module
from agos.runtime import keys
from agos.runtime.access_control import IDENTITIES, access_control
from agos.runtime.bus import Inbox, ZenohBus, connect_retry_s, session_config, zenoh_config
from agos.runtime.router import router_config
from agos.runtime.settings import ConfigError, ZenohSettings, load_config

RUN = "mesh"


def _json(config: zenoh.Config, key: str) -> object:
    return json.loads(config.get_json(key))


def test_a_list_of_routers_nearest_first_and_a_routers_peers() -> None:
    z = ZenohSettings(connect="tcp/10.0.1.2:7447, tcp/10.0.0.1:7447")
    assert z.connect_endpoints == ["tcp/10.0.1.2:7447", "tcp/10.0.0.1:7447"]
    client = session_config(z)
    assert _json(client, "connect/endpoints") == ["tcp/10.0.1.2:7447", "tcp/10.0.0.1:7447"]
    # zenoh would retry the first router until the timeout: it tries each once, agos tries the list again.
    assert _json(client, "connect/timeout_ms") == {"client": 0, "peer": -1, "router": -1}
    assert connect_retry_s(z) == z.connect_timeout_s
    one = ZenohSettings(connect="tcp/10.0.0.1:7447")
    assert _json(session_config(one), "connect/timeout_ms")["client"] == 10_000  # type: ignore[index]
    assert connect_retry_s(one) == 0.0

    env = load_config(environ={"AGOS_ZENOH__PEERS": "tcp/10.0.0.1:7447,tcp/10.0.2.1:7447",
                               "AGOS_ZENOH__LISTEN": "tcp/0.0.0.0:7447"}).zenoh
    assert env.peers == ["tcp/10.0.0.1:7447", "tcp/10.0.2.1:7447"]
    router = session_config(env, mode="router")
    assert _json(router, "connect/endpoints") == env.peers
    assert _json(router, "listen/endpoints") == ["tcp/0.0.0.0:7447"]
    assert ZenohSettings().peers == []
    assert _json(session_config(ZenohSettings(), mode="router"), "connect/endpoints") in ([], {})


def test_endpoint_lists_that_cannot_work_stop_with_one_line(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(ConfigError, match=r"^config error: environment AGOS_ZENOH__CONNECT: zenoh.connect: .*"
                                          r"the list mixes tls/ and plain endpoints"):
        load_config(environ={"AGOS_ZENOH__CONNECT": "tls/10.0.1.2:7447,tcp/10.0.0.1:7447"})
    with pytest.raises(ConfigError, match=r"zenoh.peers: .*'10.0.0.1:7447' is not an endpoint: write PROTOCOL/HOST:PORT"):
        load_config(environ={"AGOS_ZENOH__PEERS": "10.0.0.1:7447"})
    with pytest.raises(ConfigError, match=r"zenoh.connect: .*no endpoint"):
        load_config(environ={"AGOS_ZENOH__CONNECT": " , "})
    # A secured router peering over plain TCP would let unauthenticated clients of the other router in.
    assert agos(["router", "--listen", "tls/0.0.0.0:7447", "--peer", "tcp/10.0.0.1:7447"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("config error: command line: zenoh.peers:") and "tls/ on every link" in err
    assert "\n" not in err


def test_a_secured_router_presents_its_certificate_to_its_peers(tmp_path: Path) -> None:
    make_certs(tmp_path)
    z = ZenohSettings(listen="tls/0.0.0.0:7447", peers=["tls/core.lan:7447"], ca_file=tmp_path / "ca.pem",
                      cert_file=tmp_path / "router.pem", key_file=tmp_path / "router.key")
    tls = _json(router_config(z), "transport/link/tls")
    assert isinstance(tls, dict)
    assert tls["connect_certificate"] == tls["listen_certificate"] == str(tmp_path / "router.pem")
    assert tls["connect_private_key"] == tls["listen_private_key"] == str(tmp_path / "router.key")
    assert tls["enable_mtls"] is True and tls["verify_name_on_connect"] is True
    lone = _json(router_config(z.model_copy(update={"peers": []})), "transport/link/tls")
    assert isinstance(lone, dict) and lone.get("connect_certificate") is None
    zenohd = zenohd_config()["transport"]["link"]["tls"]  # type: ignore[index]
    assert zenohd["connect_certificate"] == zenohd["listen_certificate"]


def _grants(identity: str) -> list[dict]:
    acl = access_control()
    policy = next(p for p in acl["policies"] if identity in p["subjects"])
    return [r for r in acl["rules"] if r["id"] in policy["rules"]]


def test_only_the_router_identity_relays_and_only_agos_keys() -> None:
    """zenoh applies the rules to router-router links by the certificate the other router presents."""
    every = {"put", "delete", "declare_subscriber", "query", "reply", "declare_queryable", "liveliness_token",
             "declare_liveliness_subscriber", "liveliness_query"}
    relay = [r for r in _grants("router") if set(r["flows"]) == {"ingress", "egress"}]
    assert len(relay) == 1 and set(relay[0]["messages"]) == every and relay[0]["key_exprs"] == ["agos/**"]
    for identity in IDENTITIES:
        if identity != "router":
            assert all(len(r["flows"]) == 1 for r in _grants(identity)), identity


def _until(inbox: Inbox, key: str, send: Callable[[], None], timeout_s: float = 15.0) -> list[str]:
    """Send (again every 0.2 s: declarations cross the mesh in their own time) until ``key`` is heard;
    every key heard meanwhile."""
    heard: list[str] = []
    deadline = time.monotonic() + timeout_s
    while key not in heard:
        assert time.monotonic() < deadline, f"{key} never arrived; heard {heard}"
        send()
        sample = inbox.get(0.2)
        heard += [s.key for s in ([sample] if sample else []) + inbox.drain()]
    return heard


@pytest.mark.loopback
def test_a_secured_mesh_relays_what_each_router_allowed_and_nothing_else(tmp_path: Path) -> None:
    """Routers A and B (B peers A) in this process with `agos certs` credentials; a router whose
    certificate another CA signed peers A too. A world worker on B (A its fallback), the UAV agent,
    orchestrator and evaluator on A: observations, actions, results, job queries and liveliness cross
    the mesh; what B's or A's clients may not say is dropped where it comes in; the stranger router
    relays nothing."""
    certs, other = tmp_path / "certs", tmp_path / "other"
    make_certs(certs)
    make_certs(other, identities=["router", "world"])
    a, b, c = (f"tls/127.0.0.1:{free_port(0)}" for _ in range(3))

    def router(listen: str, peers: list[str], creds: Path) -> zenoh.Session:
        return zenoh.open(router_config(ZenohSettings(
            listen=listen, peers=peers, ca_file=creds / "ca.pem", cert_file=creds / "router.pem",
            key_file=creds / "router.key")))

    def client(identity: str, connect: str, creds: Path = certs) -> ZenohBus:
        return ZenohBus.from_settings(ZenohSettings(
            connect=connect, ca_file=creds / "ca.pem", cert_file=creds / f"{identity}.pem",
            key_file=creds / f"{identity}.key", connect_timeout_s=5))

    with router(a, [], certs) as router_a, router(b, [a], certs) as router_b, \
            router(c, [a], other) as stranger_router:
        # Clients declare once B has linked to A: zenoh 1.10 can leave a subscription declared on B
        # during the link's set-up unknown to A for good (seen on a loaded machine, about 1 run in 10).
        _linked(router_a, router_b)
        with client("world", f"{b},{a}") as world, client("agent-uav", a) as uav, \
                client("orchestrator", a) as orchestrator, client("world", c, other) as stranger:
            _relay_checks(router_a, stranger_router, world, uav, orchestrator, stranger)


def _linked(router_a: zenoh.Session, router_b: zenoh.Session, timeout_s: float = 15.0) -> None:
    deadline = time.monotonic() + timeout_s
    while str(router_b.zid()) not in {str(z) for z in router_a.info.routers_zid()}:
        assert time.monotonic() < deadline, "router B never linked to A"
        time.sleep(0.05)


def _relay_checks(router_a: zenoh.Session, stranger_router: zenoh.Session, world: ZenohBus, uav: ZenohBus,
                  orchestrator: ZenohBus, stranger: ZenohBus) -> None:
    """What crosses the mesh and what each router drops."""
    obs, act = keys.obs(RUN, "w1", "uav"), keys.act(RUN, "w1", "uav")
    uav_hears, world_hears, orch_hears = Inbox(), Inbox(), Inbox()
    uav.subscribe(keys.obs(RUN, "*", "uav"), uav_hears)
    # One key per role, as a world worker subscribes: a wider one (act/*/*) is more than the UAV agent's
    # grant lets A tell it of, so its client would never learn of a subscriber and drop its own puts.
    for role in keys.ROLES:
        world.subscribe(keys.act(RUN, "w1", role), world_hears)
    for key in (keys.result(RUN, "*"), keys.result_ack(RUN, "*")):
        orchestrator.subscribe(key, orch_hears)

    # B's world reaches A's agent; the stranger's world (a router of another CA) never does.
    def both() -> None:
        stranger.publish(keys.obs(RUN, "w1", "uav"), b"o")
        world.publish(obs, b"o")

    heard = _until(uav_hears, obs, both)
    assert set(heard) == {obs}
    # A's agent forges the UGV's action before its own: it never reaches B's world, only the UAV's does.
    for _ in range(5):
        uav.publish(keys.act(RUN, "w1", "ugv"), b"forged")
    assert set(_until(world_hears, act, lambda: uav.publish(act, b"a"))) == {act}
    # B's world forges acknowledgements before a result: B drops them, A's orchestrator hears the result.
    for _ in range(5):
        world.publish(keys.result_ack(RUN, "w1"), b"forged")
    assert set(_until(orch_hears, keys.result(RUN, "w1"), lambda: world.publish(keys.result(RUN, "w1"), b"r"))) \
        == {keys.result(RUN, "w1")}
    # Queries and liveliness tokens cross too: the world's job request, its token.
    jobs = orchestrator.serve(keys.jobs(RUN))
    token = world.declare_token(keys.live(RUN, "world", "w0"))
    deadline = time.monotonic() + 10
    while orchestrator.alive_tokens(keys.live(RUN, "world", "*")) != [keys.live(RUN, "world", "w0")]:
        assert time.monotonic() < deadline, "the world's token never reached A"
    stop = threading.Event()

    def answer() -> None:
        while not stop.is_set():
            if (query := jobs.get(0.1)) is not None:
                query.reply(b"grant")

    answering = threading.Thread(target=answer, daemon=True)
    answering.start()
    try:
        replies: list[bytes] = []
        while not replies:
            assert time.monotonic() < deadline, "the job request never got across"
            replies = world.request(keys.jobs(RUN), b"ask", timeout_s=2.0)
    finally:
        stop.set()
        answering.join()
    assert replies == [b"grant"]
    world.undeclare_token(token)
    # Seconds later still nothing from the stranger's world, whose router A never let in.
    assert {s.key for s in uav_hears.drain()} <= {obs}
    assert str(stranger_router.zid()) not in {str(z) for z in router_a.info.routers_zid()}


def _router_of(bus: ZenohBus) -> str | None:
    routers = bus.session.info.routers_zid()
    return str(routers[0]) if routers else None


def _wait(what: str, predicate: Callable[[], bool], timeout_s: float = 15.0) -> float:
    """Seconds until ``predicate()``, polled every 10 ms; fails the test after ``timeout_s``."""
    started = time.monotonic()
    while not predicate():
        assert time.monotonic() - started < timeout_s, f"{what}: not within {timeout_s} s"
        time.sleep(0.01)
    return time.monotonic() - started


@pytest.mark.loopback
def test_a_process_back_on_its_own_router_misses_nothing_and_hears_nothing_twice(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """Routers A and B in this process (B peers A); a bus of B's site (B, then A) fails over to A when B
    goes and moves back when B is up again: samples streamed to it (from A, and from itself) arrive once
    each, in order, across the move; its token never ends for a watcher on A, and it sees none of A's
    end; its queryable answers each query at most once, and its handles still work after."""
    monkeypatch.setattr(bus_module, "FAILBACK_POLL_S", 0.1)
    a, b = (f"tcp/127.0.0.1:{free_port(0)}" for _ in range(2))

    def router(listen: str, peers: list[str]) -> zenoh.Session:
        return zenoh.open(router_config(ZenohSettings(listen=listen, peers=peers)))

    router_a, router_b = router(a, []), router(b, [a])
    far = ZenohBus(zenoh_config(connect=[a]))
    site = ZenohBus(zenoh_config(connect=[b, a]))
    try:
        _wait("site on B", lambda: _router_of(site) == str(router_b.zid()))
        heard, own_heard, payloads, site_sees, far_sees = Inbox(), Inbox(), Inbox(), Inbox(), Inbox()
        site.subscribe("fb/stream", heard)
        site.subscribe("fb/own", own_heard)
        site.subscribe_payloads("fb/stream", lambda p: payloads.put(bus_module.Sample("", p)))
        token = site.declare_token("fb/live/site")
        far.declare_token("fb/live/far")
        site.watch_liveliness("fb/live/*", site_sees)
        far.watch_liveliness("fb/live/*", far_sees)
        queries = site.serve("fb/q")
        _wait("the site's token at A", lambda: far.alive_tokens("fb/live/*") == ["fb/live/far", "fb/live/site"])

        router_b.close()  # B goes: the site fails over to A (losing what was on the way: not this test's subject)
        _wait("site on A", lambda: _router_of(site) == str(router_a.zid()))
        _wait("the site's token at A again", lambda: "fb/live/site" in far.alive_tokens("fb/live/*"))
        _wait("far's subscription reached", lambda: far.wait_for_subscriber("fb/stream", 0))
        for inbox in (heard, own_heard, payloads, site_sees, far_sees):
            inbox.drain()

        stop = threading.Event()
        sent = {"stream": 0, "own": 0}
        answered: list[int] = []

        def stream() -> None:  # from A, and from the site to itself, until stopped
            while not stop.is_set():
                far.publish("fb/stream", sent["stream"].to_bytes(4, "big"))
                sent["stream"] += 1
                site.publish("fb/own", sent["own"].to_bytes(4, "big"))
                sent["own"] += 1
                time.sleep(0.002)

        def answer() -> None:
            while not stop.is_set():
                if (query := queries.get(0.05)) is not None:
                    query.reply(b"yes")

        def ask() -> None:
            while not stop.is_set():
                answered.append(len(far.request("fb/q", b"?", timeout_s=1.0)))

        threads = [threading.Thread(target=f, daemon=True) for f in (stream, answer, ask)]
        for thread in threads:
            thread.start()
        restarted = time.monotonic()
        router_b = router(b, [a])  # B is back, a new router: the site moves home
        _wait("site back on B", lambda: _router_of(site) == str(router_b.zid()))
        moved_s = time.monotonic() - restarted
        time.sleep(0.5)  # the stream goes on on B
        stop.set()
        for thread in threads:
            thread.join(5.0)

        def numbers(inbox: Inbox) -> list[int]:
            got: list[int] = []
            deadline = time.monotonic() + 5.0
            while time.monotonic() < deadline and (not got or got[-1] < sent[("own" if inbox is own_heard else "stream")] - 1):
                got += [int.from_bytes(s.payload, "big") for s in inbox.drain()]
                time.sleep(0.05)
            return got

        for name, inbox in (("subscribe", heard), ("subscribe_payloads", payloads), ("own puts", own_heard)):
            got = numbers(inbox)
            odd = [(i, got[i - 1], n) for i, n in enumerate(got) if i and n != got[i - 1] + 1]
            assert not odd, f"{name}: lost, twice or out of order (index, before, after): {odd[:10]} of {len(got)}"
            assert got[0] == 0 and got[-1] == sent["own" if inbox is own_heard else "stream"] - 1
        assert far_sees.drain() == [] and site_sees.drain() == []  # no token ended or began meanwhile
        assert answered and max(answered) == 1 and answered[-1] == 1
        print(f"moved back {moved_s:.2f} s after B was up; {sent['stream']} samples each way; "
              f"{answered.count(0)} of {len(answered)} queries unanswered")
        # The handles handed out before the move act on the new session.
        site.undeclare_token(token)
        _wait("the site's token ended", lambda: far.alive_tokens("fb/live/*") == ["fb/live/far"])
        assert [s.payload for s in _drain_until(far_sees, 1)] == [b"-"]
    finally:
        site.close()
        far.close()
        router_b.close()
        router_a.close()


def _drain_until(inbox: Inbox, n: int, timeout_s: float = 5.0) -> list[Any]:
    got: list[Any] = []
    deadline = time.monotonic() + timeout_s
    while len(got) < n and time.monotonic() < deadline:
        sample = inbox.get(0.05)
        if sample is not None:
            got.append(sample)
    return got
