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

Computed once per process, from the files of ``.git`` (no git process, no lock taken).
"""

from __future__ import annotations

import functools
import hashlib
import os
import platform
import re
import stat
import struct
import sys
import zlib
from importlib import metadata
from pathlib import Path
from typing import Any

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
    checkout; (None, None) when it is not; (sha, None) when the index is of a kind read here not.

    Read from ``.git`` itself, starting no process (agos's unit tests start none: tests/process_guard.py):
    dirty is what ``git status --untracked-files=no`` would list, i.e. a tracked file whose content or
    executable bit differs from the index, a conflict, or an index whose tree is not HEAD's.
    """
    try:
        git_dir = _git_dir(root)
        if git_dir is None:
            return None, None
        common = git_dir / (git_dir / "commondir").read_text().strip() if (git_dir / "commondir").is_file() else git_dir
        commit = _head_commit(git_dir, common)
    except (OSError, ValueError):
        return None, None
    if commit is None:
        return None, None
    try:
        return commit, _dirty(root, git_dir, common, commit)
    except (OSError, ValueError, zlib.error, struct.error):
        return commit, None


def _git_dir(root: Path) -> Path | None:
    dot_git = root / ".git"
    if dot_git.is_dir():
        return dot_git
    if dot_git.is_file():  # a linked worktree: "gitdir: <path>"
        line = dot_git.read_text().strip()
        if line.startswith("gitdir:"):
            return (root / line.removeprefix("gitdir:").strip()).resolve()
    return None


def _head_commit(git_dir: Path, common: Path) -> str | None:
    head = (git_dir / "HEAD").read_text().strip()
    for _ in range(5):  # symbolic refs, followed a few levels
        if not head.startswith("ref:"):
            return head if _SHA1.fullmatch(head) else None
        ref = head.removeprefix("ref:").strip()
        loose = next((d / ref for d in (git_dir, common) if (d / ref).is_file()), None)
        if loose is not None:
            head = loose.read_text().strip()
            continue
        packed = common / "packed-refs"
        lines = packed.read_text().splitlines() if packed.is_file() else []
        return next((line.split()[0] for line in lines if line.endswith(" " + ref)), None)
    return None


_SHA1 = re.compile(r"[0-9a-f]{40}")
_MODE_FILE, _MODE_EXEC, _MODE_LINK, _MODE_GITLINK = 0o100644, 0o100755, 0o120000, 0o160000


def _dirty(root: Path, git_dir: Path, common: Path, commit: str) -> bool | None:
    index_path = git_dir / "index"
    data = index_path.read_bytes()
    signature, version, count = struct.unpack(">4sII", data[:12])
    if signature != b"DIRC" or version not in (2, 3) or hashlib.sha1(data[:-20]).digest() != data[-20:]:
        return None  # index v4 (compressed paths), or not an index
    index_mtime_ns = index_path.stat().st_mtime_ns
    entries: list[tuple[bytes, int, bytes]] = []
    pos = 12
    for _ in range(count):
        mtime_s, mtime_ns, mode, size, sha, flags = (*struct.unpack(">II", data[pos + 8:pos + 16]),
                                                     struct.unpack(">I", data[pos + 24:pos + 28])[0],
                                                     struct.unpack(">I", data[pos + 36:pos + 40])[0],
                                                     data[pos + 40:pos + 60], struct.unpack(">H", data[pos + 60:pos + 62])[0])
        head = 62
        extended = 0
        if flags & 0x4000:
            extended = struct.unpack(">H", data[pos + 62:pos + 64])[0]
            head = 64
        end = data.index(b"\0", pos + head)
        path = data[pos + head:end]
        pos += (head + len(path) + 8) // 8 * 8
        if flags & 0x3000 or extended & 0x2000:  # a merge conflict, or `git add -N`
            return True
        if mode not in (_MODE_FILE, _MODE_EXEC, _MODE_LINK, _MODE_GITLINK):
            return None  # a sparse index's directory entries
        entries.append((path, mode, sha))
        if mode == _MODE_GITLINK or flags & 0x8000 or extended & 0x4000:  # submodule, assume-valid, skip-worktree
            continue
        if _changed(root / os.fsdecode(path), mode, size, sha, mtime_s * 1_000_000_000 + mtime_ns, index_mtime_ns):
            return True
    while pos < len(data) - 20:  # extensions: a split index keeps entries elsewhere
        signature, size = struct.unpack(">4sI", data[pos:pos + 8])
        if signature == b"link":
            return None
        pos += 8 + size
    tree = _commit_tree(common, commit)
    return None if tree is None else _index_tree(entries) != tree


