"""Every repository path that README.md and docs/*.md name exists, so a moved module cannot leave a
doc pointing at nothing.

A path counts when it starts with one of the repository's folders (``runtime/``, ``deploy/``, …) or
is a top-level file; a ``::name`` or ``:line`` suffix is the symbol inside it and is dropped; a path
with a placeholder (``<run>``, ``{a,b}``) or a wildcard must match at least one file. A path git
ignores (``.gitignore`` at the root, or one in the path's own folder) is an output a command makes,
not a file of the repository, and is skipped.
"""

from __future__ import annotations

import fnmatch
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
DOCS = [ROOT / "README.md", ROOT / "bench" / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
FOLDERS = ("runtime", "world", "agents", "evaluator", "deploy", "examples", "tests", "bench", "docs", ".ci")
# (not "agos/": the key space is written agos/<run>/..., and the library's own files are few: agos/*.py)

# A folder name at a word start (not inside another path or a URL), then path characters.
PATH_RE = re.compile(r"(?<![\w/.\-~])((?:" + "|".join(re.escape(f) for f in FOLDERS) + r")/[\w./*\-<>{},]*)")


def named_paths(text: str) -> set[str]:
    """The repository paths ``text`` names, without symbol suffixes and trailing punctuation."""
    found = set()
    for match in PATH_RE.finditer(text):
        path = match.group(1).split("::")[0]
        path = re.sub(r":\d+$", "", path).rstrip(".,")
        if path.rstrip("/") in FOLDERS:
            continue
        found.add(path)
    return found


def ignored(path: str) -> bool:
    """Whether git ignores ``path`` (the root ``.gitignore``, or a ``.gitignore`` in its folder)."""
    patterns = [line.strip() for line in (ROOT / ".gitignore").read_text().splitlines()
                if line.strip() and not line.startswith("#")]
    parts = path.rstrip("/").split("/")
    for pattern in patterns:
        anchored = pattern.startswith("/") or "/" in pattern.rstrip("/")
        bare = pattern.strip("/")
        if anchored and any(fnmatch.fnmatch("/".join(parts[:n]), bare) for n in range(1, len(parts) + 1)):
            return True
        if not anchored and any(fnmatch.fnmatch(part, bare) for part in parts):
            return True
    return (ROOT / path).parent.joinpath(".gitignore").exists() and not (ROOT / path).exists()


def exists(path: str) -> bool:
    """Whether ``path`` names a file or folder of the repository (a pattern: at least one)."""
    if re.search(r"[<*{]", path):
        pattern = re.sub(r"<[^>/]*>", "*", path)
        pattern = re.sub(r"\{[^}/]*\}", "*", pattern)
        return any(ROOT.glob(pattern.rstrip("/")))
    return (ROOT / path).exists()


def test_the_path_scanner_sees_what_docs_write():
    text = "see `deploy/cli.py::main`, deploy/run/ and world/towns/asset.py:12. Not runs/x or a/deploy/y."
    assert named_paths(text) == {"deploy/cli.py", "deploy/run/", "world/towns/asset.py"}


def test_outputs_git_ignores_are_not_repository_paths():
    assert ignored("deploy/.env") and ignored("bench/.cache/x.npz") and ignored("deploy/certs/ca.key")
    assert not ignored("deploy/compose.yaml") and not ignored("runtime/keys.py")


@pytest.mark.parametrize("doc", DOCS, ids=lambda p: str(p.relative_to(ROOT)))
def test_every_path_a_doc_names_exists(doc: Path):
    missing = sorted(p for p in named_paths(doc.read_text()) if not exists(p) and not ignored(p))
    assert not missing, f"{doc.relative_to(ROOT)} names paths that are not in the repository: {missing}"
