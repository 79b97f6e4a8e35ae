"""The secured bus, for real: a TLS router process enforcing the access control generated from the
key space, clients in this process holding the certificates `agos certs` makes.

Forgeries are detected with markers: a client's messages reach the router in order, so once a
legitimate message sent *after* the forgeries has arrived, a forgery that got through would have
arrived before it.
"""

from __future__ import annotations

import os
import sqlite3
import subprocess
import sys
import threading
import time
from pathlib import Path

import msgspec
import pytest
import zenoh

from agos.deploy.ops.certs import credential_env, make_certs
from agos.deploy.run.launcher import free_port, wait_listening
from agos.runtime import keys
from agos.runtime.bus import session_config, zenoh_config
from agos.runtime.codec import encode
from agos.runtime.episode_config import EpisodeConfig
from agos.runtime.failure_records import failure_record
from agos.runtime.schemas import Action, ResultAck
from agos.runtime.settings import ZenohSettings

pytestmark = pytest.mark.e2e
AGOS = [sys.executable, "-m", "agos.deploy.cli"]
RUN = "sec"


def _env(certs: Path, identity: str) -> dict[str, str]:
    return {**os.environ, **credential_env(certs, identity)}


def _start(args: list[str], certs: Path, identity: str, log: Path) -> subprocess.Popen:
    with log.open("wb") as out:
        return subprocess.Popen([*AGOS, *args], env=_env(certs, identity), stdout=out, stderr=subprocess.STDOUT)


def _session(certs: Path, identity: str, endpoint: str) -> zenoh.Session:
    z = ZenohSettings(connect=endpoint, ca_file=certs / "ca.pem", cert_file=certs / f"{identity}.pem",
                      key_file=certs / f"{identity}.key", connect_timeout_s=5)
    return zenoh.open(session_config(z))


class Heard:
    def __init__(self, session: zenoh.Session, key_expr: str) -> None:
        self.keys: list[str] = []
        self.sub = session.declare_subscriber(key_expr, lambda s: self.keys.append(str(s.key_expr)))

    def wait_for(self, key: str, send, timeout_s: float = 15.0) -> None:
        """Send (again every 0.2 s) until ``key`` is heard: the marker after the forgeries."""
        deadline = time.monotonic() + timeout_s
        while key not in self.keys:
            assert time.monotonic() < deadline, f"{key} never arrived; heard {self.keys}"
            send()
            time.sleep(0.2)


@pytest.fixture
def secured_router(tmp_path):
    certs = tmp_path / "certs"
    make_certs(certs)
    port = free_port(17447)
    endpoint = f"tls/127.0.0.1:{port}"
    router = _start(["router", "--listen", endpoint], certs, "router", tmp_path / "router.log")
    assert wait_listening("127.0.0.1", port, 15.0), (tmp_path / "router.log").read_text()
    yield certs, endpoint, port
    router.terminate()
    router.wait(timeout=10)


def test_router_refuses_forgeries_and_strangers(secured_router, tmp_path) -> None:
    certs, endpoint, port = secured_router
    ep = "e1"
    act = Action(run_id=RUN, episode_id=ep, role="uav", decision_index=1, action="WAIT")
    forged_act = msgspec.structs.replace(act, role="ugv")
    ack = ResultAck(run_id=RUN, episode_id=ep, newly_stored=True)
    with (_session(certs, "world", endpoint) as world, _session(certs, "evaluator", endpoint) as evaluator,
          _session(certs, "agent-uav", endpoint) as uav, _session(certs, "observer", endpoint) as observer,
          _session(certs, "world", endpoint) as other_world):
        world_hears_actions = Heard(world, keys.act(RUN, "*", "*"))
        # Another worker's session: a session hears its own puts without asking the router.
        world_hears_acks = Heard(other_world, keys.result_ack(RUN, "*"))
        evaluator_hears_results = Heard(evaluator, keys.result(RUN, "*"))
        observer_hears_viz = Heard(observer, keys.viz_all(RUN))
        try:  # an observer may not even ask for control traffic
            observer_hears_all = Heard(observer, "agos/**")
        except zenoh.ZError:
            observer_hears_all = None

        # The UAV's agent forges the UGV's action, a result and an acknowledgement...
        for _ in range(5):
            uav.put(keys.act(RUN, ep, "ugv"), encode(forged_act))
            uav.put(keys.result(RUN, ep), b"forged result")
            uav.put(keys.result_ack(RUN, ep), encode(ack))
        # ... then sends its own action, which does arrive.
        world_hears_actions.wait_for(keys.act(RUN, ep, "uav"), lambda: uav.put(keys.act(RUN, ep, "uav"), encode(act)))
        assert set(world_hears_actions.keys) == {keys.act(RUN, ep, "uav")}

        # A world worker may publish results but not acknowledge them: the evaluator alone does.
        for _ in range(5):
            world.put(keys.result_ack(RUN, ep), encode(ack))
        evaluator_hears_results.wait_for(keys.result(RUN, ep), lambda: world.put(keys.result(RUN, ep), b"record"))
        assert world_hears_acks.keys == []
        world_hears_acks.wait_for(keys.result_ack(RUN, ep), lambda: evaluator.put(keys.result_ack(RUN, ep), encode(ack)))

        # An observer reads the visualisation stream and nothing else.
        observer_hears_viz.wait_for(keys.viz_events(RUN, ep), lambda: world.put(keys.viz_events(RUN, ep), b"step"))
        if observer_hears_all is not None:
            assert all("/viz/" in k for k in observer_hears_all.keys), observer_hears_all.keys

    # No certificate, a certificate from another CA, or plain TCP: no session at all.
    other = tmp_path / "other-ca"
    make_certs(other, identities=["agent-uav"])
    strangers = {
        "no certificate": zenoh_config(connect=[endpoint], connect_timeout_s=2,
                                       tls={"root_ca_certificate": str(certs / "ca.pem")}),
        "another CA's certificate": zenoh_config(connect=[endpoint], connect_timeout_s=2, tls={
            "root_ca_certificate": str(certs / "ca.pem"), "enable_mtls": True,
            "connect_certificate": str(other / "agent-uav.pem"), "connect_private_key": str(other / "agent-uav.key")}),
        "plain TCP": zenoh_config(connect=[f"tcp/127.0.0.1:{port}"], connect_timeout_s=2),
    }
    for what, conf in strangers.items():
        with pytest.raises(zenoh.ZError):
            zenoh.open(conf).close()
            pytest.fail(f"a client with {what} connected")


