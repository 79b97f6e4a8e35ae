"""Recordings (deploy/recording/recorder.py, deploy/recording/episode.py): a run with ``--record`` writes one rerun file
per episode, read back here with rerun's own reader; a recorder stuck in its handler changes no
record and holds nothing up; the recorder's queue drops and counts what does not fit.

The e2e tests run real processes (``agos eval``) over a real router; the others feed a recorder
through the in-memory bus.
"""

from __future__ import annotations

import copy
import json
import os
import sqlite3
import subprocess
import sys
from collections import Counter, defaultdict
from pathlib import Path

import cv2
import msgspec
import numpy as np
import pytest
from rerun.chunk import RrdReader

from agos.deploy.recording.recorder import STALL_ENV, BoundedInbox, Recorder
from agos.deploy.run.launcher import free_port
from agos.runtime import keys
from agos.runtime.bus import Inbox, MemoryBus, Sample
from agos.runtime.codec import encode
from agos.runtime.schemas import (
    Action,
    Candidate,
    CoordinationState,
    EpisodeRecord,
    EpisodeSpec,
    EpisodeStarted,
    ImageFrame,
    LedgerEntry,
    LoggedStep,
    Pose,
    StepEvent,
    TownRef,
    VehicleSpec,
    VizFrame,
)

AGOS = [sys.executable, "-m", "agos.deploy.cli"]
VOLATILE = {"wall_time_s", "worker_id", "run_id", "decision_traces", "agent_stats"}
ENTITIES = {"/map/region", "/map/target", "/map/uav/path", "/map/uav/position", "/map/ugv/path", "/map/ugv/position",
            "/uav/nadir", "/uav/nadir/grid", "/uav/nadir/cells", "/log/steps", "/outcome"}


class Rrd:
    """A recording read back with rerun's own reader: rows and decision-timeline values per entity."""

    def __init__(self, path: Path) -> None:
        self.rows: Counter[str] = Counter()
        self.timelines: dict[str, set[str]] = defaultdict(set)
        self.decisions: dict[str, list[int]] = defaultdict(list)
        self.sim_times_s: dict[str, list[float]] = defaultdict(list)
        self.static: set[str] = set()
        for chunk in RrdReader(path).stream():
            entity = chunk.entity_path
            self.rows[entity] += chunk.num_rows
            if chunk.is_static:
                self.static.add(entity)
                continue
            self.timelines[entity] |= set(chunk.timeline_names)
            batch = chunk.to_record_batch()
            if "decision" in batch.schema.names:
                self.decisions[entity] += batch.column("decision").to_pylist()
            if "sim_time" in batch.schema.names:
                self.sim_times_s[entity] += [t.total_seconds() for t in batch.column("sim_time").to_pylist()]


def _records(run_dir: Path) -> dict[str, dict]:
    db = sqlite3.connect(run_dir / "results.sqlite")
    rows = db.execute("SELECT episode_id, record_json FROM episodes").fetchall()
    db.close()
    return {ep: json.loads(text) for ep, text in rows}


def _same(record: dict) -> dict:
    return {k: v for k, v in record.items() if k not in VOLATILE}


def _eval(tmp: Path, episodes: Path, name: str, *extra: str, env: dict[str, str] | None = None) -> tuple[Path, str]:
    run_dir = tmp / "runs" / name
    proc = subprocess.run([*AGOS, "eval", "--split", str(episodes), "--runs-dir", str(tmp / "runs"), "--run-dir",
                           str(run_dir), "--port", str(free_port(18000 + os.getpid() % 700)), *extra],
                          cwd=tmp, capture_output=True, text=True, timeout=180,
                          env={**os.environ, "COLUMNS": "150", **(env or {})})
    assert proc.returncode == 0, proc.stdout + proc.stderr
    return run_dir, proc.stdout


@pytest.fixture(scope="module")
def episodes(sample_mid_episodes) -> Path:
    return sample_mid_episodes(1, seed=2)


@pytest.fixture(scope="module")
def plain(tmp_path_factory, episodes: Path) -> dict[str, dict]:
    """The records of a run without a recorder."""
    run_dir, _ = _eval(tmp_path_factory.mktemp("plain"), episodes, "plain")
    return _records(run_dir)


