"""The human console without a browser or a bus: what the page is shown, the board that takes each
decision once and only when legal, durations, the Human row, and decision timeouts of hours."""

from __future__ import annotations

import json
import sqlite3
import urllib.request
from concurrent.futures import CancelledError
from pathlib import Path
from unittest.mock import MagicMock

import numpy as np
import pytest

from agos.agents.human.board import MESSAGE_LIMIT, DecisionBoard
from agos.agents.human.page_model import shown
from agos.agents.human.server import ConsoleServer
from agos.deploy.run.human import parse_duration
from agos.deploy.run.orchestrator import STUCK_AFTER_S, STUCK_MARGIN_S, Orchestrator
from agos.evaluator.human_row import is_human_run
from agos.runtime.codec import encode_jpeg, encode_png
from agos.runtime.episode_config import EpisodeConfig
from agos.runtime.schemas import Candidate, CoordinationState, ImageFrame, Observation, Pose, Waypoint


def _obs(index: int = 1, *, role: str = "uav", episode: str = "ep-1", attempt: int = 1) -> Observation:
    rgb = np.zeros((64, 64, 3), np.uint8)
    images = [ImageFrame(name="nadir", kind="rgb_grid", encoding="jpeg", data=encode_jpeg(rgb)),
              ImageFrame(name="nadir", kind="depth", encoding="png", data=encode_png(np.zeros((8, 8), np.uint16))),
              ImageFrame(name="map", kind="map", encoding="png", data=encode_png(np.zeros((100, 100, 3), np.uint8)))]
    candidate = Candidate(candidate_id="C001", cell="C3", polygon_world_m=[(0.0, 0.0), (10.0, 0.0), (10.0, 10.0)],
                          center_world_m=(5.0, 5.0), status="pending", created_sim_time_s=3.0)
    return Observation(
        run_id="r", episode_id=episode, role=role, decision_index=index, attempt=attempt, decision_timeout_s=7200.0,
        sim_time_s=10.0, pose=Pose(position_world_m=(50.0, 50.0, 80.0), yaw_rad=0.0), mode="aerial", images=images,
        references=[ImageFrame(name="ref_top", kind="rgb", encoding="png", data=encode_png(rgb), metres_per_px=0.05)],
        legal_actions=["MOVE_TO_UAV_WAYPOINT", "ANNOTATE_CANDIDATE", "NO_RELIABLE_CANDIDATE", "WAIT"],
        waypoint_options=[Waypoint(waypoint_id="U1_1", position_world_m=(0.0, 200.0, 80.0), kind="uav_grid")],
        region_world_m=(0.0, 0.0, 200.0, 100.0),
        coordination=CoordinationState(run_id="r", episode_id=episode, sim_time_s=10.0, candidates=[candidate],
                                       decisions_used=4, decision_budget=80))


def test_the_page_shows_what_the_vlm_prompt_carries_and_draws_on_the_map_in_its_pixels() -> None:
    view = shown(_obs())
    assert [i.label for i in view.images] == ["aerial_grid", "topdown_map", "target_ref_top"]  # no depth, as the VLM
    st = view.state
    assert st["budget"] == {"used": 4, "total": 80, "left": 76} and st["decision_timeout_s"] == 7200.0
    # The map spans the region's longer side (200 m over 100 px), north up: (0, 200) is the top-left corner.
    assert st["options"][0]["map_px"] == [0.0, 0.0] and st["pose"]["map_px"] == [25.0, 75.0]
    assert st["candidates"][0]["polygon_px"][1] == [5.0, 100.0]
    assert {c["action"] for c in view.choices} == {"MOVE_TO_UAV_WAYPOINT", "ANNOTATE_CANDIDATE", "NO_RELIABLE_CANDIDATE",
                                                   "WAIT"}
    assert shown(_obs()).sha256 == view.sha256 != shown(_obs(2)).sha256


