"""Every failure of a VLM endpoint is one console line (issue 31, item 6): ``agos eval`` against a port
nothing listens on, a host name that does not resolve, a listener that never answers, the stand-in
asking for a key (unset, then wrong), a stand-in serving other models, and a stand-in that refuses
the agents' six-view requests.

The endpoint is checked before the run's plan is made (deploy/run/plan.py::check_endpoint): each
refusal exits 2 with one line on stderr, having written nothing (no run directory, no episode read
or generated) and started no other process; each case runs ``agos`` as a process, as a user does,
against real sockets on loopback (about 1 s each, mostly the interpreter starting). The last case
passes that check and fails in the agents' own preflight: the console names the agent and gives its
reason in one line. ``agos sweep`` checks the same way before its progress bar.
"""

from __future__ import annotations

import os
import socket
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest

from agos.agents.vlm.standin.server import StandinServer
from agos.deploy.run.evaluate import last_error
from agos.deploy.run.launcher import free_port
from agos.world.episodes.files import write_episodes

from support.episodes import grid_episodes

AGOS = [sys.executable, "-m", "agos.deploy.cli"]
MODEL = "agos-standin"
KEY_ENV = "AGOS_E2E_ENDPOINT_KEY"
KEY = "sk-e2e-endpoint-key"


@pytest.fixture(scope="module")
def endpoints() -> Iterator[dict[str, str]]:
    """Base URLs: ``closed`` (bound, never listening: refused), ``silent`` (listening, never answering),
    ``unresolvable`` (a .invalid host), ``keyed`` (the stand-in asking for KEY), ``others`` (a stand-in
    serving other models)."""
    closed, silent = socket.socket(), socket.socket()
    closed.bind(("127.0.0.1", 0))
    silent.bind(("127.0.0.1", 0))
    silent.listen()
    keyed = StandinServer(models=(MODEL,), api_key=KEY).start()
    others = StandinServer(models=("qwen-a", "qwen-b")).start()
    try:
        yield {"closed": f"http://127.0.0.1:{closed.getsockname()[1]}/v1",
               "silent": f"http://127.0.0.1:{silent.getsockname()[1]}/v1",
               "unresolvable": "http://agos-no-such-endpoint.invalid:8000/v1", "keyed": keyed.url, "others": others.url}
    finally:
        keyed.close()
        others.close()
        closed.close()
        silent.close()


def _port(url: str) -> str:
    return url.rsplit(":", 1)[1].split("/")[0]


# name: (endpoint, flags, environment, words the line must hold; {url}/{port} filled in)
CASES = {
    "refused": ("closed", (), {}, ("connection refused: nothing listens on 127.0.0.1:{port}", "or fix --vlm-base-url")),
    "unresolvable": ("unresolvable", (), {}, ("cannot resolve the host name 'agos-no-such-endpoint.invalid'",
                                              "fix --vlm-base-url")),
    "timeout": ("silent", ("--vlm-timeout", "1"), {}, ("accepted the connection but did not answer /models within 1 s",
                                                       "raise --vlm-timeout")),
    "key_unset": ("keyed", ("--vlm-api-key-env", KEY_ENV), {}, ("{url} answered 401 Unauthorized",
                                                                f"it needs an API key and {KEY_ENV} is not set",
                                                                f"export {KEY_ENV}=<key>")),
    "key_wrong": ("keyed", ("--vlm-api-key-env", KEY_ENV), {KEY_ENV: "sk-not-the-key"},
                  ("{url} answered 401 Unauthorized", f"it refused the API key in {KEY_ENV} (set)")),
    "model": ("others", (), {}, (f"model '{MODEL}' is not served there; its /models lists: qwen-a, qwen-b",
                                 "pick one with --model")),
}


def _agos(*args: str | Path, env: dict[str, str] | None = None, cwd: Path | None = None) -> subprocess.CompletedProcess:
    """``agos ARGS`` as a process, without KEY_ENV unless ``env`` sets it."""
    environ = {k: v for k, v in os.environ.items() if k != KEY_ENV} | (env or {})
    return subprocess.run([*AGOS, *map(str, args)], env=environ, cwd=cwd, capture_output=True, text=True, timeout=120)


