"""``agos view FILE.rrd``: open a recording in the rerun viewer, or say how to where there is no screen.

The viewer is the ``rerun`` command that the ``rerun-sdk`` dependency installs beside ``agos``.
Without a display (no ``DISPLAY`` or ``WAYLAND_DISPLAY`` on Linux) it prints one line: how to open
the file on a desktop, with the rerun version that wrote it (a viewer reads files of its own
version).
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

RRD_MAGIC = b"RRF2"


def has_display() -> bool:
    """Whether a window can be opened here."""
    if sys.platform.startswith("linux"):
        return bool(os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))
    return True  # macOS and Windows desktops


def viewer() -> str | None:
    """The ``rerun`` command installed with this agos (next to its Python), else one on PATH."""
    beside = Path(sys.executable).parent / "rerun"
    return str(beside) if beside.exists() else shutil.which("rerun")


def main(path: Path) -> int:
    import rerun

    if not path.is_file():
        print(f"agos view: no file {path}", file=sys.stderr)
        return 2
    with path.open("rb") as f:
        if f.read(4) != RRD_MAGIC:
            print(f"agos view: {path} is not a rerun recording (.rrd)", file=sys.stderr)
            return 2
    command = viewer()
    if not has_display() or command is None:
        print(f"no display here: on a desktop, `pip install rerun-sdk=={rerun.__version__}` and run "
              f"`rerun {path.name}` (copy {path.resolve()} there first)")
        return 0
    return subprocess.call([command, str(path)])
