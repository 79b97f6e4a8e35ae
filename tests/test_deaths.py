"""How a dead child process is said (issue 39, item 2): its signal by name or its exit code, and the last
lines of its log, once per death (runtime/deaths.py, deploy/run/launcher.py). The e2e side: a world
worker SIGSEGV'd under ``agos eval`` in tests/test_e2e_resume.py, a pool worker in tests/test_e2e_sweep.py."""

from __future__ import annotations

import faulthandler
import io
import signal
from pathlib import Path

from rich.console import Console

from agos.deploy.run.evaluate import exited_children
from agos.deploy.run.launcher import Deaths, Launcher, print_death
from agos.runtime.deaths import TAIL_WIDTH, ChildDied, death_lines, ended_how, log_tail, short_how, trim
from agos.runtime.process import enable_fault_handler

FAULT = """\
Fatal Python error: Segmentation fault

Thread 0x00007f36f31c96c0 (most recent call first):
  File "/x/threading.py", line 320 in wait
  File "/x/threading.py", line 982 in run

Current thread 0x00007f36f3e5ab80 (most recent call first):
  File "/x/world/sim/scene.py", line 410 in render
  File "/x/world/sim/sensors.py", line 58 in shoot
  File "/x/world/sim/worker.py", line 12 in main
  File "<string>", line 1 in <module>

Extension modules: numpy.core._multiarray_umath, pybullet (total: 2)
"""


def test_a_signal_is_named_and_an_exit_code_is_a_code() -> None:
    assert ended_how(-signal.SIGSEGV) == "killed by SIGSEGV (Segmentation fault)"
    assert ended_how(-signal.SIGKILL) == "killed by SIGKILL (Killed)"
    assert ended_how(-signal.SIGABRT) == "killed by SIGABRT (Aborted)"
    assert ended_how(1) == "exited with code 1" and ended_how(0) == "exited with code 0"
    assert ended_how(137) == "exited with code 137 (128 + SIGKILL: a signal, as a shell reports it)"
    assert ended_how(255) == "exited with code 255"
    assert ended_how(-40).startswith("killed by signal 40")  # a real-time signal has no name of its own
    assert (short_how(-signal.SIGSEGV), short_how(3)) == ("SIGSEGV", "exit 3")


def test_the_tail_is_the_latest_starts_last_lines_trimmed(tmp_path: Path) -> None:
    log = tmp_path / "world-0.log"
    earlier = "===== agos world started 2026-01-01 10:00:00 =====\nan earlier attempt's line\n"
    lines = [f"2026-01-01 10:05:{k:02d},000 world[7] INFO agos.world: line {k}" for k in range(15)]
    log.write_text(earlier + "===== agos world started 2026-01-01 10:05:00 =====\n" + "\n\n".join(lines) + "\n")
    assert log_tail(log) == lines[-10:]  # blank lines left out
    assert log_tail(log, lines=3) == lines[-3:]
    log.write_text(earlier + "===== agos world started 2026-01-01 10:06:00 =====\n" + "x" * 500 + "\n")
    [long] = log_tail(log)
    assert len(long) == TAIL_WIDTH and long.startswith("x") and " … " in long
    assert trim("short   ") == "short" and len(trim("y" * 161)) == TAIL_WIDTH
    assert log_tail(tmp_path / "missing.log") == [] and log_tail(None) == []


def test_a_fault_handlers_traceback_shows_the_thread_that_took_the_signal(tmp_path: Path) -> None:
    log = tmp_path / "world-0.log"
    log.write_text("===== agos world started 2026-01-01 10:05:00 =====\n2026-01-01 10:05:01,000 world[7] INFO x: ok\n"
                   + FAULT)
    assert log_tail(log) == ["Fatal Python error: Segmentation fault",
                             "Current thread 0x00007f36f3e5ab80 (most recent call first):",
                             '  File "/x/world/sim/scene.py", line 410 in render',
                             '  File "/x/world/sim/sensors.py", line 58 in shoot',
                             '  File "/x/world/sim/worker.py", line 12 in main',
                             '  File "<string>", line 1 in <module>']
    assert log_tail(log, lines=3)[-1] == '  File "/x/world/sim/scene.py", line 410 in render'
    log.write_text("Fatal Python error: Aborted\n\nStack (most recent call first):\n  File \"a.py\", line 1 in f\n")
    assert log_tail(log) == ["Fatal Python error: Aborted", "Stack (most recent call first):", '  File "a.py", line 1 in f']


