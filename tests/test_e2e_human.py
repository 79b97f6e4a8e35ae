"""End to end in a real browser: a script plays a whole episode as both roles through the human
console's page, with mouse and keyboard, in headless Chromium (Debian's ``chromium``, driven by
Playwright through its ``executable_path``: no browser is downloaded).

``agos eval --policy human --decision-timeout 2h`` runs router, evaluator, a world worker and one
``agos human --role both`` on loopback; ``agos human --spectate`` watches the run read-only. The
script feeds the page bad input first (an illegal action, a waypoint that is not offered, a stale
decision index, an overlong message, a double click, a second window answering the same decision):
each gets a clear message in the page and none becomes a decision. The stored record must hold
exactly the decisions the script made, each traced as a person's. A screenshot of the page at the
UGV's STOP_OBSERVE (and one of the spectator) is kept: the test prints where.
"""

from __future__ import annotations

import json
import os
import shutil
import sqlite3
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import pytest

from agos.deploy.run.launcher import free_port

pytestmark = pytest.mark.e2e
AGOS = [sys.executable, "-m", "agos.deploy.cli"]
CHROMIUM = "chromium"
VIEWPORT = {"width": 1440, "height": 900}
WAIT_MS = 20_000


@pytest.fixture(scope="module")
def browser():
    """Headless Debian chromium under Playwright. Missing, the test fails and says how to install it
    (.ci/run does), as the compose test does for docker: a browser test that skips proves nothing."""
    executable = shutil.which(CHROMIUM)
    if executable is None:
        pytest.fail(f"no `{CHROMIUM}` on PATH: install Debian's package (apt-get install -y chromium; .ci/run does)")
    try:
        from playwright.sync_api import sync_playwright
    except ImportError:
        pytest.fail("the Python package playwright is missing: pip install -e '.[dev]'")
    with sync_playwright() as p:
        b = p.chromium.launch(executable_path=executable, args=["--no-sandbox", "--disable-gpu"])
        yield b
        b.close()


def _read_line(proc: subprocess.Popen, marker: str, seen: list[str], timeout_s: float = 60.0) -> str:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        line = proc.stdout.readline()
        if not line:
            break
        seen.append(line)
        if marker in line:
            return line
    raise AssertionError(f"no {marker!r} line; output:\n{''.join(seen)}")


def _url(line: str) -> str:
    return next(w for w in line.split() if w.startswith("http://"))


def _artifacts(tmp_path: Path) -> Path:
    out = Path(os.environ.get("AGOS_TEST_ARTIFACTS") or tmp_path / "artifacts")
    out.mkdir(parents=True, exist_ok=True)
    return out


def _asked(page: Any) -> dict[str, Any]:
    """The decision the page shows as asked (after it is drawn)."""
    page.wait_for_selector("body[data-asked=yes]", timeout=WAIT_MS)
    return page.evaluate("window.agos.state().by_role[window.agos.role()].asked.state")


def _answered(page: Any, index: int) -> None:
    """Wait until the page no longer shows decision ``index`` as asked."""
    page.wait_for_selector(f"body:not([data-asked=yes][data-decision='{index}'])", timeout=WAIT_MS)


def _feedback(page: Any) -> str:
    return page.inner_text("#feedback")


