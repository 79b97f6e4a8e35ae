"""The README runs top to bottom: its shell blocks, in order, in one fresh copy of the repository.

The rule, which README.md follows:

- Every fenced block in README.md names its language. ```` ```bash ```` blocks are commands, typed
  from the repository root; ```` ```text ```` (pictures, sample output) and ```` ```python ```` blocks
  are not run. A bare ```` ``` ```` fence or another shell tag (``sh``, ``console``, ...) fails the
  test, so no command block can slip past it.
- A ``bash`` block runs with ``bash -e -o pipefail``, so every line of it must succeed, unless the
  last non-blank line before its fence is a marker (an HTML comment, invisible on GitHub):

  - ``<!-- readme-test: skip (REASON) -->``: not run; the reason is required and is the pytest skip
    reason (long-running commands: ``make demo``, ``make test``, Docker, long evaluations; commands
    for other hosts).
  - ``<!-- readme-test: background -->``: "one terminal each": every line starts as its own process
    and keeps running while the next block that runs runs; then each gets Ctrl-C (SIGINT). None may
    exit in its first 2 s (a port taken, a bad flag); one that exited later must have exited 0 (a
    world worker leaves when its run is done).
  - ``<!-- readme-test: needs PATH -->``: runs only when PATH (relative to the repository root, e.g.
    the CARLA maps in ``../shared/maps/carla/``, which README says where to get) exists; otherwise
    skipped, naming PATH.

Set-up, as README describes it: ``make demo`` / ``make test`` (skipped by marker: long-running) create
``.venv``; the copy gets a link to this checkout's ``.venv`` instead, and ``.venv/bin`` is put first on
PATH, as ``. .venv/bin/activate`` (which README asks for) would, so plain ``agos`` works too. The copy
is a fresh one: the checkout without what ``.gitignore`` names, without the caches and without what the
README's commands make (``runs``, ``splits``, ``certs``, ``report``, ``assets``, top-level ``*.jsonl``
and ``*.png``); ``../shared`` beside it links to this checkout's ``../shared`` when there is one. The
environment has no ``AGOS_*`` variables, and an empty town asset cache (a fresh machine).

Each block is a test case (``README.md:LINE``); selecting one runs the blocks before it first.
"""

from __future__ import annotations

import fnmatch
import os
import re
import shutil
import signal
import subprocess
import time
from dataclasses import dataclass, field
from pathlib import Path

import pytest

pytestmark = pytest.mark.e2e

REPO = Path(__file__).resolve().parents[1]
README = REPO / "README.md"
MARKER = re.compile(r"^<!--\s*readme-test:\s*(?P<kind>\w+)\s*(?P<arg>.*?)\s*-->$")
SHELL_TAGS = {"sh", "shell", "console", "zsh", "shell-session", "bash-session"}
BLOCK_TIMEOUT_S = 180.0
# Never copied: version control, build and tool caches, and what the README's own commands make.
NOT_COPIED = {".git", ".venv", ".wheels", ".typecheck", ".pytest_cache", ".ruff_cache", ".mypy_cache", ".grimp_cache",
              ".import_linter_cache", "__pycache__"}
MADE_BY_README = {"runs", "splits", "certs", "report", "assets", "*.jsonl", "*.png"}


@dataclass(frozen=True)
class Block:
    line: int  # of the opening fence, 1-based
    lang: str
    text: str
    marker: tuple[str, str] | None  # (kind, argument)
    marker_line: int | None

    @property
    def commands(self) -> list[str]:
        return [ln for ln in self.text.splitlines() if ln.strip() and not ln.lstrip().startswith("#")]


def parse_readme(text: str) -> list[Block]:
    blocks: list[Block] = []
    lines = text.splitlines()
    i = 0
    while i < len(lines):
        if not lines[i].startswith("```"):
            i += 1
            continue
        start, lang = i, lines[i][3:].strip()
        end = next((j for j in range(i + 1, len(lines)) if lines[j].strip() == "```"), None)
        assert end is not None, f"README.md:{start + 1}: fence never closed"
        before = next((j for j in range(start - 1, -1, -1) if lines[j].strip()), None)
        m = MARKER.match(lines[before].strip()) if before is not None else None
        marker, marker_line = ((m["kind"], m["arg"]), before + 1) if m and before is not None else (None, None)
        blocks.append(Block(start + 1, lang, "\n".join(lines[start + 1:end]) + "\n", marker, marker_line))
        i = end + 1
    return blocks


