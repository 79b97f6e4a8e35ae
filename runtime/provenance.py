"""What made a run or a record: the agos commit, the lock file and the versions that can move a number.

:func:`provenance` is stored in every run directory's ``run.json`` (key ``provenance``, by the process
that creates the run) and in every episode record (``EpisodeRecord.provenance``, by the process that
made the record: the world worker that played the episode, or whoever wrote a failure record). It
sits beside the episode configuration, never inside it: it is not part of ``config_hash`` and
nothing is scored from it, so the same episodes under the same configuration give the same records
whatever made them, except for this field.

The map (docs/ARCHITECTURE.md §4a)::

    {"agos": "0.1.0",                       # the installed package's version
     "commit": "391c941…" | None,           # git HEAD of the source checkout agos runs from; None when
                                            # it runs from an installed wheel (an image) or git fails
     "dirty": False | True | None,          # tracked files differ from HEAD (git describe's --dirty)
     "lock_sha256": "…" | None,             # sha256 of the uv.lock the environment was installed from
     "python": "3.11.7",
     "packages": {"eclipse-zenoh": "1.5.1", "httpx": "0.28.1", "numpy": "2.3.1",
                  "opencv-python-headless": "4.12.0.88", "pybullet": "3.2.7"}}  # + openai when installed

Computed once per process; the commit and dirty flag are read by dulwich (no git process).
"""

from __future__ import annotations

import functools
import hashlib
import os
import platform
import sys
from importlib import metadata
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from dulwich.repo import Repo


PACKAGES = ("eclipse-zenoh", "pybullet", "numpy", "opencv-python-headless", "opencv-python",
            "opencv-contrib-python-headless", "opencv-contrib-python", "httpx", "openai")
"""Distributions whose versions are recorded, those installed only: the bus, the simulator, the
arrays, the image codec (whichever OpenCV wheel is there) and the model clients (httpx; openai where
present)."""

LOCK_FILE = "uv.lock"

SOURCE_ROOT = Path(__file__).resolve().parents[1]
"""The repository root when agos runs from a checkout (an editable install maps ``agos.runtime`` to
``<root>/runtime``); for an installed wheel, the ``agos`` package folder, which is no checkout."""


def provenance() -> dict[str, Any]:
    """This process's agos commit, lock hash and package versions (a fresh copy of a map computed once)."""
    found = _provenance()
    return {**found, "packages": dict(found["packages"])}


@functools.cache
def _provenance() -> dict[str, Any]:
    commit, dirty = git_state(SOURCE_ROOT)
    return {"agos": _version("agos"), "commit": commit, "dirty": dirty, "lock_sha256": lock_sha256(),
            "python": platform.python_version(),
            "packages": {name: version for name in PACKAGES if (version := _version(name)) is not None}}


def git_state(root: Path) -> tuple[str | None, bool | None]:
    """(HEAD's full sha, whether tracked files differ from it) when ``root`` is the top of a git
    checkout (a linked worktree too); (None, None) when it is not; (sha, None) when the status cannot
    be read. Dirty is what ``git status --untracked-files=no`` would list: a change staged, or a
    tracked file whose content or executable bit differs from the index.

    Read by dulwich, starting no process (agos's unit tests start none: tests/process_guard.py).
    """
    if not (root / ".git").exists():
        return None, None
    # Imported here: dulwich costs ~0.4 s of CPU to import, and every agos process imports this module
    # (records carry provenance) while only the processes that write a record or a plan call this.
    from dulwich import porcelain
    from dulwich.errors import NotGitRepository
    from dulwich.repo import Repo

    try:
        repo = Repo(str(root))
    except (NotGitRepository, OSError):
        return None, None
    with repo:
        try:
            commit = repo.head().decode()
        except KeyError:  # no commit yet
            return None, None
        try:
            status = porcelain.status(repo, untracked_files="no")
        except (OSError, ValueError, KeyError):
            return commit, None
        return commit, any(status.staged.values()) or bool(status.unstaged) or _exec_bit_changed(repo, root)


def _exec_bit_changed(repo: Repo, root: Path) -> bool:
    """Whether a tracked file's executable bit differs from the index (git reports it; dulwich's
    status compares contents only)."""
    index = repo.open_index()
    for path, _, mode in index.iterobjects():
        if mode in (REGULAR, EXECUTABLE):
            try:
                st = os.lstat(root / os.fsdecode(path))
            except FileNotFoundError:  # a deletion: the status has it
                continue
            if bool(st.st_mode & 0o100) != (mode == EXECUTABLE):
                return True
    return False


REGULAR, EXECUTABLE = 0o100644, 0o100755
"""Git's modes of a tracked file."""


def lock_sha256() -> str | None:
    """sha256 of ``uv.lock``: the checkout's, else the copy an image keeps beside its environment
    (``<sys.prefix>/uv.lock``, written by the Dockerfile); None when there is neither."""
    for path in (SOURCE_ROOT / LOCK_FILE, Path(sys.prefix) / LOCK_FILE):
        if path.is_file():
            return hashlib.sha256(path.read_bytes()).hexdigest()
    return None


def _version(distribution: str) -> str | None:
    try:
        return metadata.version(distribution)
    except metadata.PackageNotFoundError:
        return None


if __name__ == "__main__":  # python -m agos.runtime.provenance: what a run made here would record
    import json

    print(json.dumps(provenance(), indent=2))
