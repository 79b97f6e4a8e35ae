"""The one shape of every agos process: ``main(settings) -> int`` around a stop flag.

SIGINT and SIGTERM set the flag; loops poll it between bounded waits, close their session and
return. A wait the process cannot bound itself (opening a zenoh session, runtime/bus.py) asks
:func:`stop_requested` and raises :class:`Interrupted`, which the ``agos`` command answers with exit
130 as it does Ctrl-C anywhere else. A process whose unfinished work is worth nothing (a world
worker: an interrupted episode is never submitted) can also be told to end itself a few seconds after
the signal, should a long computation keep it from looking at the flag. Linux children also ask the
kernel to SIGTERM them if their parent dies, so a killed launcher leaves nothing behind.

Every process writes Python's fault handler's traceback where it logs (:func:`enable_fault_handler`,
from :func:`setup_logging` and the ``agos`` command itself) when a fatal signal (SIGSEGV, SIGBUS,
SIGFPE, SIGILL, SIGABRT) ends it: its log file when a launcher started it, stderr in a container or
a Slurm job. The process still dies of the signal, and whoever started it says so (runtime/deaths.py).
"""

from __future__ import annotations

import contextlib
import ctypes
import faulthandler
import io
import logging
import multiprocessing
import multiprocessing.connection
import os
import signal
import sys
import threading
import time
import traceback
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import Any, NoReturn, TextIO, TypeVar

from agos.runtime.deaths import START_MARK, ChildDied

PR_SET_PDEATHSIG = 1
T = TypeVar("T")
R = TypeVar("R")


log = logging.getLogger("agos.process")


class Interrupted(KeyboardInterrupt):
    """A stop signal arrived while the process waited for something it could not give up by polling
    its flag (opening a zenoh session); the ``agos`` command exits 130, as for Ctrl-C."""


class StopFlag:
    """Set once a process is asked to stop; remembers the first signal that asked (None: set by code).
    ``exit_after_s``: end the process that long after the first signal, exit 128 + the signal, if it
    has not ended by then (:func:`install_stop_handlers`)."""

    def __init__(self, *, exit_after_s: float | None = None) -> None:
        self._event = threading.Event()
        self.signum: int | None = None
        self._exit_after_s = exit_after_s

    def set(self, signum: object = None, _frame: object = None) -> None:
        """Set the flag; as a signal handler, with the signal's number."""
        if isinstance(signum, int) and self.signum is None:
            self.signum = signum
            if self._exit_after_s is not None:
                timer = threading.Timer(self._exit_after_s, _exit_now, (signum, self._exit_after_s))
                timer.daemon = True
                timer.start()
        self._event.set()

    def is_set(self) -> bool:
        return self._event.is_set()

    def wait(self, timeout_s: float) -> bool:
        return self._event.wait(timeout_s)

    def exit_code(self) -> int:
        """What a command stopped this way exits with: 130 after Ctrl-C (SIGINT), as a shell reports a
        command it interrupted; 0 otherwise (SIGTERM is how a launcher or a container ends a service)."""
        return 128 + signal.SIGINT if self.signum == signal.SIGINT else 0


_installed: StopFlag | None = None


def install_stop_handlers(*, exit_after_s: float | None = None) -> StopFlag:
    """A :class:`StopFlag` that SIGINT and SIGTERM set. ``exit_after_s``: only for a process whose
    unfinished work is worth nothing, which then ends itself that long after the signal at the latest."""
    global _installed
    flag = _installed = StopFlag(exit_after_s=exit_after_s)
    signal.signal(signal.SIGINT, flag.set)
    signal.signal(signal.SIGTERM, flag.set)
    return flag


def stop_requested() -> bool:
    """Whether this process was asked to stop: its installed flag is set (no flag installed: False)."""
    return _installed is not None and _installed.is_set()


def _exit_now(signum: int, after_s: float) -> None:
    log.warning("still busy %.0f s after %s; exiting now (unfinished work is dropped)", after_s,
                signal.Signals(signum).name)
    logging.shutdown()
    os._exit(128 + signum)


