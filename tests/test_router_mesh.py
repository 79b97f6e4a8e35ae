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

import pytest
import zenoh

from agos.deploy.cli import main as agos
from agos.deploy.ops.certs import make_certs, zenohd_config
from agos.deploy.run.launcher import free_port
from agos.runtime import keys
from agos.runtime.access_control import IDENTITIES, access_control
from agos.runtime.bus import Inbox, ZenohBus, connect_retry_s, session_config
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

    with router(a, [], certs) as router_a, router(b, [a], certs), router(c, [a], other) as stranger_router, \
            client("world", f"{b},{a}") as world, client("agent-uav", a) as uav, \
            client("orchestrator", a) as orchestrator, client("world", c, other) as stranger:
        obs, act = keys.obs(RUN, "e1", "uav"), keys.act(RUN, "e1", "uav")
        uav_hears, world_hears, orch_hears = Inbox(), Inbox(), Inbox()
        uav.subscribe(keys.obs(RUN, "*", "uav"), uav_hears)
        world.subscribe(keys.act(RUN, "*", "*"), world_hears)
        for key in (keys.result(RUN, "*"), keys.result_ack(RUN, "*")):
            orchestrator.subscribe(key, orch_hears)

        # B's world reaches A's agent; the stranger's world (a router of another CA) never does.
        def both() -> None:
            stranger.publish(keys.obs(RUN, "c1", "uav"), b"o")
            world.publish(obs, b"o")

        heard = _until(uav_hears, obs, both)
        assert set(heard) == {obs}
        # A's agent forges the UGV's action before its own: A drops it, B's world hears only the UAV's.
        for _ in range(5):
            uav.publish(keys.act(RUN, "e1", "ugv"), b"forged")
        assert set(_until(world_hears, act, lambda: uav.publish(act, b"a"))) == {act}
        # B's world forges acknowledgements before a result: B drops them, A's orchestrator hears the result.
        for _ in range(5):
            world.publish(keys.result_ack(RUN, "e1"), b"forged")
        assert set(_until(orch_hears, keys.result(RUN, "e1"), lambda: world.publish(keys.result(RUN, "e1"), b"r"))) \
            == {keys.result(RUN, "e1")}
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
