"""Stopping the processes a test started."""

from __future__ import annotations

import subprocess


def stop_all(procs: list[subprocess.Popen]) -> None:
    """SIGTERM every process still running, then wait for each (10 s, then SIGKILL)."""
    for p in procs:
        if p.poll() is None:
            p.terminate()
    for p in procs:
        try:
            p.wait(timeout=10)
        except subprocess.TimeoutExpired:
            p.kill()
            p.wait()