@pytest.mark.e2e
def test_a_recorded_run_writes_one_rrd_per_episode(tmp_path: Path, episodes: Path, plain: dict[str, dict]) -> None:
    """Full resolution: every decision's views are in the file, at the decision they were shown for,
    on both timelines; the map holds both trajectories, the target and the candidates."""
    out = tmp_path / "rec"
    run_dir, stdout = _eval(tmp_path, episodes, "rec", "--record", str(out), "--record-full")
    assert f"recordings: 1 episode in {out}" in stdout, stdout
    records = _records(run_dir)
    assert {ep: _same(r) for ep, r in records.items()} == {ep: _same(r) for ep, r in plain.items()}
    assert sorted(p.name for p in out.glob("*.rrd")) == sorted(f"{ep}.rrd" for ep in records)
    status = json.loads((out / "recorder.json").read_text())
    assert status["status"] == "stopped" and status["full_resolution"] and not status["dropped_by_queue"], status
    for episode, record in records.items():
        rrd = Rrd(out / f"{episode}.rrd")
        assert set(rrd.rows) >= ENTITIES, sorted(rrd.rows)
        assert {"/map", "/map/region", "/map/target", "/map/search_area", "/uav/nadir/grid"} <= rrd.static
        for entity, timelines in rrd.timelines.items():
            assert timelines == {"sim_time", "decision"}, (entity, timelines)  # no wall-clock timelines
        steps = record["step_log"]
        uav_steps = [k for k, s in enumerate(steps, start=1) if s["role"] == "uav"]
        ugv_steps = [k for k, s in enumerate(steps, start=1) if s["role"] == "ugv"]
        # One nadir view per UAV decision, logged at that decision of the shared timeline.
        assert sorted(rrd.decisions["/uav/nadir"]) == uav_steps
        assert sorted(rrd.sim_times_s["/uav/nadir"]) == pytest.approx([steps[k - 1]["sim_time_s"] for k in uav_steps],
                                                                      abs=1e-3)
        # The UGV: a forward view while driving, the six views after a STOP_OBSERVE (until it moves).
        six = sorted(rrd.decisions["/ugv/six/front"])
        assert sorted(rrd.decisions["/ugv/forward"]) == [k for k in ugv_steps if k not in six]
        assert six == _six_view_steps(steps) and six
        for view in ("front_left", "front_right", "back_left", "back", "back_right"):
            assert sorted(rrd.decisions[f"/ugv/six/{view}"]) == six
        assert rrd.rows["/map/uav/path"] >= len(uav_steps) and rrd.rows["/map/ugv/path"] >= len(ugv_steps)
        assert {f"/map/candidates/{c['candidate_id']}" for c in record["candidates"]} <= set(rrd.rows)
        assert rrd.rows["/log/steps"] == len(steps) + 2  # the start, every decision, the end
        assert max(rrd.decisions["/map/ugv/path"]) == len(steps)
        assert status["episodes"][episode]["frames"] == {"uav": len(uav_steps), "ugv": len(ugv_steps) + 5 * len(six)}


def _six_view_steps(steps: list[dict]) -> list[int]:
    """The episode steps whose UGV observation held the six views: those after a STOP_OBSERVE, before
    the UGV moved again (world/sim/rules.py)."""
    out, stopped = [], False
    for k, step in enumerate(steps, start=1):
        if step["role"] != "ugv":
            continue
        if stopped:
            out.append(k)
        if step["applied"] == "STOP_OBSERVE":
            stopped = True
        elif step["applied"] in ("MOVE_TO_ROAD_WAYPOINT", "GO_TO_CANDIDATE", "REJECT"):
            stopped = False
    return out


@pytest.mark.e2e
def test_a_stuck_recorder_changes_no_record_and_holds_nothing_up(tmp_path: Path, episodes: Path,
                                                                 plain: dict[str, dict]) -> None:
    """The recorder's handler sleeps 30 s at its first sample: the run finishes meanwhile (the recorder is
    stopped while still stuck) with the records of a run without a recorder, and the recorder then writes
    what it had queued."""
    out = tmp_path / "rec"
    run_dir, stdout = _eval(tmp_path, episodes, "stuck", "--record", str(out), env={STALL_ENV: "30"})
    assert {ep: _same(r) for ep, r in _records(run_dir).items()} == {ep: _same(r) for ep, r in plain.items()}
    log = (run_dir / "logs" / "recorder.log").read_text()
    assert "the handler stops for 30 s" in log and "stopped while stuck" in log, log
    assert "recordings: 1 episode in" in stdout, stdout
    assert len(list(out.glob("*.rrd"))) == 1


