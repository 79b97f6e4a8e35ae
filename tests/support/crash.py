"""Functions for process-pool tests (runtime/process.py: ``interruptible_imap``), importable by a spawned worker."""

from __future__ import annotations

import os
import signal


def segfault_on(item: int) -> int:
    """``item`` back, except 1: the worker kills itself with SIGSEGV (as a crash in native code ends it)."""
    if item == 1:
        os.kill(os.getpid(), signal.SIGSEGV)
    return item


def fail_on(item: int) -> int:
    """``item`` back, except 1: ValueError."""
    if item == 1:
        raise ValueError("item 1 is refused")
    return item
