"""A pytest plugin that keeps the unit tier honest: a test starts processes or opens sockets only if marked.

- ``@pytest.mark.e2e``: the test starts OS processes (the ``agos`` CLI, a router, services); it may also
  open sockets.
- ``@pytest.mark.loopback``: the test opens sockets inside this process only (a loopback HTTP server,
  an in-process zenoh session); it starts no process.
- Unmarked (a unit test, ``make check``): neither.

While a test's setup, call and teardown run, the plugin stands in front of every way this suite could
start a process (``subprocess.Popen``, ``os.fork``/``forkpty``, ``os.posix_spawn``/``posix_spawnp``,
``os.system``, ``multiprocessing`` ``Process.start``, which pools and executors use) or open a socket
(``socket.socket`` ``connect``/``connect_ex``/``bind``/``listen``, and ``zenoh.open``, whose sockets live
in Rust where Python cannot see them). A test that is not marked for it gets an error at the call, and
the test fails with that error even where the code under test catches it, naming the test, what it
tried and how to fix it. Session fixtures are set up inside the first test that asks for them, so they
are held to that test's marks.

tests/conftest.py loads it; ``pytest -p process_guard`` loads it into a pytester run (tests/ is on
``sys.path``), which is how tests/test_process_guard.py shows it failing a test.
"""

from __future__ import annotations

import multiprocessing.process
import os
import socket
import subprocess
import threading
from collections.abc import Iterator
from typing import Any

import pytest
import zenoh

PROCESSES = "e2e"
SOCKETS = ("e2e", "loopback")


class ProcessGuardError(RuntimeError):
    """A test not marked for it started a process or opened a socket."""


class _Guard:
    """The rule for the phase that runs now: which test, and what it may do (``None``: no test runs)."""

    def __init__(self) -> None:
        self.item: pytest.Item | None = None
        self.may_start_processes = True
        self.may_open_sockets = True
        self.violations: list[str] = []


_guard = _Guard()
_originals: list[tuple[Any, str, Any]] = []
_installs = 0


def _refuse(kind: str, what: str) -> None:
    item = _guard.item
    if item is None:
        return
    allowed = _guard.may_start_processes if kind == "process" else _guard.may_open_sockets
    if allowed:
        return
    thread = threading.current_thread()
    where = "" if thread is threading.main_thread() else f" (from thread {thread.name!r})"
    if kind == "process":
        fix = ("call the code in-process, or, where starting the process is the promise (the CLI, the "
               "services), mark the test @pytest.mark.e2e")
    else:
        fix = ("use an in-memory fake (agos.runtime.bus's in-memory bus), or mark the test "
               "@pytest.mark.loopback (sockets in this process only) or @pytest.mark.e2e (starts processes)")
    message = (f"{item.nodeid} {what}{where}, but it is not marked for it: a unit test (make check) starts no "
               f"process and opens no socket. Fix: {fix}.")
    _guard.violations.append(message)
    raise ProcessGuardError(message)


def _describe(args: Any) -> str:
    text = repr(args)
    return text if len(text) <= 200 else text[:197] + "..."


def _wrap(owner: Any, name: str, kind: str, verb: str) -> None:
    original = getattr(owner, name, None)
    if original is None:
        return

    if kind == "process" and owner is subprocess.Popen:
        def guarded(self: Any, args: Any, *rest: Any, **kwargs: Any) -> Any:
            _refuse(kind, f"started a process: subprocess.Popen({_describe(args)})")
            return original(self, args, *rest, **kwargs)
    elif owner is socket.socket:
        def guarded(self: Any, *args: Any, **kwargs: Any) -> Any:
            _refuse(kind, f"opened a socket: socket.{name}({_describe(args)[1:-1].rstrip(',')})")
            return original(self, *args, **kwargs)
    else:
        def guarded(*args: Any, **kwargs: Any) -> Any:
            _refuse(kind, f"{verb}: {name}({_describe(args)[1:-1].rstrip(',')})")
            return original(*args, **kwargs)

    guarded.__name__ = getattr(original, "__name__", name)
    guarded.__doc__ = getattr(original, "__doc__", None)
    _originals.append((owner, name, original))
    setattr(owner, name, guarded)


def _install() -> None:
    global _installs
    _installs += 1
    if _installs > 1:
        return
    _wrap(subprocess.Popen, "_execute_child", "process", "started a process")
    for name in ("fork", "forkpty", "posix_spawn", "posix_spawnp", "system"):
        _wrap(os, name, "process", f"started a process with os.{name}")
    _wrap(multiprocessing.process.BaseProcess, "start", "process", "started a multiprocessing process")
    for name in ("connect", "connect_ex", "bind", "listen"):
        _wrap(socket.socket, name, "socket", "opened a socket")
    _wrap(zenoh, "open", "socket", "opened a zenoh session (its sockets live in Rust)")


def _uninstall() -> None:
    global _installs
    _installs -= 1
    if _installs > 0:
        return
    while _originals:
        owner, name, original = _originals.pop()
        setattr(owner, name, original)


def pytest_configure(config: pytest.Config) -> None:
    _install()


def pytest_unconfigure(config: pytest.Config) -> None:
    _uninstall()


def _held(item: pytest.Item) -> Iterator[None]:
    """Runs one phase of ``item`` held to its marks; a refused call fails the phase even where it was caught."""
    marks = {mark.name for mark in item.iter_markers()}
    saved = (_guard.item, _guard.may_start_processes, _guard.may_open_sockets, _guard.violations)
    _guard.item, _guard.violations = item, []
    _guard.may_start_processes = PROCESSES in marks
    _guard.may_open_sockets = bool(marks.intersection(SOCKETS))
    violations = _guard.violations
    try:
        result = yield
    except ProcessGuardError:
        raise
    except BaseException as error:
        if violations:
            raise ProcessGuardError(violations[0]) from error
        raise
    finally:
        _guard.item, _guard.may_start_processes, _guard.may_open_sockets, _guard.violations = saved
    if violations:
        raise ProcessGuardError(violations[0])
    return result


@pytest.hookimpl(wrapper=True)
def pytest_runtest_setup(item: pytest.Item) -> Iterator[None]:
    return (yield from _held(item))


@pytest.hookimpl(wrapper=True)
def pytest_runtest_call(item: pytest.Item) -> Iterator[None]:
    return (yield from _held(item))


@pytest.hookimpl(wrapper=True)
def pytest_runtest_teardown(item: pytest.Item) -> Iterator[None]:
    return (yield from _held(item))