BLOCKS = parse_readme(README.read_text(encoding="utf-8"))
BASH = [b for b in BLOCKS if b.lang == "bash"]


def test_every_block_says_what_it_is() -> None:
    """No bare fences, one shell tag, markers only on bash blocks, and every marker well formed."""
    problems = []
    for b in BLOCKS:
        if not b.lang:
            problems.append(f"README.md:{b.line}: bare ``` fence: tag it bash (commands), text or python")
        elif b.lang in SHELL_TAGS:
            problems.append(f"README.md:{b.line}: ```{b.lang}: command blocks are tagged bash")
        if b.marker and b.lang != "bash":
            problems.append(f"README.md:{b.line}: readme-test marker on a {b.lang or 'bare'} block")
        if b.marker:
            kind, arg = b.marker
            if kind == "skip" and not re.fullmatch(r"\(.+\)", arg):
                problems.append(f"README.md:{b.line}: skip needs a reason: <!-- readme-test: skip (REASON) -->")
            elif kind == "needs" and not arg:
                problems.append(f"README.md:{b.line}: needs needs a path: <!-- readme-test: needs PATH -->")
            elif kind == "background" and arg:
                problems.append(f"README.md:{b.line}: background takes no argument")
            elif kind not in {"skip", "needs", "background"}:
                problems.append(f"README.md:{b.line}: unknown readme-test marker {kind!r}")
    attached = {b.marker_line for b in BLOCKS}
    dangling = [n + 1 for n, ln in enumerate(README.read_text(encoding="utf-8").splitlines())
                if MARKER.match(ln.strip()) and n + 1 not in attached]
    problems += [f"README.md:{n}: readme-test marker not right before a fence" for n in dangling]
    assert BASH, "README.md has no bash blocks"
    assert not problems, "\n".join(problems)


def _ignore(root: Path):
    gitignore = (root / ".gitignore").read_text().splitlines() if (root / ".gitignore").exists() else []
    patterns = [p.strip() for p in gitignore if p.strip() and not p.startswith("#")]
    names = {p.strip("/") for p in patterns if not p.startswith("/")}
    rooted = {p.strip("/") for p in patterns if p.startswith("/")}  # `/data/`: the root's data/, not deploy/data/

    def ignore(directory: str, entries: list[str]) -> set[str]:
        here = Path(directory)
        rel = here.relative_to(root)
        made_here = MADE_BY_README | rooted if here == root else set()
        return {e for e in entries
                if e in NOT_COPIED or any(fnmatch.fnmatch(e, n) or fnmatch.fnmatch((rel / e).as_posix(), n) for n in names)
                or any(fnmatch.fnmatch(e, n) for n in made_here)}

    return ignore


@dataclass
class Background:
    block: Block
    procs: list[tuple[str, subprocess.Popen, Path]] = field(default_factory=list)


