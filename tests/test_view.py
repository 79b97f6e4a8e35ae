"""``agos view``: refuses what is not a recording, says how to open one without a display, and
serves rerun's web viewer with ``--web``."""

from __future__ import annotations

import os
import socket
import subprocess
import sys
import time
from pathlib import Path

import httpx
import pytest

AGOS = [sys.executable, "-m", "agos.deploy.cli"]


@pytest.fixture
def recording(tmp_path: Path) -> Path:
    import rerun as rr

    path = tmp_path / "ep.rrd"
    rec = rr.RecordingStream("agos", recording_id="ep")
    rec.save(str(path))
    rec.set_time("decision", sequence=1)
    rec.log("log/steps", rr.TextLog("step 1"))
    rec.flush()
    rec.disconnect()
    return path


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_view_refuses_a_file_that_is_not_a_recording(tmp_path: Path, agos) -> None:
    bad = tmp_path / "x.rrd"
    bad.write_text("not rerun")
    out = agos("view", bad)
    assert out.returncode == 2 and "is not a rerun recording" in out.stderr


def test_view_without_a_display_says_how(recording: Path, agos, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    out = agos("view", recording)
    assert out.returncode == 0 and f"agos view --web {recording}" in out.stdout


@pytest.mark.e2e
def test_view_web_serves_the_web_viewer(recording: Path) -> None:
    port = _free_port()
    proc = subprocess.Popen([*AGOS, "view", "--web", "--web-port", str(port), str(recording)],
                            stdout=subprocess.PIPE, text=True, start_new_session=True)
    try:
        assert proc.stdout is not None
        assert f"http://127.0.0.1:{port}/" in proc.stdout.readline()
        deadline = time.monotonic() + 30
        while True:
            try:
                assert httpx.get(f"http://127.0.0.1:{port}/", timeout=2).status_code == 200
                break
            except httpx.TransportError:
                assert time.monotonic() < deadline, "the web viewer never answered"
                time.sleep(0.3)
    finally:
        os.killpg(proc.pid, 15)
        proc.wait(timeout=20)