def test_secured_run_completes_under_forgery(secured_router, tmp_path, sample_mid_episodes) -> None:
    """Every process on the secured router, a forger holding the UAV agent's credentials flooding
    results, acknowledgements and UGV actions: the run completes, each episode stored once, no forgery
    in any record, no private key in any log, record or command line."""
    from agos.world.episodes.sampling import read_episodes

    certs, endpoint, _ = secured_router
    split = sample_mid_episodes(2, 3)
    specs = read_episodes(split)
    runs = tmp_path / "runs"
    logs = tmp_path / "logs"
    logs.mkdir()
    common = ["--connect", endpoint, "--run", RUN]
    procs = [
        _start(["evaluator", "--connect", endpoint, "--runs-dir", str(runs)], certs, "evaluator", logs / "evaluator.log"),
        _start(["agent", "--role", "uav", *common], certs, "agent-uav", logs / "agent-uav.log"),
        _start(["agent", "--role", "ugv", *common], certs, "agent-ugv", logs / "agent-ugv.log"),
        _start(["world", *common, "--worker-id", "w0"], certs, "world", logs / "world.log"),
    ]
    stop = threading.Event()
    rounds: list[int] = []

    def forge() -> None:
        with _session(certs, "agent-uav", endpoint) as forger:
            while not stop.is_set():
                rounds.append(1)
                for spec in specs:
                    record = msgspec.structs.replace(
                        failure_record(RUN, spec, status="world_crashed", worker_id="forger", error="forged",
                                       config=EpisodeConfig()),
                        status="finished", success=True)
                    forger.put(keys.result(RUN, spec.episode_id), encode(record))
                    forger.put(keys.result_ack(RUN, spec.episode_id),
                               encode(ResultAck(run_id=RUN, episode_id=spec.episode_id, newly_stored=True)))
                    for index in range(1, 30):
                        forger.put(keys.act(RUN, spec.episode_id, "ugv"), encode(Action(
                            run_id=RUN, episode_id=spec.episode_id, role="ugv", decision_index=index, action="CONFIRM",
                            rationale="forger")))
                time.sleep(0.05)

    forger_thread = threading.Thread(target=forge, daemon=True)
    forger_thread.start()
    try:
        out = subprocess.run([*AGOS, "eval", "--connect", endpoint, "--run", RUN, "--split", str(split),
                              "--run-dir", str(runs / RUN)], env=_env(certs, "orchestrator"), capture_output=True,
                             text=True, timeout=240)
        assert out.returncode == 0, out.stdout + out.stderr
        cmdlines = [Path(f"/proc/{p.pid}/cmdline").read_bytes() for p in procs if p.poll() is None]
    finally:
        stop.set()
        forger_thread.join(timeout=10)
        assert len(rounds) > 10, "the forger did not run"
        for p in procs:
            p.terminate()
        for p in procs:
            p.wait(timeout=15)

    db = sqlite3.connect(runs / RUN / "results.sqlite")
    rows = db.execute("SELECT episode_id, status, record_json FROM episodes WHERE run_id = ?", (RUN,)).fetchall()
    db.close()
    assert sorted(r[0] for r in rows) == sorted(s.episode_id for s in specs)  # once each (primary key)
    assert all(r[1] == "finished" for r in rows)
    assert not any("forge" in r[2] for r in rows), "a forged result or action reached a stored record"
    secrets = [(certs / f"{i}.key").read_text().splitlines()[1] for i in ("world", "agent-uav", "evaluator", "orchestrator")]
    texts = [p.read_text() for p in logs.glob("*.log")] + [out.stdout, out.stderr] + [r[2] for r in rows]
    texts += [c.decode(errors="replace") for c in cmdlines]
    assert not any(s in t for s in secrets for t in texts)
