"""uv.lock matches pyproject.toml, and the two pip-readable exports match uv.lock (make lock writes all three)."""

from __future__ import annotations

import re
import shutil
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
EXPORTS = {"requirements.lock.txt": [], "requirements-dev.lock.txt": ["--extra", "dev"]}
"""Each export and the `uv export` options that make it (the Makefile's `lock` target)."""


def _uv() -> str:
    version = re.search(r"^UV_VERSION\s*:=\s*(\S+)", (ROOT / "Makefile").read_text(), re.M)
    pinned = ROOT / ".venv" / f"uv-{version.group(1) if version else '?'}" / "bin" / "uv"
    found = str(pinned) if pinned.exists() else shutil.which("uv")
    if found is None:
        pytest.skip(f"no uv here: `make` puts the pinned one at {pinned.relative_to(ROOT)}")
    return found


def _requirements(text: str) -> str:
    """An export without its comment lines (the header names the file it was written to)."""
    return "\n".join(line for line in text.splitlines() if not line.startswith("#"))


@pytest.mark.e2e  # starts uv; needs no network (a current lock is checked without resolving)
def test_lock_matches_pyproject() -> None:
    done = subprocess.run([_uv(), "lock", "--check", "--offline"], cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, f"uv.lock does not match pyproject.toml; run make lock:\n{done.stderr}"


@pytest.mark.e2e  # starts uv; reads only uv.lock
@pytest.mark.parametrize("name", sorted(EXPORTS))
def test_exports_match_the_lock(name: str, tmp_path: Path) -> None:
    out = tmp_path / name
    subprocess.run([_uv(), "export", "--frozen", "--no-emit-project", "--quiet", *EXPORTS[name], "--output-file", str(out)],
                   cwd=ROOT, check=True, capture_output=True, timeout=120)
    assert _requirements((ROOT / name).read_text()) == _requirements(out.read_text()), f"{name} is stale: run make lock"
