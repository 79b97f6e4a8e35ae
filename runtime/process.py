"""The one shape of every agos process: ``main(settings) -> int`` around a stop flag.

SIGINT and SIGTERM set the flag; loops poll it between bounded waits, close their session and
return. A wait the process cannot bound itself (opening a zenoh session, runtime/bus.py) asks
:func:`stop_requested` and raises :class:`Interrupted`, which the ``agos`` command answers with exit
130 as it does Ctrl-C anywhere else. A process whose unfinished work is worth nothing (a world
worker: an interrupted episode is never submitted) can also be told to end itself a few seconds after
the signal, should a long computation keep it from looking at the flag. Linux children also ask the
kernel to SIGTERM them if their parent dies, so a killed launcher leaves nothing behind.
"""

from __future__ import annotations

import contextlib
import ctypes
import logging
import multiprocessing
import os
import signal
import sys
import threading
from collections.abc import Callable, Iterator, Sequence
from typing import TypeVar

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
    logging.basicConfig(level=getattr(logging, level.upper(), logging.INFO),
                        format=f"%(asctime)s {name}[{os.getpid()}] %(levelname)s %(name)s: %(message)s")
    return logging.getLogger(f"agos.{name}")


def _ignore_sigint() -> None:
    signal.signal(signal.SIGINT, signal.SIG_IGN)


def interruptible_imap(fn: Callable[[T], R], items: Sequence[T], workers: int) -> Iterator[R]:
    """``fn`` over ``items`` in ``workers`` spawned processes, results as they finish (any order).

    Ctrl-C is the parent's alone: the workers ignore SIGINT (one dying of its own would break the
    pool and leave the parent waiting), and the parent terminates them on KeyboardInterrupt, or on
    any error, before it propagates. So a caller that keeps each result as it arrives loses only
    the items in flight. Nothing is started for no items."""
    if not items:
        return
    pool = multiprocessing.get_context("spawn").Pool(min(workers, len(items)), initializer=_ignore_sigint)
    try:
        yield from pool.imap_unordered(fn, items)
        pool.close()
    except BaseException:
        pool.terminate()
        raise
    finally:
        pool.join()