def test_a_person_plays_a_whole_episode_through_the_page(tmp_path: Path, browser) -> None:
    episodes = tmp_path / "eps.jsonl"
    subprocess.run([*AGOS, "episodes", "sample", "--town", "grid-s7", "--difficulty", "easy", "-n", "1", "--seed", "3",
                    "--out", str(episodes)], check=True, capture_output=True, timeout=120)
    run_dir, port = tmp_path / "runs" / "human-e2e", free_port(17800)
    env = {**os.environ, "COLUMNS": "200", "AGOS_WORLD__DECISION_BUDGET": "16"}
    ev = subprocess.Popen([*AGOS, "eval", "--split", str(episodes), "--policy", "human", "--decision-timeout", "2h",
                           "--run-dir", str(run_dir), "--port", str(port)], stdout=subprocess.PIPE,
                          stderr=subprocess.STDOUT, text=True, cwd=tmp_path, env=env)
    spectator = None
    out: list[str] = []
    try:
        console = _url(_read_line(ev, "human console:", out))
        spectator = subprocess.Popen([*AGOS, "human", "--spectate", "--connect", f"tcp/127.0.0.1:{port}", "--run",
                                      "human-e2e", "--port", str(free_port(17900))], stdout=subprocess.PIPE,
                                     stderr=subprocess.STDOUT, text=True, cwd=tmp_path)
        watch = _url(_read_line(spectator, "human console:", []))
        pages = {role: browser.new_page(viewport=VIEWPORT) for role in ("uav", "ugv", "uav2", "spectator")}
        errors: list[str] = []
        for page in pages.values():
            page.on("pageerror", lambda e: errors.append(str(e)))
        for role in ("uav", "ugv", "uav2"):
            pages[role].goto(f"{console}?role={role[:3]}")
        pages["spectator"].goto(watch)
        uav, ugv, uav2 = pages["uav"], pages["ugv"], pages["uav2"]
        made: list[tuple[str, int, str]] = []  # what the script decided: (role, decision, action)

        # ----- UAV decision 1: the wait is shown; bad input is refused in the page, nothing is decided.
        st = _asked(uav)
        assert st["decision_index"] == 1 and st["decision_timeout_s"] == 7200.0
        assert "waits up to 2:00:00" in uav.inner_text("#clock")
        bad = [({"action": "CONFIRM"}, "not legal"),
               ({"action": "MOVE_TO_UAV_WAYPOINT", "waypoint_id": "nowhere"}, "not an option"),
               ({"action": "WAIT", "decision_index": 0}, "Stale"),
               ({"action": "WAIT", "message": "x" * 201}, "at most 200")]
        for fields, says in bad:
            answer = uav.evaluate("(f) => window.agos.send(f)", fields)
            assert answer and not answer["ok"] and says in answer["message"], answer
            assert says in _feedback(uav)
        # Choose with the mouse (a grid cell), change it with the keyboard (A, D, 2), write, double-click Send.
        uav.click(".grid div[data-cell=C3]")
        assert "ANNOTATE_CANDIDATE C3" in uav.inner_text("#selected")
        for key in ("a", "d", "2"):
            uav.keyboard.press(key)
        assert "ANNOTATE_CANDIDATE D2" in uav.inner_text("#selected")
        uav.fill("#message", "red truck in D2")
        uav.dblclick("#send")
        uav.wait_for_function("document.querySelector('#feedback').innerText.includes('Sent: UAV decision 1')")
        # The second click of the double click sends nothing: it is ignored while the first is in flight,
        # or, when the console answered between the two clicks, it lands on a Send disabled by the answer.
        feedback = _feedback(uav)
        assert feedback.count("Sent: UAV decision 1") == 1, feedback
        assert "ignored" in feedback or uav.is_disabled("#send"), feedback
        made.append(("uav", 1, "ANNOTATE_CANDIDATE"))
        # A second window on the same role answers the same decision: refused as already sent.
        again = uav2.evaluate("(f) => window.agos.send(f)", {"action": "WAIT", "episode_id": st["episode_id"],
                                                             "attempt": 1, "decision_index": 1})
        assert again["ok"] is False and "already sent" in again["message"] and "already sent" in _feedback(uav2)

        # ----- UGV: WAIT by keyboard until a candidate is known, then GO_TO_CANDIDATE by mouse, STOP_OBSERVE by
        # keyboard, and at the six views a screenshot, then CONFIRM by mouse (the episode ends either way).
        shot = None
        for _ in range(12):
            st = _asked(ugv)
            index, legal = st["decision_index"], st["legal_actions"]
            if st["mode"] == "stop_6view":
                shot = _artifacts(tmp_path) / "human_console_stop_observe.png"
                ugv.wait_for_function("[...document.querySelectorAll('#camera img')].every(i => i.complete && i.naturalWidth)")
                ugv.screenshot(path=str(shot))
                ugv.click("button.choice[data-action=CONFIRM]")
                ugv.click("#send")
                made.append(("ugv", index, "CONFIRM"))
                break
            if any(c["status"] == "arrived" for c in st["candidates"]):
                ugv.keyboard.press("s")
                ugv.keyboard.press("Enter")
                made.append(("ugv", index, "STOP_OBSERVE"))
            elif "GO_TO_CANDIDATE" in legal:
                ugv.click("button.choice[data-action=GO_TO_CANDIDATE]")
                ugv.click("#send")
                made.append(("ugv", index, "GO_TO_CANDIDATE"))
            else:
                ugv.keyboard.press("w")
                ugv.keyboard.press("Enter")
                made.append(("ugv", index, "WAIT"))
            _answered(ugv, index)
        assert shot is not None, f"no STOP_OBSERVE within 12 UGV decisions: {made}"
        print(f"\nscreenshot at the UGV's STOP_OBSERVE: {shot}")

        # ----- the run ends; the spectator saw it, read-only.
        assert ev.wait(timeout=60) == 0, "".join(out) + ev.stdout.read()
        spec = pages["spectator"]
        spec.wait_for_function("document.querySelector('.episode .steps') && "
                               "document.querySelector('.episode .steps').innerText.includes('CONFIRM')", timeout=WAIT_MS)
        assert spec.locator(".episode img").count() >= 1
        refused = spec.evaluate("() => fetch('/api/act', {method: 'POST', headers: {'Content-Type': 'application/json'},"
                                " body: JSON.stringify({role: 'uav'})}).then(r => r.status)")
        assert refused == 403
        spec_shot = _artifacts(tmp_path) / "human_console_spectator.png"
        spec.screenshot(path=str(spec_shot))
        print(f"spectator screenshot: {spec_shot}")
        assert not errors, errors
    finally:
        for proc in (ev, spectator):
            if proc is not None and proc.poll() is None:
                proc.terminate()
                proc.wait(timeout=20)

    # ----- the record holds exactly the script's decisions, each traced as a person's.
    db = sqlite3.connect(run_dir / "results.sqlite")
    record = json.loads(db.execute("SELECT record_json FROM episodes").fetchone()[0])
    db.close()
    traces = record["decision_traces"]
    assert [(t["role"], t["decision_index"], t["parsed_action"]) for t in traces] == made  # in the order applied
    assert {t["policy"] for t in traces} == {"human"} and {t["model"] for t in traces} == {"person"}
    assert record["fallbacks"] == 0 and record["decisions_uav"] == 1 and record["decisions_ugv"] == len(made) - 1
    first = traces[0]
    assert first["role"] == "uav" and first["reasks"] == 3 and first["http_attempts"] == 4  # the stale one never counted
    assert json.loads(first["raw_reply"])["message"] == "red truck in D2" and first["latency_s"] > 0
    assert record["termination"] in ("confirmed", "false_confirm")

    # ----- agos report: the run is the Human row.
    report = subprocess.run([*AGOS, "report", str(run_dir), "--out", str(tmp_path / "report")], capture_output=True,
                            text=True, timeout=60)
    assert report.returncode == 0, report.stderr
    assert "| Human |" in (tmp_path / "report" / "main.md").read_text()
