"""The one shape of every agos process: ``main(settings) -> int`` around a stop flag.

SIGINT and SIGTERM set the flag; loops poll it between bounded waits, close their session and
return. Linux children also ask the kernel to SIGTERM them if their parent dies, so a killed
launcher leaves nothing behind.
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


class StopFlag:
    def __init__(self) -> None:
        self._event = threading.Event()

    def set(self, *_: object) -> None:
        self._event.set()

    def is_set(self) -> bool:
        return self._event.is_set()

    def wait(self, timeout_s: float) -> bool:
        return self._event.wait(timeout_s)


def install_stop_handlers() -> StopFlag:
    flag = StopFlag()
    signal.signal(signal.SIGINT, flag.set)
    signal.signal(signal.SIGTERM, flag.set)
    return flag


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
