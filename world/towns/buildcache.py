"""The build cache: what one process built from a town's inputs (the frozen procedural town, the rich
look's city meshes), kept on disk so that the next process reads it back instead of building it again.

An entry is named by what it was built from and lives in a folder named by :func:`code_key`, the
sha256 of every source file of ``agos.world.towns`` (this package builds everything stored here and
imports nothing else of agos that shapes its output) and of the versions of Python and of the
libraries whose arithmetic it uses. Any edit there, even a comment, gives a new folder, so a stale
entry is never read (a version constant would rely on someone remembering to bump it, and a pinned
test would then pass on the old geometry). Folders of older keys are pruned (the newest few kept).

The key is read once a process; a process whose sources change while it runs (an edit during a
test session) stores nothing more, since what it built may come from either version.

Each file is sealed: a magic line and the sha256 of the payload before the payload. A file that is
cut short, damaged or of another format reads as absent, and the caller builds again. Writers write
a private temporary file beside the entry and rename it over the entry (``os.replace``), so
concurrent processes writing the same entry race harmlessly and a reader sees a whole file or none.
Writing is best effort: a read-only cache costs the build, never an error.
"""

from __future__ import annotations

import functools
import hashlib
import os
import secrets
import shutil
import sys
from pathlib import Path

import cv2
import msgspec
import networkx as nx
import numpy as np

MAGIC = b"agos-build-cache 1\n"
KEEP_KEYS = 4
"""Code-key folders kept under ``build/`` (the current one and the most recently written others)."""
_SOURCES = Path(__file__).resolve().parent


@functools.cache
def code_key() -> str | None:
    """The key of this process's code: :func:`source_key` of ``agos.world.towns``; None where its sources
    cannot be read (an install without them), and then nothing is cached."""
    try:
        return source_key(_SOURCES)
    except OSError:
        return None


def source_key(root: Path) -> str:
    """sha256 of the sources below ``root`` (path and bytes of every ``.py`` file) and of the Python,
    numpy, networkx, OpenCV and msgspec versions."""
    sources = sorted(root.rglob("*.py"))
    if not sources:
        raise FileNotFoundError(f"no Python sources below {root}")
    h = hashlib.sha256()
    for path in sources:
        h.update(path.relative_to(root).as_posix().encode() + b"\0")
        h.update(hashlib.sha256(path.read_bytes()).digest())
    h.update("\0".join([sys.version, np.__version__, nx.__version__, cv2.__version__, msgspec.__version__]).encode())
    return h.hexdigest()


def entry_path(cache_root: Path, name: str) -> Path | None:
    """Where the entry ``name`` of the current code lives under the asset cache ``cache_root`` (None: no cache)."""
    key = code_key()
    return None if key is None else cache_root / "build" / key[:24] / name


def read_entry(path: Path | None) -> bytes | None:
    """The payload of a sealed entry, or None where it is missing, cut short or damaged."""
    if path is None:
        return None
    try:
        data = path.read_bytes()
    except OSError:
        return None
    head = len(MAGIC) + 32
    if len(data) < head or not data.startswith(MAGIC):
        return None
    payload = data[head:]
    return payload if hashlib.sha256(payload).digest() == data[len(MAGIC):head] else None


def write_entry(path: Path | None, payload: bytes) -> None:
    """Seal ``payload`` into ``path``: a temporary file of this writer's own, then renamed over the entry."""
    if path is None:
        return
    folder = path.parent
    try:
        if source_key(_SOURCES) != code_key():  # edited while this process ran: what it built may be either's
            return
        fresh = not folder.exists()
        folder.mkdir(parents=True, exist_ok=True)
        tmp = folder / f".{path.name}.{os.getpid()}.{secrets.token_hex(4)}.tmp"
        try:
            with open(tmp, "xb") as out:
                out.write(MAGIC + hashlib.sha256(payload).digest())
                out.write(payload)
            os.replace(tmp, path)
        except BaseException:
            tmp.unlink(missing_ok=True)
            raise
    except OSError:
        return
    if fresh:
        _prune(folder.parent, keep=folder)


def _prune(build_root: Path, *, keep: Path) -> None:
    """Remove code-key folders but ``keep`` and the most recently written others (another checkout or
    version sharing the cache loses at most its entries, which it builds again)."""
    try:
        others = sorted((d for d in build_root.iterdir() if d.is_dir() and d != keep),
                        key=lambda d: d.stat().st_mtime, reverse=True)
    except OSError:
        return
    for old in others[KEEP_KEYS - 1:]:
        shutil.rmtree(old, ignore_errors=True)