def test_a_decision_is_taken_once_and_only_when_legal() -> None:
    board = DecisionBoard(["uav"], player="ana")
    asked = board.ask(_obs())
    assert asked.kind == "new" and asked.future is not None
    assert board.ask(_obs()).kind == "pending"  # the world's resend joins the open decision
    key = {"role": "uav", "episode_id": "ep-1", "attempt": 1, "decision_index": 1}

    illegal = board.submit({**key, "action": "CONFIRM"})
    assert (illegal.status, illegal.ok) == (422, False) and "not legal" in illegal.message and "still yours" in illegal.message
    assert "not an option" in board.submit({**key, "action": "MOVE_TO_UAV_WAYPOINT", "waypoint_id": "U9_9"}).message
    assert "F7" in board.submit({**key, "action": "ANNOTATE_CANDIDATE", "cell": "F7"}).message
    long = board.submit({**key, "action": "WAIT", "message": "x" * (MESSAGE_LIMIT + 1)})
    assert long.status == 422 and f"at most {MESSAGE_LIMIT}" in long.message
    assert board.submit({**key, "role": "ugv", "action": "WAIT"}).status == 400
    assert board.submit("WAIT").status == 400
    stale = board.submit({**key, "decision_index": 0, "action": "WAIT"})
    assert stale.status == 409 and "Stale" in stale.message
    assert not asked.future.done()

    sent = board.submit({**key, "action": "annotate_candidate", "cell": "d2", "message": "red truck", "input": "mouse"})
    assert sent.ok and sent.status == 200
    action = asked.future.result(timeout=1)
    assert (action.action, action.cell, action.message) == ("ANNOTATE_CANDIDATE", "D2", "red truck")
    trace = action.trace
    assert trace is not None and (trace.policy, trace.model, trace.stage, trace.fallback) == ("human", "ana", "aerial", False)
    assert (trace.http_attempts, trace.reasks) == (5, 4) and trace.prompt_sha256 == shown(_obs()).sha256
    assert json.loads(trace.raw_reply or "")["input"] == "mouse"

    again = board.submit({**key, "action": "WAIT"})  # a double click, a second window
    assert again.status == 409 and "already sent" in again.message
    assert board.ask(_obs()).action is action  # the world asks again: the same answer goes out


def test_a_decision_the_world_gave_up_on_is_closed_and_a_late_answer_is_stale() -> None:
    board = DecisionBoard(["uav"])
    first = board.ask(_obs(1))
    second = board.ask(_obs(2))  # the world applied WAIT after its timeout and asks decision 2
    assert second.kind == "new" and first.future is not None and first.future.cancelled()
    with pytest.raises(CancelledError):
        first.future.result(timeout=0)
    late = board.submit({"role": "uav", "episode_id": "ep-1", "attempt": 1, "decision_index": 1, "action": "WAIT"})
    assert late.status == 409 and "decision 2 is" in late.message
    snap = json.loads(board.snapshot_json())
    assert snap["by_role"]["uav"]["asked"]["state"]["decision_index"] == 2
    assert snap["history"][0]["outcome"] == "not answered" and "applied WAIT" in snap["notices"][0]["text"]
    board.forget("ep-1")
    assert second.future is not None and second.future.cancelled()
    assert "ended" in board.submit({"role": "uav", "episode_id": "ep-1", "decision_index": 2, "action": "WAIT"}).message


@pytest.mark.loopback  # the console's HTTP server, in this process
def test_the_server_serves_the_page_the_state_images_and_refusals() -> None:
    board = DecisionBoard(["uav"])
    board.ask(_obs())
    server = ConsoleServer(board, "127.0.0.1", 0).start()
    base = f"http://127.0.0.1:{server.port}"
    try:
        assert b"console.js" in urllib.request.urlopen(base + "/").read()
        state = json.loads(urllib.request.urlopen(base + "/api/state").read())
        url = state["by_role"]["uav"]["asked"]["images"][0]["url"]
        assert urllib.request.urlopen(base + url).read()[:2] == b"\xff\xd8"  # the JPEG as the world sent it

        def post(body: bytes, kind: str = "application/json") -> tuple[int, dict]:
            req = urllib.request.Request(base + "/api/act", data=body, headers={"Content-Type": kind})
            try:
                with urllib.request.urlopen(req) as r:
                    return r.status, json.loads(r.read())
            except urllib.error.HTTPError as e:
                return e.code, json.loads(e.read())

        assert post(b"{not json")[0] == 400
        assert post(b'{"action": "WAIT"}', "text/plain")[0] == 415  # a cross-site form cannot decide
        code, answer = post(json.dumps({"role": "uav", "episode_id": "ep-1", "decision_index": 1,
                                        "action": "CONFIRM"}).encode())
        assert code == 422 and not answer["ok"] and "not legal" in answer["message"]
    finally:
        server.close()


def test_durations_people_type() -> None:
    assert [parse_duration(t) for t in ("90", "90s", "30m", "2h", "1.5h")] == [90, 90, 1800, 7200, 5400]
    for bad in ("", "0", "-5", "2d", "soon"):
        with pytest.raises(ValueError):
            parse_duration(bad)


