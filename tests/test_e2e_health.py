"""`agos health`: a real liveliness query for the token a process announced, on a plain and a secured bus."""

from __future__ import annotations

import os
import subprocess
import sys
import time

import pytest

from agos.deploy.ops.certs import credential_env, make_certs
from agos.deploy.run.launcher import free_port, wait_listening

pytestmark = pytest.mark.e2e
AGOS = [sys.executable, "-m", "agos.deploy.cli"]


def _health(kind: str, endpoint: str, env: dict[str, str], *extra: str) -> subprocess.CompletedProcess:
    return subprocess.run([*AGOS, "health", kind, "--connect", endpoint, "--timeout", "2", *extra], env=env,
                          capture_output=True, text=True, timeout=60)


def _wait_healthy(kind: str, endpoint: str, env: dict[str, str], timeout_s: float = 30.0) -> None:
    deadline = time.monotonic() + timeout_s
    while (out := _health(kind, endpoint, env)).returncode != 0:
        assert time.monotonic() < deadline, out.stderr
        time.sleep(0.5)


@pytest.mark.parametrize("secure", [False, True], ids=["tcp", "mtls"])
def test_health_follows_the_process_token(tmp_path, secure: bool) -> None:
    port = free_port(17500)
    env = {**os.environ, "AGOS_HEALTH_DIR": str(tmp_path / "health")}
    endpoint = f"{'tls' if secure else 'tcp'}/127.0.0.1:{port}"
    if secure:
        make_certs(tmp_path / "certs")

    def as_(identity: str) -> dict[str, str]:
        if not secure:
            return env
        return {**env, **credential_env(tmp_path / "certs", identity)}

    no_router = _health("router", endpoint, as_("router"))
    assert no_router.returncode == 1 and "no router has announced itself" in no_router.stderr
    router = subprocess.Popen([*AGOS, "router", "--listen", endpoint], env=as_("router"),
                              stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    evaluator = None
    try:
        assert wait_listening("127.0.0.1", port, 15)
        _wait_healthy("router", endpoint, as_("router"))
        evaluator = subprocess.Popen([*AGOS, "evaluator", "--connect", endpoint, "--run", "h1", "--runs-dir",
                                      str(tmp_path / "runs")], env=as_("evaluator"),
                                     stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        _wait_healthy("evaluator", endpoint, as_("evaluator"))
        assert "agos/h1/live/evaluator/main" in _health("evaluator", endpoint, as_("evaluator")).stdout
        missing = _health("world", endpoint, as_("world"), "--id", "w9", "--run", "h1")
        assert missing.returncode == 1 and "agos/h1/live/world/w9 not alive" in missing.stderr
        evaluator.kill()  # the token goes with the process; the announcement file stays
        evaluator.wait()
        deadline = time.monotonic() + 20
        while _health("evaluator", endpoint, as_("evaluator")).returncode == 0:
            assert time.monotonic() < deadline, "a dead evaluator still reads healthy"
            time.sleep(0.5)
    finally:
        for p in (evaluator, router):
            if p is not None and p.poll() is None:
                p.terminate()
                p.wait(timeout=10)