def die_with_parent() -> None:
    """preexec hook for child processes (Linux): SIGTERM when the parent exits."""
    if sys.platform.startswith("linux"):
        with contextlib.suppress(OSError):
            ctypes.CDLL("libc.so.6", use_errno=True).prctl(PR_SET_PDEATHSIG, signal.SIGTERM)


def setup_logging(name: str, level: str = "INFO") -> logging.Logger:
    """Log records to stderr as ``TIME NAME[PID] LEVEL LOGGER: MESSAGE``; a fatal signal's traceback
    goes there too (:func:`enable_fault_handler`)."""
    logging.basicConfig(level=getattr(logging, level.upper(), logging.INFO),
                        format=f"%(asctime)s {name}[{os.getpid()}] %(levelname)s %(name)s: %(message)s")
    enable_fault_handler()
    return logging.getLogger(f"agos.{name}")


_fault_stream: TextIO | None = None
"""Where :func:`enable_fault_handler` pointed the fault handler (None: it did not)."""


def _log_stream() -> TextIO:
    """The stream the root logger writes to (its first stream or file handler with a file descriptor),
    else stderr."""
    for handler in logging.getLogger().handlers:
        stream = getattr(handler, "stream", None) if isinstance(handler, logging.StreamHandler) else None
        if stream is not None:
            with contextlib.suppress(AttributeError, ValueError, OSError):
                stream.fileno()
                return stream
    return sys.stderr


def enable_fault_handler(stream: TextIO | None = None) -> bool:
    """Write every thread's Python traceback to ``stream`` (default: where this process logs,
    :func:`_log_stream`) when a fatal signal ends the process (:mod:`faulthandler`; the process still
    dies of the signal). A fault handler that something else enabled (pytest, ``PYTHONFAULTHANDLER``,
    ``-X faulthandler``: stderr) is left alone; False then, or when the stream has no file descriptor."""
    global _fault_stream
    if faulthandler.is_enabled() and _fault_stream is None:
        return False
    target = stream if stream is not None else _log_stream()
    try:
        faulthandler.enable(file=target, all_threads=True)
    except (AttributeError, ValueError, OSError, io.UnsupportedOperation, RuntimeError):
        return False
    _fault_stream = target
    return True


class _RemoteTraceback(Exception):
    """The traceback of an exception a pool worker raised, as its ``__cause__`` (as :mod:`multiprocessing`'s pool)."""

    def __init__(self, text: str) -> None:
        super().__init__(text)
        self.text = text

    def __str__(self) -> str:
        return self.text