def test_a_decision_timeout_of_hours_is_not_taken_for_a_stuck_world(monkeypatch, tmp_path: Path) -> None:
    monkeypatch.setenv("AGOS_HEALTH_DIR", str(tmp_path))
    hours = Orchestrator(MagicMock(), "r", [], policies={}, config=EpisodeConfig(decision_timeout_s=7200.0))
    assert hours.stuck_after_s == 7200.0 + STUCK_MARGIN_S
    assert Orchestrator(MagicMock(), "r", [], policies={}, config=EpisodeConfig()).stuck_after_s == STUCK_AFTER_S


def test_human_runs_are_found_by_run_json_or_by_their_traces(tmp_path: Path) -> None:
    run = tmp_path / "run-a"
    run.mkdir()
    (run / "run.json").write_text(json.dumps({"policies": {"uav": "human", "ugv": "human"}}))
    assert is_human_run(run) and is_human_run(run / "results.sqlite")
    (run / "run.json").write_text(json.dumps({"policies": {"uav": "human", "ugv": "heuristic"}}))
    assert not is_human_run(run)
    copied = tmp_path / "copied.sqlite"  # a results file without its run directory
    db = sqlite3.connect(copied)
    db.execute("CREATE TABLE episodes (run_id, episode_id, difficulty, status, success, record_json, stored_utc)")
    traces = [{"role": r, "policy": "human"} for r in ("uav", "ugv")]
    db.execute("INSERT INTO episodes VALUES ('r', 'e', 'easy', 'finished', 1, ?, '')",
               (json.dumps({"decision_traces": traces}),))
    db.commit()
    db.close()
    assert is_human_run(copied)


def test_the_spectator_follows_episodes_by_their_payload_on_one_workers_keys() -> None:
    """Keys name the world worker: its next episode follows on the same keys, and a late frame of the
    one before still lands on that one. Another run's samples are left out when a run is given."""
    from agos.agents.human.spectator import SpectatorBoard
    from agos.runtime import keys
    from agos.runtime.codec import encode
    from agos.runtime.schemas import EpisodeRecord, EpisodeStarted, VizFrame

    def frame(episode: str, index: int) -> bytes:
        image = ImageFrame(name="nadir", kind="rgb", encoding="jpeg", data=encode_jpeg(np.full((8, 8, 3), index, np.uint8)))
        return encode(VizFrame(run_id="r", episode_id=episode, role="uav", decision_index=index, sim_time_s=1.0 * index,
                               pose=Pose(position_world_m=(0.0, 0.0, 80.0), yaw_rad=0.0), image=image))

    def started(episode: str, run: str = "r") -> bytes:
        return encode(EpisodeStarted(run_id=run, episode_id=episode, difficulty="easy", worker_id="w", town_id="t",
                                     asset_sha256=""))

    record = encode(EpisodeRecord(run_id="r", episode_id="ep-a", difficulty="easy", status="finished",
                                  termination="confirmed", success=True, ground_observed=True, n_confirm=1,
                                  ugv_path_length_m=1.0, shortest_path_length_m=1.0, final_distance_m=2.0, uav_budget=10,
                                  uav_first_visible_step=1, candidates=[], decisions_uav=1, decisions_ugv=1,
                                  sim_time_s=5.0, wall_time_s=1.0, worker_id="w", town_id="t", asset_sha256="", seed=1,
                                  renderer="tiny"))
    board = SpectatorBoard("r")
    events, frames = keys.viz_events("r", "w"), keys.viz_frame("r", "w", "uav")
    for key, payload in [(events, started("ep-a")), (frames, frame("ep-a", 1)), (keys.viz_result("r", "w"), record),
                         (events, started("ep-b")), (frames, frame("ep-b", 1)), (frames, frame("ep-a", 2)),
                         (keys.viz_events("other", "w"), started("ep-c", "other"))]:
        board.take(key, payload)
    shown_episodes = {ep["episode_id"]: ep for ep in board.snapshot()["episodes"]}
    assert shown_episodes.keys() == {"ep-a", "ep-b"} and board.unreadable == 0
    assert shown_episodes["ep-a"]["outcome"]["termination"] == "confirmed" and shown_episodes["ep-b"]["outcome"] is None
    assert shown_episodes["ep-a"]["frames"]["uav"]["decision_index"] == 2
    assert shown_episodes["ep-b"]["frames"]["uav"]["decision_index"] == 1
