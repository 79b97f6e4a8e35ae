"""How a child process died, in words: its signal by name or its exit code, and the last lines of its log.

``agos eval``/``demo`` (deploy/run/launcher.py, :class:`~agos.deploy.run.launcher.Deaths`) and the
process pool of ``agos sweep`` and ``agos episodes split`` (:func:`agos.runtime.process.interruptible_imap`)
say once, for each process they started that ended by a signal or a non-zero exit while they still
needed it, which one, how, and what its log said last. A process killed by a fatal signal has written
Python's fault handler's traceback there first (:func:`agos.runtime.process.enable_fault_handler`), so
for those the lines shown are that traceback's head and the innermost frames of the thread that
took the signal, rather than the log's very last lines (the outermost frames of the main thread).
"""

from __future__ import annotations

import signal
from pathlib import Path

TAIL_LINES = 10
"""How many lines of a dead process's log are shown."""
TAIL_WIDTH = 160
"""Longer lines are cut in the middle (a frame's path is long; its line number and function are at the end)."""
TAIL_BYTES = 65_536
"""How much of the end of a log is read."""
START_MARK = "===== agos "
"""How a launcher marks each start of a process in its (appended) log: the lines before the latest belong
to an earlier attempt."""
FATAL_MARK = "Fatal Python error: "
"""The fault handler's first line (runtime/process.py: :func:`~agos.runtime.process.enable_fault_handler`)."""


def signal_name(signum: int) -> str:
    """``SIGSEGV``; ``signal 99`` for a number Python does not name."""
    try:
        return signal.Signals(signum).name
    except ValueError:
        return f"signal {signum}"


def ended_how(returncode: int) -> str:
    """A process's end in words, from its exit status as :mod:`subprocess` and :mod:`multiprocessing`
    give it (negative: killed by that signal): ``killed by SIGSEGV (Segmentation fault)``, ``exited
    with code 3``; a code above 128 that a shell gives a command a signal ended is said to be one too."""
    if returncode < 0:
        signum = -returncode
        words = signal.strsignal(signum) if signum < signal.NSIG else None
        return f"killed by {signal_name(signum)}" + (f" ({words})" if words else "")
    if 128 < returncode < 128 + signal.NSIG:
        try:
            name = signal.Signals(returncode - 128).name
        except ValueError:
            return f"exited with code {returncode}"
        return f"exited with code {returncode} (128 + {name}: a signal, as a shell reports it)"
    return f"exited with code {returncode}"


def short_how(returncode: int) -> str:
    """The same in a word or two, for a list of processes: ``SIGSEGV``, ``exit 3``."""
    return signal_name(-returncode) if returncode < 0 else f"exit {returncode}"


def trim(line: str, width: int = TAIL_WIDTH) -> str:
    """``line`` without its trailing space, cut in the middle to ``width`` characters at most."""
    line = line.rstrip()
    if len(line) <= width:
        return line
    keep = width - 3
    return f"{line[: keep // 2]} … {line[len(line) - (keep - keep // 2):]}"


def log_tail(log: Path | None, lines: int = TAIL_LINES, width: int = TAIL_WIDTH) -> list[str]:
    """What a dead process's log says last, since its latest start (``START_MARK``), each line trimmed,
    blank lines left out: the fault handler's first line and the innermost frames of the thread that
    took the signal when it wrote a traceback, else the last ``lines`` lines. [] without a log."""
    if log is None:
        return []
    try:
        with log.open("rb") as f:
            f.seek(max(0, f.seek(0, 2) - TAIL_BYTES))
            text = f.read().decode(errors="replace")
    except OSError:
        return []
    found = text.splitlines()
    starts = [i for i, line in enumerate(found) if line.startswith(START_MARK)]
    found = [line for line in found[starts[-1] + 1 if starts else 0:] if line.strip()]
    fatal = [i for i, line in enumerate(found) if line.startswith(FATAL_MARK)]
    if fatal:
        dump = found[fatal[-1]:]
        current = next((i for i, line in enumerate(dump) if line.startswith("Current thread ")), None)
        if current is None:  # one thread: "Stack (most recent call first):"
            picked = dump
        else:
            frames = [line for line in dump[current + 1:] if line.startswith("  ")]
            picked = [dump[0], dump[current], *frames]
        return [trim(line, width) for line in picked[:lines]]
    return [trim(line, width) for line in found[-lines:]]


def death_lines(name: str, returncode: int, log: Path | None, tail: list[str] | None = None) -> list[str]:
    """A dead process in plain lines: ``NAME died: HOW; the last lines of LOG:`` and the log's lines,
    indented (``tail``: those lines, else read now with :func:`log_tail`)."""
    tail = log_tail(log) if tail is None else tail
    head = f"{name} died: {ended_how(returncode)}"
    if tail and log is not None:
        return [f"{head}; the last lines of {log}:", *(f"    {line}" for line in tail)]
    if log is not None:
        return [f"{head}; its log {log} says nothing"]
    return [head]


class ChildDied(RuntimeError):
    """A worker process a command needed ended by a signal or a non-zero exit (or before it finished
    what it was given): its name, exit status (negative: the signal) and log (None: it wrote to this
    process's own output)."""

    def __init__(self, name: str, returncode: int, log: Path | None = None) -> None:
        self.name, self.returncode, self.log = name, returncode, log
        self.tail = log_tail(log)
        super().__init__("\n".join(death_lines(name, returncode, log, self.tail)))
