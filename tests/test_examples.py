"""The library's examples run as docs/LIBRARY.md shows them: README's five-line use (the same block opens
docs/LIBRARY.md), the random-policy loop over agos.Env and the heuristic through the PettingZoo API
(examples/random_loop.py, examples/heuristic_pettingzoo.py), on generated flat episodes, the examples
with small images and a short budget. The behaviour-cloning loop (examples/bc_data_loop.py) reads a
dataset: tests/test_dataset_stats.py runs it on the tiny one built there."""

from __future__ import annotations

import contextlib
import importlib
import io
import re
import sys
from pathlib import Path

import pytest

from agos import episode_config

from support.episodes import SMALL_CAMERAS

REPO = Path(__file__).resolve().parents[1]
CONFIG = episode_config(look="flat", decision_budget=10,
                        cameras=SMALL_CAMERAS)


@pytest.fixture
def examples(monkeypatch: pytest.MonkeyPatch):
    """``examples(name)``: the example module, imported from the repository root as the docs run it."""
    monkeypatch.syspath_prepend(str(REPO))

    def load(name: str):
        monkeypatch.delitem(sys.modules, f"examples.{name}", raising=False)
        return importlib.import_module(f"examples.{name}")

    return load


def test_the_random_loop_plays_an_episode_with_legal_actions_only(examples) -> None:
    record = examples("random_loop").main(seed=1, config=CONFIG)
    assert record.status == "finished" and record.fallbacks == 0  # every random action was legal (Env raises else)
    assert 1 <= record.decisions_uav + record.decisions_ugv <= 10


def test_the_heuristic_plays_through_the_pettingzoo_api(examples) -> None:
    returns, record = examples("heuristic_pettingzoo").main(seed=3, config=CONFIG)
    assert record.status == "finished"
    assert record.success or record.decisions_uav + record.decisions_ugv == 10  # it confirmed, or spent the budget
    assert returns == dict.fromkeys(("uav", "ugv"), 1.0 if record.success else 0.0)
    assert record.fallbacks == 0  # each index it gave was in the mask


def test_the_readmes_five_lines_run_and_open_docs_library() -> None:
    readme = (REPO / "README.md").read_text()
    section = readme[readme.index("## Python: agos as a library"):]
    block = re.search(r"```python\n(.*?)```", section, re.S)
    assert block is not None
    code = block.group(1)
    assert len([line for line in code.splitlines() if line.strip()]) == 5
    assert code in (REPO / "docs" / "LIBRARY.md").read_text()
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        exec(compile(code, "README.md", "exec"), {})
    termination, decisions = out.getvalue().split()
    assert termination in ("confirmed", "false_confirm", "budget_exhausted") and int(decisions) > 0