def _serve(conn: multiprocessing.connection.Connection, fn: Callable[[Any], Any], name: str,
           log: Path | None) -> None:
    """A pool worker: ``fn`` on each item it is sent until it is sent None. Ctrl-C is its parent's alone.
    ``log``: its output (stdout, stderr, its log records, a fault handler's traceback) is appended there."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    if log is not None:
        fd = os.open(log, os.O_WRONLY | os.O_CREAT | os.O_APPEND, 0o644)
        os.write(fd, f"{START_MARK}{name} started {time.strftime('%Y-%m-%d %H:%M:%S')} =====\n".encode())
        os.dup2(fd, 1)
        os.dup2(fd, 2)
        os.close(fd)
        setup_logging(name, "WARNING")
    else:
        enable_fault_handler()
    while True:
        try:
            item = conn.recv()
        except (EOFError, OSError):  # the parent is gone
            return
        if item is None:
            return
        try:
            reply: tuple[bool, Any, str] = (True, fn(item), "")
        except Exception as exc:
            reply = (False, exc, "".join(traceback.format_exception(exc)))
        try:
            conn.send(reply)
        except Exception as exc:  # a result or an exception that does not pickle
            conn.send((False, RuntimeError(f"{type(exc).__name__}: {exc}"), "".join(traceback.format_exception(exc))))


class _Pool:
    """``workers`` spawned processes, each fed one item at a time over its own pipe; a worker that dies
    is noticed at once (its process sentinel), never waited on as :mod:`multiprocessing`'s pool does."""

    def __init__(self, fn: Callable[[Any], Any], workers: int, name: str, log_dir: Path | None) -> None:
        ctx = multiprocessing.get_context("spawn")
        if log_dir is not None:
            log_dir.mkdir(parents=True, exist_ok=True)
        self.names = [f"{name}-{k}" for k in range(workers)]
        self.logs = [None if log_dir is None else log_dir / f"{n}.log" for n in self.names]
        self.procs: list[Any] = []
        self.conns: list[multiprocessing.connection.Connection] = []
        for k in range(workers):
            mine, theirs = ctx.Pipe()
            proc = ctx.Process(target=_serve, args=(theirs, fn, self.names[k], self.logs[k]), name=self.names[k],
                               daemon=True)
            self.procs.append(proc)
            self.conns.append(mine)
            proc.start()
            theirs.close()

    def imap_unordered(self, items: Sequence[Any]) -> Iterator[Any]:
        todo = list(reversed(items))
        busy: set[int] = set()
        for k in range(len(self.procs)):
            if todo:
                self.conns[k].send(todo.pop())
                busy.add(k)
        while busy:
            watched: dict[Any, int] = {self.conns[k]: k for k in busy} | {self.procs[k].sentinel: k for k in busy}
            for k in sorted({watched[ready] for ready in multiprocessing.connection.wait(list(watched))}):
                if not self.conns[k].poll():  # its process ended without a reply
                    self._died(k)
                try:
                    ok, value, text = self.conns[k].recv()
                except (EOFError, OSError):  # ended, the pipe closed
                    self._died(k)
                if not ok:
                    raise value from _RemoteTraceback(text)
                busy.discard(k)
                if todo:
                    self.conns[k].send(todo.pop())
                    busy.add(k)
                yield value

    def _died(self, k: int) -> NoReturn:
        """Worker ``k`` ended while it had an item: :class:`~agos.runtime.deaths.ChildDied`."""
        proc = self.procs[k]
        proc.join(5)
        code = proc.exitcode if proc.exitcode is not None else 0
        raise ChildDied(self.names[k], code, self.logs[k])

    def close(self) -> None:
        """Let every worker finish and exit (each gets None)."""
        for conn in self.conns:
            with contextlib.suppress(OSError):
                conn.send(None)
        for proc in self.procs:
            proc.join(10)
        self.terminate()

    def terminate(self) -> None:
        for proc in self.procs:
            if proc.is_alive():
                proc.terminate()
        for proc in self.procs:
            proc.join()
        for conn in self.conns:
            conn.close()


def interruptible_imap(fn: Callable[[T], R], items: Sequence[T], workers: int, *, name: str = "worker",
                       log_dir: Path | None = None) -> Iterator[R]:
    """``fn`` over ``items`` in ``workers`` spawned processes, results as they finish (any order).

    Ctrl-C is the parent's alone: the workers ignore SIGINT (one dying of its own would lose its
    item), and the parent terminates them on KeyboardInterrupt, or on any error, before it
    propagates. So a caller that keeps each result as it arrives loses only the items in flight.
    An exception ``fn`` raises is raised here (its worker's traceback as its cause); a worker that
    dies (a signal, an exit) raises :class:`~agos.runtime.deaths.ChildDied`, naming it
    (``NAME-K``), how it died and the last lines of its log. ``log_dir``: each worker's output goes to
    ``log_dir/NAME-K.log`` (its fault handler's traceback included), else to this process's own.
    Nothing is started for no items."""
    if not items:
        return
    pool = _Pool(fn, min(workers, len(items)), name, log_dir)
    try:
        yield from pool.imap_unordered(items)
        pool.close()
    except BaseException:
        pool.terminate()
        raise
