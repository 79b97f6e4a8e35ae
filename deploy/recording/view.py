"""``agos view FILE.rrd``: open a recording in the rerun viewer, or say how to where there is no screen.

The viewer is the ``rerun`` command that the ``rerun-sdk`` dependency installs beside ``agos``.
Without a display (no ``DISPLAY`` or ``WAYLAND_DISPLAY`` on Linux) it prints one line: how to open
the file on a desktop, with the rerun version that wrote it (a viewer reads files of its own
version), or in a browser with ``--web``: rerun's web viewer served on loopback until Ctrl-C
(reach it from another machine through an SSH tunnel). docs/images/rerun_recording.png is that
web viewer, in headless Chromium with a software rasterizer.
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


def main(path: Path, *, web: bool = False, web_port: int = 9090) -> int:
    import rerun

    if not path.is_file():
        print(f"agos view: no file {path}", file=sys.stderr)
        return 2
    with path.open("rb") as f:
        if f.read(4) != RRD_MAGIC:
            print(f"agos view: {path} is not a rerun recording (.rrd)", file=sys.stderr)
            return 2
    command = viewer()
    if web and command is not None:
        print(f"rerun's web viewer of {path.name}: http://127.0.0.1:{web_port}/?url=rerun%2Bhttp%3A%2F%2F127.0.0.1"
              f"%3A9876%2Fproxy (Ctrl-C stops it)", flush=True)
        try:
            return subprocess.call([command, "--web-viewer", str(path), "--bind", "127.0.0.1",
                                    "--web-viewer-port", str(web_port)], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        except KeyboardInterrupt:
            return 130
    if not has_display() or command is None:
        print(f"no display here: `agos view --web {path}` serves it to a browser, or on a desktop "
              f"`pip install rerun-sdk=={rerun.__version__}` and run `rerun {path.name}` (copy {path.resolve()} there first)")
        return 0
    return subprocess.call([command, str(path)])
