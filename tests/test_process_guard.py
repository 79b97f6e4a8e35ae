"""The unit tier stays honest: tests/process_guard.py fails an unmarked test that starts a process or opens a socket.

Each case runs a small test file through pytest in this process (pytester), with the guard loaded as
tests/conftest.py loads it, and reads the outcome and the message.
"""

from __future__ import annotations

import pytest

pytest_plugins = ["pytester"]

INI = """
[pytest]
markers =
    e2e: starts processes
    loopback: sockets in this process only
"""


def _run(pytester: pytest.Pytester, body: str) -> pytest.RunResult:
    pytester.makeini(INI)
    pytester.makepyfile(test_inner="import os, socket, subprocess, sys, multiprocessing\n"
                                   "import pytest, zenoh\n\n" + body)
    return pytester.runpytest_inprocess("-p", "process_guard", "-p", "no:cacheprovider", "-q")


def test_an_unmarked_test_that_starts_a_process_fails_naming_it_and_the_fix(pytester: pytest.Pytester) -> None:
    result = _run(pytester, "def test_cli():\n"
                            "    subprocess.run([sys.executable, '-c', 'pass'], check=True)\n")
    result.assert_outcomes(failed=1)
    result.stdout.fnmatch_lines(["*test_inner.py::test_cli started a process: subprocess.Popen(*-c*pass*"
                                 "not marked for it*mark the test @pytest.mark.e2e*"])


@pytest.mark.parametrize(("what", "code"), [
    ("os.fork", "os.fork()"),
    ("multiprocessing", "multiprocessing.Process(target=print).start()"),
    ("socket.bind", "socket.socket().bind(('127.0.0.1', 0))"),
    ("socket.connect", "socket.create_connection(('127.0.0.1', 9), timeout=1)"),
    ("zenoh session", "zenoh.open(zenoh.Config())"),
])
def test_every_way_in_is_refused(pytester: pytest.Pytester, what: str, code: str) -> None:
    result = _run(pytester, f"def test_it():\n    {code}\n")
    result.assert_outcomes(failed=1)
    result.stdout.fnmatch_lines([f"*test_inner.py::test_it *{what}*not marked for it*"])


def test_a_refusal_the_code_swallows_still_fails_the_test(pytester: pytest.Pytester) -> None:
    result = _run(pytester, "def test_quiet():\n"
                            "    try:\n"
                            "        subprocess.run(['true'])\n"
                            "    except Exception:\n"
                            "        pass\n")
    result.assert_outcomes(failed=1)
    result.stdout.fnmatch_lines(["*test_inner.py::test_quiet started a process*"])


def test_a_fixture_is_held_to_the_marks_of_the_test_that_sets_it_up(pytester: pytest.Pytester) -> None:
    result = _run(pytester, "@pytest.fixture(scope='session')\n"
                            "def server():\n"
                            "    with socket.socket() as s:\n"
                            "        s.bind(('127.0.0.1', 0))\n"
                            "        yield s\n\n"
                            "def test_uses_it(server):\n"
                            "    pass\n")
    result.assert_outcomes(errors=1)
    result.stdout.fnmatch_lines(["*test_inner.py::test_uses_it opened a socket: socket.bind*"])


def test_a_loopback_test_opens_sockets_but_starts_no_process(pytester: pytest.Pytester) -> None:
    result = _run(pytester, "@pytest.mark.loopback\n"
                            "def test_spawns():\n"
                            "    subprocess.run(['true'])\n")
    result.assert_outcomes(failed=1)
    result.stdout.fnmatch_lines(["*test_inner.py::test_spawns started a process*"])


@pytest.mark.loopback
def test_a_loopback_test_may_open_a_socket(pytester: pytest.Pytester) -> None:
    result = _run(pytester, "@pytest.mark.loopback\n"
                            "def test_listens():\n"
                            "    with socket.socket() as s:\n"
                            "        s.bind(('127.0.0.1', 0))\n"
                            "        s.listen()\n")
    result.assert_outcomes(passed=1)