def test_the_plain_text_names_the_process_how_and_the_log(tmp_path: Path) -> None:
    log = tmp_path / "sweep-0.log"
    log.write_text(FAULT)
    died = ChildDied("sweep-0", -signal.SIGSEGV, log)
    text = str(died).splitlines()
    assert text[0] == f"sweep-0 died: killed by SIGSEGV (Segmentation fault); the last lines of {log}:"
    assert text[1] == "    Fatal Python error: Segmentation fault" and died.tail[0] == text[1].strip()
    empty = tmp_path / "empty.log"
    assert death_lines("w", 3, empty) == [f"w died: exited with code 3; its log {empty} says nothing"]
    assert death_lines("w", -9, None) == ["w died: killed by SIGKILL (Killed)"]


class _Child:
    """A child process as :class:`Deaths` and :meth:`Launcher.dead` see it."""

    def __init__(self, pid: int, returncode: int | None) -> None:
        self.pid, self.returncode = pid, returncode

    def poll(self) -> int | None:
        return self.returncode


def test_each_death_is_said_once_and_exits_with_0_not_at_all(tmp_path: Path) -> None:
    launcher = Launcher(tmp_path)
    (tmp_path / "world-1.log").write_text("===== agos world started x =====\n" + FAULT)
    (tmp_path / "recorder.log").write_text("2026-01-01 10:05:01,000 record[9] ERROR x: out of disk\n")
    children = {"world-0": _Child(10, None), "world-1": _Child(11, -signal.SIGSEGV), "agent-uav": _Child(12, 0),
                "recorder": _Child(13, 1)}
    launcher.children = children  # type: ignore[assignment]
    out = io.StringIO()
    console = Console(file=out, width=300)
    deaths = Deaths(launcher, None, notes={"recorder": "; the run goes on without recording"})
    deaths.report(console)
    said = out.getvalue()
    assert f"world-1 died: killed by SIGSEGV (Segmentation fault); the last lines of {tmp_path / 'world-1.log'}:" in said
    assert "    Fatal Python error: Segmentation fault\n" in said and "line 410 in render" in said
    assert "recorder died: exited with code 1; the run goes on without recording; the last lines of " in said
    assert "out of disk" in said and "world-0" not in said and "agent-uav" not in said
    assert len(said.splitlines()) == 1 + 6 + 1 + 1  # two short blocks
    deaths.report(console)
    assert out.getvalue() == said  # once
    children["world-0"].returncode = -signal.SIGKILL
    deaths.report(console)
    assert out.getvalue()[len(said):].startswith("world-0 died: killed by SIGKILL (Killed); its log ")


def test_print_death_escapes_markup_and_the_halt_line_names_the_signal(tmp_path: Path) -> None:
    out = io.StringIO()
    print_death(Console(file=out, width=300), "agent-uav", 2, None, ["[red]not markup[/]"])
    assert out.getvalue() == "agent-uav died: exited with code 2\n    [red]not markup[/]\n"
    launcher = Launcher(tmp_path)
    launcher.children = {"evaluator": _Child(1, -signal.SIGSEGV), "world-0": _Child(2, None)}  # type: ignore[assignment]
    halt = exited_children(launcher, tmp_path)
    assert halt is not None and halt.line.startswith("[red]process exited early: evaluator (SIGSEGV); logs in ")


def test_a_fault_handler_someone_else_enabled_stays_theirs() -> None:
    assert faulthandler.is_enabled()  # pytest's, on its own stream
    assert enable_fault_handler(io.StringIO()) is False and faulthandler.is_enabled()
