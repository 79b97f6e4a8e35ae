"""A command started as a terminal starts it, and Ctrl-C sent to it as a terminal sends it (issue 30,
item 3): for the tests that interrupt ``agos`` commands (tests/test_ctrl_c.py, tests/test_e2e_dataset.py)."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

AGOS = [sys.executable, "-m", "agos.deploy.cli"]
HANG_BOUND_S = 60.0
"""A hang, not a speed: a command still running this long after Ctrl-C does not stop. Issue 30 asks
every command to stop within 10 s; the tests print how long each took (0.1-4.7 s at load 6-12 on 2
cores: docs/ARCHITECTURE.md), and fail only on a command that does not stop."""


def descendants(pid: int) -> list[int]:
    """Every process below ``pid`` (its children, theirs ...), from /proc."""
    children: dict[int, list[int]] = {}
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                parent = int((entry / "stat").read_text().rsplit(")", 1)[1].split()[1])
            except (OSError, IndexError, ValueError):
                continue
            children.setdefault(parent, []).append(int(entry.name))
    found, todo = [], [pid]
    while todo:
        for child in children.get(todo.pop(), []):
            found.append(child)
            todo.append(child)
    return found


def importing(pid: int) -> bool:
    """Whether ``pid`` has loaded a compiled module from the environment's site-packages: the agos
    command's imports, all inside its Ctrl-C guard (deploy/cli/__init__.py), have begun."""
    try:
        maps = Path(f"/proc/{pid}/maps").read_text()
    except OSError:
        return False
    return any("site-packages" in line and ".so" in line for line in maps.splitlines())


def alive(pid: int) -> bool:
    """Whether ``pid`` runs (a zombie waiting for its parent does not)."""
    try:
        return (Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]) != "Z"
    except OSError:
        return False


class Interruptible:
    """``agos ARGV`` in ``cwd``, in a process group of its own with SIGINT's default disposition restored
    (a non-interactive shell starts background jobs with SIGINT ignored, and pytest may run under one);
    its output in ``cwd/out.txt`` and ``cwd/err.txt``."""

    def __init__(self, cwd: Path, argv: list[str]) -> None:
        self.cwd, self.started = cwd, time.monotonic()
        with (cwd / "out.txt").open("wb") as out, (cwd / "err.txt").open("wb") as err:
            self.proc = subprocess.Popen([*AGOS, *argv], cwd=cwd, stdout=out, stderr=err, stdin=subprocess.DEVNULL,
                                         process_group=0,
                                         preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))

    def out(self) -> str:
        return (self.cwd / "out.txt").read_text()

    def err(self) -> str:
        return (self.cwd / "err.txt").read_text()

    def after(self, seconds: float) -> Callable[[], bool]:
        """A moment: ``seconds`` after the command's own imports began (:func:`importing`): a SIGINT
        before that ends any Python with -2 before a line of agos runs, and a loaded CI machine can take
        over a second to get there."""
        began: list[float] = []

        def moment() -> bool:
            if not began and importing(self.proc.pid):
                began.append(time.monotonic())
            return bool(began) and time.monotonic() - began[0] >= seconds

        return moment

    def wait_for(self, moment: Callable[[], bool], timeout_s: float = 120.0) -> None:
        """Until ``moment()``; fails if the command exits first or the moment does not come."""
        deadline = time.monotonic() + timeout_s
        while not moment():
            assert self.proc.poll() is None, f"exited {self.proc.returncode} before its moment: {self.err()[-2000:]}"
            assert time.monotonic() < deadline, f"no moment in {timeout_s:.0f} s: {self.out()[-1000:]} {self.err()[-1000:]}"
            time.sleep(0.05)

    def ctrl_c(self) -> float:
        """SIGINT to the group, as a terminal sends it; checks exit 130 (within ``HANG_BOUND_S``), no
        traceback, and nothing left running that the command started; the seconds it took to stop."""
        below = descendants(self.proc.pid)
        sent = time.monotonic()
        os.killpg(self.proc.pid, signal.SIGINT)
        try:
            self.proc.wait(timeout=HANG_BOUND_S)
        except subprocess.TimeoutExpired:
            raise AssertionError(f"still running {HANG_BOUND_S:.0f} s after Ctrl-C: {self.err()[-2000:]}") from None
        finally:
            if self.proc.poll() is None:
                os.killpg(self.proc.pid, signal.SIGKILL)
        took = time.monotonic() - sent
        assert self.proc.returncode == 130, f"exit {self.proc.returncode}: {self.err()[-2000:]}"
        assert "Traceback" not in self.err(), self.err()[-3000:]
        # what it started ends soon after it (a multiprocessing resource tracker once its pipe closes);
        # HANG_BOUND_S only tells one that never does from a slow machine's
        deadline = time.monotonic() + HANG_BOUND_S
        while (left := [pid for pid in below if alive(pid)]) and time.monotonic() < deadline:
            time.sleep(0.1)
        assert not left, f"left running: {[Path(f'/proc/{p}/cmdline').read_bytes() for p in left]}"
        return took
