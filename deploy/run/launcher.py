"""Starts agos processes as children (the no-Docker local launcher) and stops them all.

Each child runs ``python -m agos.deploy.cli ...`` in its own session (a terminal Ctrl-C
reaches only the launcher, which then stops the children in order) with its output in
``<log_dir>/<name>.log``. On Linux a child also dies with its parent. A child's settings travel in
its environment (deploy/run/children.py), its command line holds only the command's arguments.

While a run goes on, :class:`Deaths` says once for each child that ended by a signal or a non-zero exit
which one, how (the signal by name, the exit code) and the last lines of its log (runtime/deaths.py);
children this process stops itself at the end are not its business.

Once this process is asked to stop (Ctrl-C while a run starts), it starts no more children and waits
for no more listeners: :meth:`Launcher.start` and :func:`wait_listening` raise
:class:`~agos.runtime.process.Interrupted`, and the caller stops the children already started.
"""

from __future__ import annotations

import logging
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

from rich.console import Console
from rich.markup import escape

from agos.deploy.run.children import child_environ
from agos.runtime.deaths import ended_how, log_tail
from agos.runtime.process import Interrupted, die_with_parent, stop_requested
from agos.runtime.settings import AgosConfig

log = logging.getLogger("agos.launcher")

STOP_GRACE_S = 8.0
"""How long the children have, together, to exit after SIGTERM before each one left is killed."""
ROUTER_PORT = 7447
"""The router port a local run prefers (zenoh's default), else a free one."""
ROUTER_START_S = 15.0
"""How long a local run waits for its router to listen."""
SERVER_START_S = 30.0
"""How long a local run waits for a server child (the VLM stand-in, a human console) to listen."""


class Launcher:
    def __init__(self, log_dir: Path | None) -> None:
        """``log_dir`` None: a launcher that will start nothing (attach mode)."""
        self.log_dir = log_dir or Path(".")
        if log_dir is not None:
            log_dir.mkdir(parents=True, exist_ok=True)
        self.children: dict[str, subprocess.Popen] = {}

    def start(self, name: str, args: list[str], settings: AgosConfig | None = None) -> subprocess.Popen:
        """Start ``agos ARGS`` as ``name``. ``settings``: the child's settings, which reach it as its
        environment (:func:`~agos.deploy.run.children.child_environ`; credentials travel there, never
        in ``args``, which any user can read in a process listing); None: it inherits this process's.
        :class:`~agos.runtime.process.Interrupted` instead once this process was asked to stop."""
        if stop_requested():
            raise Interrupted(f"stopped before starting {name}")
        # Appended, never truncated: a resumed run keeps the logs of its earlier attempts.
        out = (self.log_dir / f"{name}.log").open("ab")
        out.write(f"===== agos {args[0]} started {time.strftime('%Y-%m-%d %H:%M:%S')} =====\n".encode())
        out.flush()
        proc = subprocess.Popen([sys.executable, "-m", "agos.deploy.cli", *args], stdout=out,
                                stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL, start_new_session=True,
                                preexec_fn=die_with_parent,
                                env=None if settings is None else child_environ(settings, os.environ))
        out.close()
        self.children[name] = proc
        return proc

    def log_path(self, name: str) -> Path:
        """Where child ``name`` writes its output."""
        return self.log_dir / f"{name}.log"

    def dead(self) -> dict[str, int]:
        """Children that have exited, with their exit codes."""
        return {n: p.returncode for n, p in self.children.items() if p.poll() is not None}

    def stop_all(self, order: list[str] | None = None, grace_s: float = STOP_GRACE_S) -> None:
        names = order or list(reversed(self.children))
        for name in names:
            proc = self.children.get(name)
            if proc is not None and proc.poll() is None:
                proc.send_signal(signal.SIGTERM)
        deadline = time.monotonic() + grace_s
        for name in names:
            proc = self.children.get(name)
            if proc is None:
                continue
            try:
                proc.wait(timeout=max(0.1, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                log.warning("%s did not stop in %.0f s; killing it", name, grace_s)
                proc.kill()
                proc.wait()


def print_death(console: Console, name: str, returncode: int, log: Path | None, tail: list[str] | None = None,
                note: str = "") -> None:
    """One short block for a process that died: ``NAME died: HOW`` (red) and the last lines of its log
    (dim, indented; ``tail``: those lines, else read from ``log`` now). ``note``: what it means for the run."""
    tail = log_tail(log) if tail is None else tail
    where = f"; the last lines of {log}:" if tail and log is not None else (f"; its log {log} says nothing" if log else "")
    console.print(f"[bold red]{escape(name)} died:[/] [red]{escape(ended_how(returncode))}[/]{escape(note)}"
                  f"{escape(where)}", highlight=False)
    for line in tail:
        console.print(f"[dim]    {escape(line)}", highlight=False)


class Deaths:
    """Says, once for each, which children of ``launchers`` ended by a signal or a non-zero exit
    (:func:`print_death`); ``notes``: what a child's death means for the run, by name."""

    def __init__(self, *launchers: Launcher | None, notes: dict[str, str] | None = None) -> None:
        self.launchers = [launcher for launcher in launchers if launcher is not None]
        self.notes = notes or {}
        self.said: set[int] = set()  # the pids already reported

    def report(self, console: Console) -> None:
        for launcher in self.launchers:
            for name, proc in launcher.children.items():
                code = proc.poll()
                if code is None or code == 0 or proc.pid in self.said:
                    continue
                self.said.add(proc.pid)
                print_death(console, name, code, launcher.log_path(name), note=self.notes.get(name, ""))


def free_port(preferred: int = ROUTER_PORT, host: str = "127.0.0.1") -> int:
    """``preferred`` if nothing listens there, else a free port chosen by the kernel."""
    for port in (preferred, 0):
        with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as sock:
            try:
                sock.bind((host, port))
            except OSError:
                continue
            return sock.getsockname()[1]
    raise RuntimeError("no free TCP port")


def wait_listening(host: str, port: int, timeout_s: float) -> bool:
    """Whether something listens on ``host:port`` within ``timeout_s``; :class:`~agos.runtime.process.Interrupted`
    as soon as this process is asked to stop."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if stop_requested():
            raise Interrupted(f"stopped while waiting for {host}:{port}")
        with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as sock:
            sock.settimeout(0.2)
            if sock.connect_ex((host, port)) == 0:
                return True
        time.sleep(0.05)
    return False