# ----- the recorder without processes ------------------------------------------------------------

RUN, EP, WORKER = "r", "grid-s7-mid-000-v1", "w"
EP2 = "grid-s7-mid-001-v1"


def _jpeg(side_px: int) -> bytes:
    ok, data = cv2.imencode(".jpg", np.full((side_px, side_px, 3), 90, np.uint8))
    assert ok
    return data.tobytes()


def _stream(episode: str = EP) -> list[tuple[str, object]]:
    """One short episode as the world worker ``WORKER`` publishes it on its slot's visualisation keys:
    UAV move and annotate, UGV to the candidate, STOP_OBSERVE, CONFIRM (frames of the STOP_OBSERVE
    decision arrive first)."""
    spec = EpisodeSpec(episode_id=episode, town=TownRef(generator="nowhere", seed=0, town_id="none"), asset_sha256="ab" * 32,
                       difficulty="mid", region_world_m=(0.0, 0.0, 100.0, 100.0),
                       target=VehicleSpec(model="sedan", colour="red", position_world_m=(50.0, 50.0, 0.0), yaw_rad=0.0),
                       uav_start_waypoint="U0_0", ugv_start_waypoint="R1", active_uav_waypoints=["U0_0"], seed=1)
    polygon = [(40.0, 40.0), (60.0, 40.0), (60.0, 60.0), (40.0, 60.0)]
    plan = [("uav", 1, "MOVE_TO_UAV_WAYPOINT", (40.0, 40.0)), ("uav", 2, "ANNOTATE_CANDIDATE", (40.0, 40.0)),
            ("ugv", 1, "GO_TO_CANDIDATE", (50.0, 30.0)), ("ugv", 2, "STOP_OBSERVE", (50.0, 30.0)),
            ("ugv", 3, "CONFIRM", (50.0, 30.0))]
    out: list[tuple[str, object]] = [
        (keys.viz_events(RUN, WORKER), EpisodeStarted(run_id=RUN, episode_id=episode, difficulty="mid",
                                                      worker_id=WORKER, town_id="none", asset_sha256="ab" * 32)),
        (keys.viz_spec(RUN, WORKER), spec)]
    log: list[LoggedStep] = []
    for step, (role, index, action, xy) in enumerate(plan, start=1):
        t = 10.0 * step
        pose = Pose(position_world_m=(*xy, 80.0 if role == "uav" else 0.0), yaw_rad=0.0)
        names = ["front_left", "front", "front_right", "back_left", "back", "back_right"] if index == 3 else \
            ["nadir" if role == "uav" else "forward"]
        frames = [VizFrame(run_id=RUN, episode_id=episode, role=role, decision_index=index, sim_time_s=t, pose=pose,
                           image=ImageFrame(name=n, kind="rgb", encoding="jpeg", data=_jpeg(160))) for n in names]
        event = StepEvent(run_id=RUN, episode_id=episode, role=role, decision_index=index, episode_step=step,
                          sim_time_s=t, requested=Action(run_id=RUN, episode_id=episode, role=role, decision_index=index,
                                                         action=action, cell="C3" if role == "uav" else None),
                          applied=action, pose_after=pose, candidate_id="C001" if step >= 2 else None)
        frame_key = keys.viz_frame(RUN, WORKER, role)
        if index == 3:  # frames after their step event
            out += [(keys.viz_events(RUN, WORKER), event)] + [(frame_key, f) for f in frames]
        else:
            out += [(frame_key, f) for f in frames] + [(keys.viz_events(RUN, WORKER), event)]
        if step >= 2:
            status = {2: "pending", 3: "arrived", 4: "arrived", 5: "confirmed"}[step]
            out.append((keys.viz_coord(RUN, WORKER), CoordinationState(
                run_id=RUN, episode_id=episode, sim_time_s=t, decisions_used=step,
                candidates=[Candidate(candidate_id="C001", cell="C3", polygon_world_m=polygon, center_world_m=(50.0, 50.0),
                                      status=status, created_sim_time_s=20.0)])))
        log.append(LoggedStep(role=role, decision_index=index, sim_time_s=t, applied=action, position_world_m=xy,
                              road_path_world_m=[(50.0, 0.0), (50.0, 30.0)] if step == 3 else [],
                              candidate_polygon_world_m=polygon if step == 2 else []))
    record = EpisodeRecord(run_id=RUN, episode_id=episode, difficulty="mid", status="finished", termination="confirmed",
                           success=True, ground_observed=True, n_confirm=1, ugv_path_length_m=30.0, shortest_path_length_m=30.0,
                           final_distance_m=20.0, uav_budget=80, uav_first_visible_step=1, candidates=[], decisions_uav=2,
                           decisions_ugv=3, sim_time_s=50.0, wall_time_s=1.0, worker_id=WORKER, town_id="none",
                           asset_sha256="ab" * 32, seed=1, renderer="tiny", step_log=log,
                           ledger=[LedgerEntry(seq=1, kind="sync", sender="uav", receiver="ugv", sent_s=20.0, size_bytes=90,
                                               delivered=False, drop_reason="loss")])
    return out + [(keys.viz_result(RUN, WORKER), record)]


