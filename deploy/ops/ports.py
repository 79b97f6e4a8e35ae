"""Is a TCP port free here, and if not, which process holds it: so a command that needs a port and
finds it taken says which process to stop instead of failing without a word.

:func:`port_free` binds the port (as the server that wants it would); :func:`port_holder` names the
process listening on it, from ``/proc`` on Linux (a process of another user, or another system: None).
"""

from __future__ import annotations

import contextlib
import os
import socket
from pathlib import Path

_LISTEN = "0A"
"""The state of a listening socket in ``/proc/net/tcp``."""


def port_free(port: int, host: str = "127.0.0.1") -> bool:
    """Whether a server could listen on ``host:port`` now."""
    with socket.socket() as s:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)  # a port in TIME_WAIT is free to a server
        try:
            s.bind((host, port))
        except OSError:
            return False
    return True


def port_holder(port: int, proc: Path = Path("/proc")) -> str | None:
    """``"<command line> (pid N)"`` of the process listening on TCP ``port``, or None when it cannot be
    told (no ``/proc``, or a socket of a process this user may not look into)."""
    inodes = _listening_inodes(port, proc)
    if not inodes:
        return None
    for pid_dir in proc.iterdir():
        if not pid_dir.name.isdigit():
            continue
        with contextlib.suppress(OSError):
            for fd in (pid_dir / "fd").iterdir():
                with contextlib.suppress(OSError):
                    if os.readlink(fd) in inodes:
                        return f"{_command_line(pid_dir)} (pid {pid_dir.name})"
    return None


def _listening_inodes(port: int, proc: Path) -> set[str]:
    """``socket:[inode]`` of every socket listening on ``port`` (IPv4 and IPv6)."""
    found = set()
    for table in ("tcp", "tcp6"):
        try:
            lines = (proc / "net" / table).read_text().splitlines()[1:]
        except OSError:
            continue
        for line in lines:
            fields = line.split()
            if len(fields) > 9 and fields[3] == _LISTEN and int(fields[1].rsplit(":", 1)[1], 16) == port:
                found.add(f"socket:[{fields[9]}]")
    return found


def _command_line(pid_dir: Path, limit: int = 100) -> str:
    """The process's command line, its program by name only (``rerun --web-viewer x.rrd ...``)."""
    try:
        words = [w.decode(errors="replace") for w in (pid_dir / "cmdline").read_bytes().split(b"\0") if w]
    except OSError:
        return "a process"
    if not words:
        return "a process"
    text = " ".join([Path(words[0]).name, *words[1:]])
    return text if len(text) <= limit else text[:limit - 3] + "..."