def _changed(path: Path, mode: int, size: int, sha: bytes, mtime_ns: int, index_mtime_ns: int) -> bool:
    try:
        st = path.lstat()
    except FileNotFoundError:
        return True
    if mode == _MODE_LINK:
        if not stat.S_ISLNK(st.st_mode):
            return True
        content = os.fsencode(os.readlink(path))
    else:
        if not stat.S_ISREG(st.st_mode) or bool(st.st_mode & 0o100) != (mode == _MODE_EXEC):
            return True
        # Same size and mtime as indexed, and the index written after it: git trusts that (racy-git otherwise).
        if (st.st_size & 0xFFFFFFFF) == size and st.st_mtime_ns == mtime_ns and mtime_ns < index_mtime_ns:
            return False
        content = path.read_bytes()
    return hashlib.sha1(b"blob %d\0" % len(content) + content).digest() != sha


def _index_tree(entries: list[tuple[bytes, int, bytes]]) -> bytes:
    """The tree `git write-tree` would write from these entries (path-sorted, as an index is): its sha."""
    def tree(items: list[tuple[list[bytes], int, bytes]]) -> bytes:
        body: list[tuple[bytes, bytes]] = []  # (sort key, entry)
        i = 0
        while i < len(items):
            parts, mode, sha = items[i]
            if len(parts) == 1:
                body.append((parts[0], b"%o %s\0" % (mode, parts[0]) + sha))
                i += 1
                continue
            j = i
            while j < len(items) and len(items[j][0]) > 1 and items[j][0][0] == parts[0]:
                j += 1
            sub = tree([(p[1:], m, s) for p, m, s in items[i:j]])
            body.append((parts[0] + b"/", b"40000 %s\0" % parts[0] + sub))
            i = j
        raw = b"".join(entry for _, entry in sorted(body))
        return hashlib.sha1(b"tree %d\0" % len(raw) + raw).digest()

    return tree([(path.split(b"/"), mode, sha) for path, mode, sha in entries])


def _commit_tree(common: Path, commit: str) -> bytes | None:
    """The tree of ``commit``, read from a loose object or a pack (None for a deltified commit)."""
    body = _loose_object(common, commit) or _packed_commit(common, commit)
    if body is None or not body.startswith(b"tree "):
        return None
    return bytes.fromhex(body[5:45].decode())


def _loose_object(common: Path, sha: str) -> bytes | None:
    path = common / "objects" / sha[:2] / sha[2:]
    if not path.is_file():
        return None
    raw = zlib.decompress(path.read_bytes())
    return raw[raw.index(b"\0") + 1:] if raw.startswith(b"commit ") else None


def _packed_commit(common: Path, sha: str) -> bytes | None:
    want = bytes.fromhex(sha)
    for idx_path in sorted((common / "objects" / "pack").glob("pack-*.idx")):
        idx = idx_path.read_bytes()
        if idx[:8] != b"\377tOc\0\0\0\2":
            continue
        fanout = struct.unpack(">256I", idx[8:8 + 1024])
        n = fanout[255]
        lo, hi = (fanout[want[0] - 1] if want[0] else 0), fanout[want[0]]
        names = 8 + 1024
        while lo < hi:  # binary search among the names starting with that byte
            mid = (lo + hi) // 2
            name = idx[names + 20 * mid:names + 20 * mid + 20]
            if name == want:
                break
            lo, hi = (mid + 1, hi) if name < want else (lo, mid)
        else:
            continue
        offsets = names + 24 * n  # names (20 n), then crc32s (4 n), then offsets (4 n)
        offset = struct.unpack(">I", idx[offsets + 4 * mid:offsets + 4 * mid + 4])[0]
        if offset & 0x80000000:
            large = offsets + 4 * n + 8 * (offset & 0x7FFFFFFF)
            offset = struct.unpack(">Q", idx[large:large + 8])[0]
        with idx_path.with_suffix(".pack").open("rb") as pack:
            pack.seek(offset)
            chunk = pack.read(65536)
        if (chunk[0] >> 4) & 7 != 1:  # not stored whole as a commit (a delta)
            return None
        i = 0
        while chunk[i] & 0x80:
            i += 1
        return zlib.decompressobj().decompress(chunk[i + 1:])
    return None


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