def test_the_recorder_writes_the_stream_of_an_episode(tmp_path: Path) -> None:
    bus = MemoryBus()
    recorder = Recorder(bus, RUN, tmp_path)  # no town can be had for this spec: no map image, the rest is drawn
    for key, message in _stream():
        bus.publish_viz(key, message)
    while (sample := recorder.inbox.get(timeout_s=0)) is not None:
        recorder.handle(sample)
    assert list(recorder.closing) == [EP]  # the record came: the file is closed a little later (late frames)
    recorder.finish()
    assert not recorder.open and recorder.finished[EP]["record"]
    rrd = Rrd(tmp_path / f"{EP}.rrd")
    assert rrd.decisions["/uav/nadir"] == [1, 2]
    assert rrd.decisions["/ugv/forward"] == [3, 4] and rrd.decisions["/ugv/six/back"] == [5]  # logged once its step came
    assert rrd.rows["/map/candidates/C001"] == 3  # pending, arrived, confirmed
    assert rrd.decisions["/log/link"] == [2] and rrd.rows["/uav/nadir/annotated"] == 1
    assert max(rrd.decisions["/map/ugv/path"]) == 5 and rrd.rows["/outcome"] == 1
    assert {"/map/region", "/map/target", "/uav/nadir/grid", "/uav/nadir/cells"} <= rrd.static


def test_a_step_event_lost_on_the_stream_comes_from_the_record(tmp_path: Path) -> None:
    """The stream is best effort: without the UGV's STOP_OBSERVE event (decision 4) the file still has
    every decision in its step log and the forward view that waited for it, taken from the record."""
    bus = MemoryBus()
    recorder = Recorder(bus, RUN, tmp_path)
    for key, message in _stream():
        if not (isinstance(message, StepEvent) and message.episode_step == 4):
            bus.publish_viz(key, message)
    while (sample := recorder.inbox.get(timeout_s=0)) is not None:
        recorder.handle(sample)
    recorder.finish()
    rrd = Rrd(tmp_path / f"{EP}.rrd")
    assert rrd.rows["/log/steps"] == 5 + 2  # the start, every decision, the end
    assert rrd.decisions["/ugv/forward"] == [3, 4]