@pytest.mark.e2e
@pytest.mark.parametrize("name", list(CASES))
def test_an_endpoint_failure_is_one_line_before_anything_starts(endpoints, tmp_path: Path, name: str) -> None:
    endpoint, flags, env, says = CASES[name]
    url = endpoints[endpoint]
    run_dir = tmp_path / "run"
    result = _agos("eval", "--policy", "agos-agent", "--vlm-base-url", url, "--model", MODEL, "--run-dir", run_dir,
                   *flags, env=env, cwd=tmp_path)
    assert result.returncode == 2, result.stdout + result.stderr
    lines = result.stderr.splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"eval error: VLM endpoint {url}"), result.stderr
    for words in says:
        assert words.format(url=url, port=_port(url)) in lines[0], (words, lines[0])
    assert result.stdout == ""
    assert not run_dir.exists()  # refused before the plan: nothing written, no episode read or built
    assert KEY not in result.stderr and "sk-not-the-key" not in result.stderr


@pytest.mark.e2e
def test_a_sweep_refuses_an_endpoint_before_its_progress_bar(endpoints, tmp_path: Path) -> None:
    split = tmp_path / "eps.jsonl"
    write_episodes(split, grid_episodes()[:1])
    url = endpoints["others"]
    out = _agos("sweep", "--split", split, "--out", tmp_path / "sweep", "--policy", "agos-agent", "--vlm-base-url", url,
                "--model", MODEL, cwd=tmp_path)
    assert out.returncode == 2 and len(out.stderr.splitlines()) == 1, out
    assert out.stderr.startswith(f"sweep error: VLM endpoint {url}: model '{MODEL}' is not served there"), out
    assert not out.stdout and not (tmp_path / "sweep").exists()  # no bar drawn, nothing made


@pytest.mark.e2e
def test_the_agents_preflight_reason_is_the_console_line(tmp_path: Path) -> None:
    """The endpoint answers /models with the key, so the run starts; its agents' preflight sends a
    decision's eight or twelve images, which a server taking one refuses (the run stops before its
    episode is played, so the episode need not be solvable)."""
    split = tmp_path / "eps.jsonl"
    write_episodes(split, grid_episodes()[:1])
    with StandinServer(models=(MODEL,), api_key=KEY, max_images=1) as server:
        proc = subprocess.run([*AGOS, "eval", "--policy", "agos-agent", "--vlm-base-url", server.url, "--model", MODEL,
                               "--vlm-api-key-env", KEY_ENV, "--split", str(split), "--run-dir", str(tmp_path / "run"),
                               "--port", str(free_port(24000 + os.getpid() % 400))],
                              cwd=tmp_path, env={**os.environ, KEY_ENV: KEY}, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 1, proc.stdout + proc.stderr
    assert f"VLM endpoint: {server.url} serves {MODEL} (API key from {KEY_ENV})" in proc.stdout
    [line] = [line for line in proc.stdout.splitlines() if "process exited early" in line]
    assert line.startswith("process exited early: agent-u") and "(exit 3): VLM preflight failed: " in line, line
    assert "HTTP 400: At most 1 image(s) may be provided in one prompt" in line, line
    assert "refused a request like a u" in line and "--limit-mm-per-prompt" in line, line  # the hint's own line, joined
    assert KEY not in proc.stdout + proc.stderr


def test_last_error_joins_a_records_continuation_lines_and_leaves_tracebacks_out(tmp_path: Path) -> None:
    log = tmp_path / "agent-uav.log"
    log.write_text("===== agos agent started 2026-11-26 10:00:00 =====\n"
                   "2026-11-26 10:00:01,000 agent-uav[1] ERROR agos.agent: an earlier run's error\n"
                   "===== agos agent started 2026-11-26 10:05:00 =====\n"
                   "2026-11-26 10:05:01,000 agent-uav[2] INFO agos.agent: starting\n"
                   "2026-11-26 10:05:02,000 agent-uav[2] ERROR agos.agent: VLM preflight failed: HTTP 400: too many\n"
                   "images: the hint on its own line\n"
                   "Traceback (most recent call last):\n"
                   '  File "x.py", line 1, in <module>\n'
                   "2026-11-26 10:05:03,000 agent-uav[2] INFO agos.agent: stopping\n")
    assert last_error(log) == "VLM preflight failed: HTTP 400: too many images: the hint on its own line"
    log.write_text(log.read_text() + "===== agos agent started 2026-11-26 10:09:00 =====\n")
    assert last_error(log) is None and last_error(tmp_path / "missing.log") is None
