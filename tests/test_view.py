"""``agos view``: refuses what is not a recording, says how to open one without a display, says which
process holds a port it needs, and never leaves its viewer behind (Ctrl-C, SIGTERM). The web viewer
served for real and stopped by Ctrl-C: tests/test_ctrl_c.py::test_view_web."""

from __future__ import annotations

import os
import signal
import socket
import sys
from pathlib import Path

import pytest

from support.recordings import write_tiny_recording

AGOS = [sys.executable, "-m", "agos.deploy.cli"]


@pytest.fixture
def recording(tmp_path: Path) -> Path:
    return write_tiny_recording(tmp_path / "ep.rrd")


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


@pytest.mark.loopback
def test_a_port_in_use_is_named_with_the_process_that_holds_it(recording: Path, agos) -> None:
    from agos.deploy.ops.ports import port_free, port_holder

    with socket.socket() as held:
        held.bind(("127.0.0.1", 0))
        held.listen()
        port = held.getsockname()[1]
        assert not port_free(port)
        if Path("/proc/net/tcp").exists():
            assert f"(pid {os.getpid()})" in (port_holder(port) or "")
        for flags, flag in ((("--web-port", str(port)), "--web-port"), (("--grpc-port", str(port)), "--grpc-port")):
            out = agos("view", "--web", *flags, recording)  # in this process: the viewer may not start
            assert out.returncode == 2 and not out.stdout, out
            line = out.stderr.strip()
            assert "\n" not in line and line.startswith(f"agos view: port {port} is busy, held by ") and flag in line
            if Path("/proc/net/tcp").exists():
                assert f"(pid {os.getpid()})" in line
    assert port_free(port)


class _Viewer:
    """A viewer process as ``subprocess.Popen`` gives it; ``wait`` gets the signal ``signum`` first."""

    def __init__(self, signum: int) -> None:
        self.signum, self.terminated, self.returncode = signum, 0, None

    def wait(self, timeout: float | None = None) -> int:
        if self.returncode is None:
            signal.raise_signal(self.signum)  # agos view's handler terminates us
        assert self.returncode is not None
        return self.returncode

    def poll(self) -> int | None:
        return self.returncode

    def terminate(self) -> None:
        self.terminated += 1
        if self.returncode is None:
            self.returncode = -signal.SIGTERM

    def kill(self) -> None:
        self.returncode = -signal.SIGKILL


@pytest.mark.parametrize(("signum", "code"), [(signal.SIGTERM, 143), (signal.SIGINT, 130)])
def test_sigterm_and_ctrl_c_stop_the_viewer_too(monkeypatch: pytest.MonkeyPatch, signum: int, code: int) -> None:
    """The viewer used to outlive a SIGTERM (re-parented to pid 1, holding both ports)."""
    from agos.deploy.recording import view

    viewers: list[_Viewer] = []
    monkeypatch.setattr(view.subprocess, "Popen", lambda argv, **_: viewers.append(_Viewer(signum)) or viewers[-1])
    monkeypatch.setattr(view, "_signal_group", lambda proc, _signum: proc.terminate())  # its process group
    before = signal.getsignal(signal.SIGTERM), signal.getsignal(signal.SIGINT)
    assert view.run_viewer(["rerun", "x.rrd"]) == code
    assert viewers[0].terminated and (signal.getsignal(signal.SIGTERM), signal.getsignal(signal.SIGINT)) == before


def test_a_signal_while_the_viewer_starts_stops_it_once_started(monkeypatch: pytest.MonkeyPatch) -> None:
    """Ctrl-C inside Popen (after the fork) used to raise there and lose the child: now it is noted, and
    the viewer is stopped as soon as Popen returns it."""
    from agos.deploy.recording import view

    viewers: list[_Viewer] = []

    def popen(argv, **_):
        signal.raise_signal(signal.SIGINT)  # the user's Ctrl-C, while the child starts
        viewers.append(_Viewer(signal.SIGINT))
        return viewers[-1]

    monkeypatch.setattr(view.subprocess, "Popen", popen)
    monkeypatch.setattr(view, "_signal_group", lambda proc, _signum: proc.terminate())
    assert view.run_viewer(["rerun", "x.rrd"]) == 130
    assert viewers[0].terminated