def test_one_slot_carries_two_episodes_in_a_row_into_two_files(tmp_path: Path) -> None:
    """Keys name the world worker, not the episode: the worker's next episode follows on the same keys,
    its first frame right after the previous record, and the previous episode's last frames (the six
    views of its CONFIRM, from the world's frame thread) arrive after both. Each sample goes to the
    episode its payload names: two files, each as if it had been alone."""
    first, second = _stream(EP), _stream(EP2)
    late = [(k, m) for k, m in first if isinstance(m, VizFrame) and m.role == "ugv" and m.decision_index == 3]
    assert len(late) == 6 and {k for k, _ in first} == {k for k, _ in second}  # the same keys
    stream = [item for item in first if item not in late] + second[2:3] + late + second[:2] + second[3:]
    assert isinstance(second[2][1], VizFrame)  # B's first frame arrives before its start and spec
    bus = MemoryBus()
    recorder = Recorder(bus, RUN, tmp_path)
    for key, message in stream:
        bus.publish_viz(key, message)
    while (sample := recorder.inbox.get(timeout_s=0)) is not None:
        recorder.handle(sample)
    assert set(recorder.closing) == set(recorder.open) == {EP, EP2} and not recorder.rejections.total
    recorder.finish()
    assert sorted(p.name for p in tmp_path.glob("*.rrd")) == [f"{EP}.rrd", f"{EP2}.rrd"]
    for episode in (EP, EP2):
        seen = recorder.finished[episode]
        assert seen["record"] and seen["steps"] == 5 and seen["frames"] == {"uav": 2, "ugv": 2 + 6}, (episode, seen)
        rrd = Rrd(tmp_path / f"{episode}.rrd")
        assert rrd.decisions["/uav/nadir"] == [1, 2]
        assert rrd.decisions["/ugv/forward"] == [3, 4] and rrd.decisions["/ugv/six/back"] == [5]
        assert rrd.rows["/log/steps"] == 5 + 2 and rrd.rows["/outcome"] == 1


def test_the_recorder_refuses_what_is_not_its_run(tmp_path: Path) -> None:
    bus = MemoryBus()
    recorder = Recorder(bus, RUN, tmp_path)
    recorder.handle(Sample(keys.viz_events(RUN, WORKER), b"\x93garbage"))
    stranger = EpisodeStarted(run_id="other", episode_id=EP, difficulty="mid", worker_id=WORKER, town_id="t",
                              asset_sha256="")
    recorder.handle(Sample(keys.viz_events(RUN, WORKER), encode(stranger)))
    assert recorder.rejections.total == 2 and not recorder.open


@pytest.mark.parametrize("episode", ["..", "../x", "-rf", "", "a/b", "x" * 129])
def test_the_recorder_refuses_a_payload_that_names_no_valid_episode(tmp_path: Path, episode: str) -> None:
    """The episode id comes from the payload and names the file: one that is no valid id is refused."""
    bus = MemoryBus()
    recorder = Recorder(bus, RUN, tmp_path / "out")
    started = EpisodeStarted(run_id=RUN, episode_id=episode, difficulty="mid", worker_id=WORKER, town_id="t",
                             asset_sha256="")
    recorder.handle(Sample(keys.viz_events(RUN, WORKER), encode(started)))
    assert recorder.rejections.counts == {("events", "names no valid episode"): 1} and not recorder.open
    assert [p.name for p in tmp_path.iterdir()] == ["out"] and not list((tmp_path / "out").iterdir())


def test_the_recorder_refuses_a_message_that_names_no_episode(tmp_path: Path) -> None:
    from agos.runtime.schemas import RunManifest

    recorder = Recorder(MemoryBus(), RUN, tmp_path)
    manifest = RunManifest(run_id=RUN, status="running", policies={}, n_episodes=1, created_utc="now")
    recorder.handle(Sample(keys.viz_events(RUN, WORKER), encode(manifest)))
    assert recorder.rejections.counts == {("events", "a RunManifest where none is expected"): 1} and not recorder.open


def _payload(episode: object, pad_bytes: int) -> bytes:
    """A payload that names ``episode``, ``pad_bytes`` more than its smallest."""
    return msgspec.msgpack.encode({"episode_id": episode, "pad": bytes(pad_bytes)})


def test_a_full_queue_drops_and_counts_instead_of_blocking() -> None:
    """Counted by the episode the dropped payload names (the key names the worker only) and kind."""
    inbox = BoundedInbox(max_samples=3, max_bytes=1000)
    frames = [_payload(EP, k) for k in range(5)]
    for payload in frames:
        inbox.put(Sample(keys.viz_frame(RUN, WORKER, "uav"), payload))
    inbox.put(Sample(keys.viz_events(RUN, WORKER), _payload(EP2, 0)))
    inbox.put(Sample(keys.viz_events(RUN, WORKER), _payload("../x", 0)))  # no valid id: no episode's
    inbox.put(Sample(keys.viz_events(RUN, WORKER), b"\x93garbage"))
    assert inbox.dropped == {(EP, "frame"): 2, (EP2, "events"): 1, ("?", "events"): 2}
    assert inbox.get(0) is not None
    inbox.put(Sample(keys.viz_coord(RUN, WORKER), _payload(EP2, 1000)))  # alone larger than the byte bound
    assert inbox.dropped[(EP2, "coord")] == 1 and inbox.queued_bytes == len(frames[1]) + len(frames[2])