class ReadmeSession:
    """One fresh copy of the repository in which the README's blocks run in order."""

    def __init__(self, base: Path) -> None:
        self.root = base / REPO.name
        shutil.copytree(REPO, self.root, ignore=_ignore(REPO), symlinks=True)
        (self.root / ".venv").symlink_to(REPO / ".venv", target_is_directory=True)
        if (REPO.parent / "shared").is_dir():
            (base / "shared").symlink_to(REPO.parent / "shared", target_is_directory=True)
        self.logs = base / "logs"
        self.logs.mkdir()
        env = {k: v for k, v in os.environ.items() if not k.startswith("AGOS_") and k not in {"VIRTUAL_ENV", "PYTHONPATH"}}
        env.update(PATH=f"{self.root / '.venv' / 'bin'}{os.pathsep}{env.get('PATH', '')}", VIRTUAL_ENV=str(self.root / ".venv"),
                   AGOS_ASSET_CACHE=str(base / "asset-cache"), COLUMNS="120", PYTHONUNBUFFERED="1")
        self.env = env
        self.done = 0  # BASH[:done] have been handled
        self.background: list[Background] = []
        self.outcomes: dict[int, str | None] = {}  # block line -> skip reason, or None when it ran

    def play(self, index: int) -> str | None:
        """Handle BASH[done..index] in order; the skip reason of BASH[index], or None when it ran."""
        while self.done <= index:
            block = BASH[self.done]
            self.done += 1
            self.outcomes[block.line] = self._handle(block)
        return self.outcomes[BASH[index].line]

    def _handle(self, block: Block) -> str | None:
        kind, arg = block.marker or ("", "")
        if kind == "skip":
            return arg.strip("()")
        if kind == "needs" and not (self.root / arg).exists():
            return f"needs {arg}, which is not here (README says where it comes from)"
        if kind == "background":
            self._start_background(block)
            return None
        waiting, self.background = self.background, []
        try:
            self._run(block)
        finally:
            died = [problem for bg in waiting for problem in self._stop(bg)]
        assert not died, "\n".join(died)
        return None

    def _run(self, block: Block) -> None:
        log = self.logs / f"block-{block.line}.log"
        started = time.monotonic()
        with log.open("w") as out:
            proc = subprocess.Popen(["bash", "-e", "-o", "pipefail", "-c", block.text], cwd=self.root, env=self.env,
                                    stdout=out, stderr=subprocess.STDOUT, start_new_session=True)
            try:
                rc = proc.wait(timeout=BLOCK_TIMEOUT_S)
            except subprocess.TimeoutExpired:
                _interrupt(proc)
                pytest.fail(f"README.md:{block.line}: still running after {BLOCK_TIMEOUT_S:.0f} s "
                            f"(long-running blocks need a skip marker)\n{_tail(log)}")
        assert rc == 0, f"README.md:{block.line}: exit {rc} after {time.monotonic() - started:.1f} s\n{block.text}\n{_tail(log)}"

    def _start_background(self, block: Block) -> None:
        bg = Background(block)
        for n, command in enumerate(block.commands):
            log = self.logs / f"block-{block.line}-{n}.log"
            with log.open("w") as out:
                proc = subprocess.Popen(["bash", "-c", command], cwd=self.root, env=self.env, stdout=out,
                                        stderr=subprocess.STDOUT, start_new_session=True)
            bg.procs.append((command, proc, log))
        self.background.append(bg)
        time.sleep(2.0)  # one that cannot start (a port taken, a bad flag) fails here, not as a hang later
        failed = [f"README.md:{block.line}: `{c}` exited ({p.returncode}) at start\n{_tail(log)}"
                  for c, p, log in bg.procs if p.poll() is not None]
        assert not failed, "\n".join(failed)

    def _stop(self, bg: Background) -> list[str]:
        """Ctrl-C to each process of a background block; those that had failed before it."""
        died = [f"README.md:{bg.block.line}: `{c}` failed (exit {p.returncode}) before Ctrl-C\n{_tail(log)}"
                for c, p, log in bg.procs if p.poll() not in (None, 0)]
        for _, proc, _ in bg.procs:
            _interrupt(proc)
        return died

    def close(self) -> None:
        for bg in self.background:
            for _, proc, _ in bg.procs:
                _interrupt(proc)
        self.background = []


def _interrupt(proc: subprocess.Popen) -> None:
    """Ctrl-C to the process group, as a terminal would; harder signals after 20 s."""
    for sig, wait_s in ((signal.SIGINT, 20.0), (signal.SIGTERM, 5.0), (signal.SIGKILL, 5.0)):
        if proc.poll() is not None:
            return
        try:
            os.killpg(proc.pid, sig)
        except ProcessLookupError:
            return
        try:
            proc.wait(timeout=wait_s)
            return
        except subprocess.TimeoutExpired:
            continue


def _tail(log: Path, chars: int = 4000) -> str:
    return log.read_text(errors="replace")[-chars:]


@pytest.fixture(scope="module")
def readme(tmp_path_factory: pytest.TempPathFactory):
    if not (REPO / ".venv" / "bin" / "agos").exists():
        pytest.skip("no .venv with agos in this checkout: `make test` creates it")
    session = ReadmeSession(tmp_path_factory.mktemp("readme"))
    try:
        yield session
    finally:
        session.close()


@pytest.mark.parametrize("index", range(len(BASH)), ids=[f"README.md:{b.line}" for b in BASH])
def test_readme_block(readme: ReadmeSession, index: int) -> None:
    reason = readme.play(index)
    if reason is not None:
        pytest.skip(f"README.md:{BASH[index].line}: {reason}")
