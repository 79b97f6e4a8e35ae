"""``agos view FILE.rrd``: open a recording in the rerun viewer, or say how to where there is no screen.

The viewer is the ``rerun`` command that the ``rerun-sdk`` dependency installs beside ``agos``.
Without a display (no ``DISPLAY`` or ``WAYLAND_DISPLAY`` on Linux) it prints one line: how to open
the file on a desktop, with the rerun version that wrote it (a viewer reads files of its own
version), or in a browser with ``--web``: rerun's web viewer served on loopback until Ctrl-C
(reach it from another machine through an SSH tunnel). docs/images/rerun_recording.png is that
web viewer, in headless Chromium with a software rasterizer.

The web viewer needs two ports, the page's (``--web-port``, 9090) and the one it reads the recording
from (``--grpc-port``, 9876); a port already taken is one line naming the process that holds it, exit
2, before anything starts. The viewer is a child process: Ctrl-C or SIGTERM to ``agos view`` stops it
too (a viewer left behind would keep both ports).
"""

from __future__ import annotations

import contextlib
import importlib.metadata
import importlib.util
import os
import shutil
import signal
import subprocess
import sys
import tempfile
from pathlib import Path

from agos.deploy.ops.ports import port_free, port_holder

RRD_MAGIC = b"RRF2"
MCAP_MAGIC = b"\x89MCAP0\r\n"
"""The first bytes of an MCAP file (``agos record --format mcap``), which this viewer does not open."""
STOP_GRACE_S = 5.0
"""How long the viewer has to exit after it is told to, before it is killed."""


def has_display() -> bool:
    """Whether a window can be opened here."""
    if sys.platform.startswith("linux"):
        return bool(os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))
    return True  # macOS and Windows desktops


def viewer() -> str | None:
    """The rerun viewer installed with this agos: the binary of its ``rerun_cli`` package (the ``rerun``
    script beside Python only starts that as a child of its own and passes no signal on), else the
    ``rerun`` command next to this Python, else one on PATH."""
    package = importlib.util.find_spec("rerun_cli")
    if package is not None and package.origin:
        binary = Path(package.origin).parent / "rerun"
        if binary.is_file() and os.access(binary, os.X_OK):
            return str(binary)
    beside = Path(sys.executable).parent / "rerun"
    return str(beside) if beside.exists() else shutil.which("rerun")


def busy_port(ports: dict[int, str]) -> str | None:
    """The line for the first of ``ports`` (port -> the flag that moves it) that is taken, or None."""
    for port, flag in ports.items():
        if not port_free(port):
            holder = port_holder(port)
            return (f"agos view: port {port} is busy, held by {holder or 'another process'}; stop it or give {flag} N "
                    "for another port")
    return None


def run_viewer(argv: list[str]) -> int:
    """Run the viewer ``argv`` until it exits, Ctrl-C (130) or SIGTERM (143), never leaving it behind: it
    runs in a process group of its own, and the whole group is stopped (a wrapper's child too). A viewer
    that fails on its own has its last line of output printed."""
    stopped: list[int] = []
    proc: subprocess.Popen | None = None

    def stop(signum: int, _frame: object) -> None:
        stopped.append(signum)
        if proc is not None:
            _signal_group(proc, signal.SIGTERM)

    # Both signals are noted rather than raised from before the viewer starts: a KeyboardInterrupt inside
    # Popen, after the fork, would lose the child, which runs in a session of its own and keeps both ports.
    previous = {signum: signal.signal(signum, stop) for signum in (signal.SIGINT, signal.SIGTERM)}
    with tempfile.TemporaryFile() as log:
        try:
            proc = subprocess.Popen(argv, stdout=subprocess.DEVNULL, stderr=log, start_new_session=True)
            if stopped:  # told to stop while it started
                _signal_group(proc, signal.SIGTERM)
            code = proc.wait()
        finally:
            for signum, handler in previous.items():
                signal.signal(signum, handler)
            if proc is not None:
                _signal_group(proc, signal.SIGTERM)  # what the viewer started goes too, even once it has exited
                try:
                    proc.wait(STOP_GRACE_S)
                except subprocess.TimeoutExpired:
                    _signal_group(proc, signal.SIGKILL)
                    proc.wait()
        if stopped:
            return 128 + stopped[0]
        if code != 0:
            log.seek(0)
            lines = [ln for ln in log.read().decode(errors="replace").splitlines() if ln.strip()]
            print(f"agos view: the rerun viewer exited {code}" + (f": {lines[-1].strip()}" if lines else ""),
                  file=sys.stderr)
        return code


def _signal_group(proc: subprocess.Popen, signum: int) -> None:
    """Send ``signum`` to the process group ``proc`` leads (none left: nothing to do)."""
    with contextlib.suppress(ProcessLookupError, PermissionError):
        os.killpg(proc.pid, signum)


def main(path: Path, *, web: bool = False, web_port: int = 9090, grpc_port: int = 9876) -> int:
    if not path.is_file():
        print(f"agos view: no file {path}", file=sys.stderr)
        return 2
    with path.open("rb") as f:
        magic = f.read(len(MCAP_MAGIC))
    if magic == MCAP_MAGIC:
        print(f"agos view: {path} is an MCAP recording: open it in Foxglove (File > Open local file)", file=sys.stderr)
        return 2
    if magic[:4] != RRD_MAGIC:
        print(f"agos view: {path} is not a rerun recording (.rrd)", file=sys.stderr)
        return 2
    command = viewer()
    if web and command is not None:
        busy = busy_port({web_port: "--web-port", grpc_port: "--grpc-port"})
        if busy is not None:
            print(busy, file=sys.stderr)
            return 2
        print(f"rerun's web viewer of {path.name}: http://127.0.0.1:{web_port}/?url=rerun%2Bhttp%3A%2F%2F127.0.0.1"
              f"%3A{grpc_port}%2Fproxy (Ctrl-C stops it)", flush=True)
        return run_viewer([command, "--web-viewer", str(path), "--bind", "127.0.0.1", "--web-viewer-port", str(web_port),
                           "--port", str(grpc_port)])
    if not has_display() or command is None:
        print(f"no display here: `agos view --web {path}` serves it to a browser, or on a desktop "
              f"`pip install rerun-sdk=={importlib.metadata.version('rerun-sdk')}` and run `rerun {path.name}` "
              f"(copy {path.resolve()} there first)")
        return 0
    return run_viewer([command, str(path)])