def test_what_the_queue_dropped_is_told_per_episode_of_one_slot(tmp_path: Path) -> None:
    """The queue has room for the first episode and three samples of the worker's next: the drops are
    the second episode's, in its file's summary and recorder.json, none the first's."""
    first, second = _stream(EP), _stream(EP2)
    recorder = Recorder(MemoryBus(), RUN, tmp_path, inbox=BoundedInbox(max_samples=len(first) + 3))
    for key, message in first + second:
        recorder.bus.publish_viz(key, message)
    while (sample := recorder.inbox.get(timeout_s=0)) is not None:
        recorder.handle(sample)
    recorder.finish()
    recorder._status("stopped")
    assert recorder.finished[EP]["dropped_by_queue"] == 0 and recorder.finished[EP]["record"]
    assert recorder.finished[EP2]["dropped_by_queue"] == len(second) - 3 and not recorder.finished[EP2]["record"]
    status = json.loads((tmp_path / "recorder.json").read_text())
    assert sum(status["dropped_by_queue"].values()) == len(second) - 3 and status["episodes"].keys() == {EP, EP2}


# ----- what the world sends for recorders ----------------------------------------------------------

def test_every_view_gets_a_thumbnail_and_full_frames_share_the_observations_bytes(observations) -> None:
    from agos.runtime.viz import THUMB_PX, full_frames, thumbnails

    six = next(o for o in observations if o.mode == "stop_6view")
    rgb = [f for f in six.images if f.kind == "rgb"]
    thumbs = thumbnails(six)
    assert [t.image.name for t in thumbs] == [f.name for f in rgb] == \
        ["front_left", "front", "front_right", "back_left", "back", "back_right"]
    assert all(max(cv2.imdecode(np.frombuffer(t.image.data, np.uint8), cv2.IMREAD_COLOR).shape[:2]) <= THUMB_PX
               for t in thumbs)
    full = full_frames(six)
    assert [f.image for f in full] == rgb and all(a.image.data is b.data for a, b in zip(full, rgb, strict=True))
    uav = next(o for o in observations if o.role == "uav")
    assert [f.image.name for f in full_frames(uav)] == ["nadir"]  # not the grid overlay, depth, semantics or map


def test_the_world_sends_full_frames_only_while_someone_asks(observations) -> None:
    from agos.runtime.process import StopFlag
    from agos.world.sim.worker import BusDecisionSource, WorkerSlot

    later = [o for o in observations if o.decision_index > 1]  # no waiting for agents' ready tokens
    # copies: decide() stamps its attempt and timeout on what it sends, and the fixture's observations are
    # shared with other modules' tests (a VLM test once read this 0.01 s timeout as its decision's time)
    obs = {"uav": copy.copy(next(o for o in later if o.role == "uav")),
           "ugv": copy.copy(next(o for o in later if o.mode == "stop_6view"))}
    bus = MemoryBus()
    run = obs["uav"].run_id
    slot = WorkerSlot(bus, run, WORKER)
    source = BusDecisionSource(slot, obs["uav"].episode_id, timeout_s=0.01, stop=StopFlag())

    def full_sent() -> list[str]:
        return [k for k, _ in bus.published if k.startswith(keys.viz_full(run, WORKER, ""))]

    source.decide(obs)
    assert full_sent() == []  # nobody asks: nothing made, nothing sent (agos watch subscribes to viz_light)
    assert not any("/full/" in k for k in keys.viz_light()) and keys.viz_light(full=True)[2].endswith("/full/*")
    bus.subscribe(keys.viz_full("*", "*", "*"), Inbox())
    source.decide(obs)
    assert sorted(full_sent()) == sorted([keys.viz_full(run, WORKER, "uav")] + 6 * [keys.viz_full(run, WORKER, "ugv")])
    source.close()
    slot.close()
