"""MCAP recordings (``agos record --format mcap``, deploy/recording/mcap_episode.py): one episode's
visualisation stream, as a world worker publishes it, recorded by the recorder and read back with the
MCAP libraries' own readers (``mcap.reader.make_reader``, ``mcap_ros2.decoder.DecoderFactory``; json
for agos's channels); counts and times checked against the episode's record and observations.

The episode is played in this process (``agos.Env``, flat look, small images, the oracle: it annotates,
sends messages, stops to observe and confirms within a short budget) with the world worker's own sink
(``BusSink``) on an in-memory bus, plus what the worker adds around it: the start, the spec, every
view at full resolution and as a thumbnail, the record's copy.
"""

from __future__ import annotations

import json
from collections import defaultdict
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import jsonschema
import msgspec
import numpy as np
import pytest
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory

from agos import Env, episode_config
from agos.agents.registry import make_policy
from agos.deploy.recording import mcap_episode
from agos.deploy.recording.recorder import Recorder
from agos.runtime import keys
from agos.runtime.bus import Inbox, MemoryBus, Sample
from agos.runtime.codec import decode
from agos.runtime.schemas import EpisodeRecord, EpisodeStarted, Observation, StepEvent
from agos.runtime.viz import full_frames, thumbnails
from agos.world.episodes.sampling import sample_episode
from agos.world.sim.scene import Scene
from agos.world.sim.worker import BusSink
from agos.world.towns.asset import open_town

from support.episodes import SMALL_CAMERAS

RUN, WORKER = "mcap", "w"
JSON_TOPICS = {"/agos/episode", "/agos/steps", "/agos/coordination", "/agos/messages", "/agos/link", "/agos/record"}


@dataclass
class Played:
    """One episode's visualisation stream (every sample, in the order published), its record and observations."""

    samples: list[Sample]
    record: EpisodeRecord
    observations: list[Observation]


@pytest.fixture(scope="module")
def played() -> Played:
    town = open_town("grid-s7")
    bus, stream = MemoryBus(), Inbox()
    bus.subscribe(keys.viz_all(RUN), stream)
    observations: list[Observation] = []
    policies = {r: make_policy("oracle", r) for r in ("uav", "ugv")}
    with Scene(town.layout, look="flat") as scene:
        spec = sample_episode(town, scene, "mid", 0, seed=2, stream=1)
        bus.publish_viz(keys.viz_events(RUN, WORKER), EpisodeStarted(
            run_id=RUN, episode_id=spec.episode_id, difficulty=spec.difficulty, worker_id=WORKER, town_id=town.town_id,
            asset_sha256=town.sha256))
        bus.publish_viz(keys.viz_spec(RUN, WORKER), spec)
        config = episode_config(policies="oracle", look="flat", decision_budget=12, cameras=SMALL_CAMERAS)
        with Env(spec, config, run_id=RUN, worker_id=WORKER, scene=scene, town=town,
                 sink=BusSink(bus, RUN, WORKER)) as env:
            asked = env.reset()
            while asked:
                for role, obs in asked.items():  # as the world worker sends them, before the decision
                    observations.append(obs)
                    for frame in full_frames(obs):
                        bus.publish_viz(keys.viz_full(RUN, WORKER, role), frame)
                    for frame in thumbnails(obs):
                        bus.publish_viz(keys.viz_frame(RUN, WORKER, role), frame)
                actions = {r: policies[r].act(o) for r, o in asked.items()}
                asked = env.step(actions).observations
            record = env.record
    bus.publish(keys.viz_result(RUN, WORKER), record)
    return Played(stream.drain(), record, observations)


@dataclass
class Message:
    topic: str
    log_time: int
    publish_time: int
    value: Any


@dataclass
class Mcap:
    """A file read back with the MCAP libraries: the messages of each channel in the file's order."""

    path: Path
    by_topic: dict[str, list[Message]] = field(default_factory=lambda: defaultdict(list))
    encodings: dict[str, tuple[str, str, str]] = field(default_factory=dict)
    """Topic -> (schema name, schema encoding, message encoding)."""
    schemas: dict[str, bytes] = field(default_factory=dict)
    in_order: list[int] = field(default_factory=list)
    """Every message's log time, in the order read with ``log_time_order``."""
    metadata: dict[str, dict[str, str]] = field(default_factory=dict)

    @classmethod
    def read(cls, path: Path) -> Mcap:
        out, ros = cls(path), DecoderFactory()
        with path.open("rb") as f:
            reader = make_reader(f, decoder_factories=[ros])
            for schema, channel, message in reader.iter_messages(log_time_order=False):
                assert schema is not None
                out.encodings[channel.topic] = (schema.name, schema.encoding, channel.message_encoding)
                out.schemas[channel.topic] = schema.data
                if channel.message_encoding == "cdr":
                    decoder = ros.decoder_for(channel.message_encoding, schema)
                    assert decoder is not None
                    value = decoder(message.data)
                else:
                    assert channel.message_encoding == "json"
                    value = json.loads(message.data)
                out.by_topic[channel.topic].append(Message(channel.topic, message.log_time, message.publish_time, value))
            out.in_order = [m.log_time for _, _, m in reader.iter_messages(log_time_order=True)]
            out.metadata = {m.name: m.metadata for m in reader.iter_metadata()}
        return out


def _record(played: Played, out: Path, *, full: bool, lose: set[tuple[str, int]] = frozenset()) -> Mcap:
    """The stream recorded as MCAP (``lose``: (role, decision) of step events the stream loses)."""
    bus = MemoryBus()
    recorder = Recorder(bus, RUN, out, full=full, fmt="mcap")
    for sample in played.samples:
        message = decode(sample.payload)
        if isinstance(message, StepEvent) and (message.role, message.decision_index) in lose:
            continue
        bus.publish_viz(sample.key, sample.payload)  # the recorder hears what it subscribed to (frame/ or full/)
    while (sample := recorder.inbox.get(timeout_s=0)) is not None:
        recorder.handle(sample)
    recorder.finish()
    assert not recorder.rejections.total and recorder.finished[played.record.episode_id]["record"]
    return Mcap.read(out / f"{played.record.episode_id}.mcap")


def _views(observations: list[Observation]) -> dict[str, list[tuple[float, Any]]]:
    """Image topic -> (sim time, the observation's RGB image) of every view shown, in order."""
    out: dict[str, list[tuple[float, Any]]] = defaultdict(list)
    for obs in observations:
        for image in obs.images:
            if image.kind == "rgb":
                out[f"/{obs.role}/camera/{image.name}/image/compressed"].append((obs.sim_time_s, image))
    return out


def _rotation(q: Any) -> np.ndarray:
    x, y, z, w = q.x, q.y, q.z, q.w
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                     [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                     [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


def test_every_channel_reads_back_with_the_counts_and_times_of_the_record(played: Played, tmp_path: Path) -> None:
    record, steps = played.record, played.record.step_log
    assert record.status == "finished" and record.termination == "confirmed"
    views = _views(played.observations)
    assert any("/front_left/" in t for t in views) and any(e.kind == "message" and e.delivered for e in record.ledger)
    mcap = _record(played, tmp_path, full=True)
    cameras = {t.rsplit("/image/", 1)[0] for t in views}
    assert set(mcap.by_topic) == ({"/uav/pose", "/ugv/pose", "/tf"} | JSON_TOPICS | set(views)
                                  | {f"{c}/camera_info" for c in cameras})
    for topic, (schema, schema_encoding, encoding) in mcap.encodings.items():
        if topic in JSON_TOPICS:
            assert (schema_encoding, encoding) == ("jsonschema", "json") and schema.startswith("agos."), topic
        else:
            assert (schema_encoding, encoding) == ("ros2msg", "cdr") and schema in mcap_episode.MSGDEFS, topic
            assert b"MSG: std_msgs/Header" in mcap.schemas[topic] and b"MSG: builtin_interfaces/Time" in mcap.schemas[topic]
    # Time: the episode's simulated time in ns, from the spec at 0 to the record at its end.
    end_ns = round(record.sim_time_s * 1e9)
    assert mcap.in_order[0] == 0 and mcap.in_order[-1] == end_ns and mcap.in_order == sorted(mcap.in_order)
    assert [m.log_time for m in mcap.by_topic["/agos/episode"]] == [0]
    assert [m.log_time for m in mcap.by_topic["/agos/record"]] == [end_ns]
    for topic, messages in mcap.by_topic.items():
        times = [m.log_time for m in messages]
        assert times == sorted(times) and all(m.publish_time == m.log_time for m in messages), topic
        assert max(times) <= end_ns, topic
    # One step and one pose per applied decision, at its time; both in the map frame, stamped as logged.
    assert [m.value["episode_step"] for m in mcap.by_topic["/agos/steps"]] == list(range(1, len(steps) + 1))
    assert [m.log_time for m in mcap.by_topic["/agos/steps"]] == pytest.approx([s.sim_time_s * 1e9 for s in steps],
                                                                              abs=1e6)  # the log rounds to 1 ms
    assert not any("from_record" in m.value for m in mcap.by_topic["/agos/steps"])
    for role in ("uav", "ugv"):
        mine = [s for s in steps if s.role == role]
        poses = mcap.by_topic[f"/{role}/pose"]
        assert len(poses) == len(mine) == (record.decisions_uav if role == "uav" else record.decisions_ugv)
        for pose, step in zip(poses, mine, strict=True):
            header = pose.value.header
            assert header.frame_id == "map" and header.stamp.sec * 10**9 + header.stamp.nanosec == pose.log_time
            assert pose.log_time == pytest.approx(step.sim_time_s * 1e9, abs=1e6)
            p = pose.value.pose.position
            assert (p.x, p.y) == pytest.approx(step.position_world_m, abs=1e-6)
    # Every view the observations held, at the time it was shown, with its camera's intrinsics.
    for topic, shown in views.items():
        images = mcap.by_topic[topic]
        infos = mcap.by_topic[topic.replace("/image/compressed", "/camera_info")]
        assert [m.log_time for m in images] == [m.log_time for m in infos] == [round(t * 1e9) for t, _ in shown]
        for image, info, (_, frame) in zip(images, infos, shown, strict=True):
            assert bytes(image.value.data) == frame.data and image.value.format == frame.encoding
            k = frame.intrinsics
            assert (info.value.width, info.value.height) == (k.width_px, k.height_px)
            assert list(info.value.k) == pytest.approx([k.fx_px, 0, k.cx_px, 0, k.fy_px, k.cy_px, 0, 0, 1])
            assert list(info.value.p) == pytest.approx([k.fx_px, 0, k.cx_px, 0, 0, k.fy_px, k.cy_px, 0, 0, 0, 1, 0])
            assert info.value.distortion_model == "plumb_bob" and list(info.value.d) == [0.0] * 5
            assert info.value.header.frame_id == image.value.header.frame_id == \
                mcap_episode.camera_frame(topic.split("/")[1], frame.name)
    assert sum(len(v) for v in views.values()) == sum(len(m) for t, m in mcap.by_topic.items() if t.endswith("compressed"))
    assert len(views["/uav/camera/nadir/image/compressed"]) == record.decisions_uav
    # /tf: map -> base_link at every pose, map -> the camera's optical frame (world_from_camera) at every view.
    transforms = [t for m in mcap.by_topic["/tf"] for t in m.value.transforms]
    by_child: dict[str, list[Any]] = defaultdict(list)
    for t in transforms:
        assert t.header.frame_id == "map"
        by_child[t.child_frame_id].append(t)
    assert len(by_child["uav/base_link"]) == record.decisions_uav and len(by_child["ugv/base_link"]) == record.decisions_ugv
    for topic, shown in views.items():
        role = topic.split("/")[1]
        cams = by_child[mcap_episode.camera_frame(role, shown[0][1].name)]
        assert len(cams) == len(shown)
        for t, (_, frame) in zip(cams, shown, strict=True):
            m = np.array(frame.world_from_camera).reshape(4, 4)
            tr = t.transform.translation
            assert (tr.x, tr.y, tr.z) == pytest.approx(tuple(m[:3, 3]), abs=1e-9)
            assert _rotation(t.transform.rotation) == pytest.approx(m[:3, :3], abs=1e-6)
    # agos's channels: valid against their own schemas; what the record holds, once each.
    for topic in JSON_TOPICS:
        schema = json.loads(mcap.schemas[topic])
        assert schema["type"] == "object"
        for m in mcap.by_topic[topic]:
            jsonschema.Draft202012Validator(schema).validate(m.value)
    assert mcap.by_topic["/agos/record"][0].value == json.loads(msgspec.json.encode(record))
    assert [m.value["seq"] for m in mcap.by_topic["/agos/link"]] == [e.seq for e in record.ledger]
    delivered = sorted((e.sender, e.arrive_s) for e in record.ledger if e.kind == "message" and e.delivered
                       and e.fault != "duplicate")
    messages = mcap.by_topic["/agos/messages"]
    got = sorted((m.value["sender"], m.value["delivered_sim_time_s"]) for m in messages)
    assert [g[0] for g in got] == [d[0] for d in delivered]
    assert [g[1] for g in got] == pytest.approx([d[1] for d in delivered], abs=1e-3)
    assert [m.log_time for m in messages] == [round(m.value["delivered_sim_time_s"] * 1e9) for m in messages]
    published = [s for s in played.samples if s.key == keys.viz_coord(RUN, WORKER)]
    assert len(mcap.by_topic["/agos/coordination"]) == len(published) > 0
    assert mcap.metadata["agos"]["episode_id"] == record.episode_id and mcap.metadata["outcome"]["success"] == "true"


def test_thumbnails_come_with_their_scaled_intrinsics(played: Played, tmp_path: Path) -> None:
    """Without --full the file holds the stream's thumbnails; their CameraInfo is the camera's, scaled to them."""
    mcap = _record(played, tmp_path, full=False)
    for topic, shown in _views(played.observations).items():
        images = mcap.by_topic[topic]
        infos = mcap.by_topic[topic.replace("/image/compressed", "/camera_info")]
        assert len(images) == len(infos) == len(shown)
        for image, info, (_, frame) in zip(images, infos, shown, strict=True):
            h, w = cv2.imdecode(np.frombuffer(bytes(image.value.data), np.uint8), cv2.IMREAD_COLOR).shape[:2]
            k, scale = frame.intrinsics, w / frame.intrinsics.width_px
            assert (info.value.width, info.value.height) == (w, h) and image.value.format == "jpeg"
            assert list(info.value.k) == pytest.approx([k.fx_px * scale, 0, k.cx_px * scale, 0, k.fy_px * h / k.height_px,
                                                        k.cy_px * h / k.height_px, 0, 0, 1])


def test_a_step_event_lost_on_the_stream_comes_from_the_record(played: Played, tmp_path: Path) -> None:
    """The stream loses a UGV step event: its step and pose come from the record's step log, at its time."""
    steps = played.record.step_log
    k, lost = next((k, s) for k, s in enumerate(steps, start=1) if s.role == "ugv" and k > 2)
    mcap = _record(played, tmp_path, full=True, lose={(lost.role, lost.decision_index)})
    written = mcap.by_topic["/agos/steps"]
    assert sorted(m.value["episode_step"] for m in written) == list(range(1, len(steps) + 1))
    again = next(m for m in written if m.value["episode_step"] == k)
    assert again.value["from_record"] is True and again.log_time == round(lost.sim_time_s * 1e9)  # the log's time
    assert again.value["applied"] == lost.applied
    poses = mcap.by_topic["/ugv/pose"]
    assert len(poses) == len([s for s in steps if s.role == "ugv"])
    assert any(p.log_time == again.log_time and (p.value.pose.position.x, p.value.pose.position.y) ==
               pytest.approx(lost.position_world_m) for p in poses)


def test_without_the_mcap_libraries_the_command_says_what_to_install(agos, tmp_path: Path,
                                                                       monkeypatch: pytest.MonkeyPatch) -> None:
    import importlib.util

    real = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec", lambda name, *a: None if name == "mcap_ros2" else real(name, *a))
    result = agos("record", "--connect", "tcp/127.0.0.1:1", "--run", "r", "--out", str(tmp_path / "rec"),
                  "--format", "mcap")
    assert result.returncode == 2 and result.stderr.strip() == \
        "agos record: --format mcap needs mcap-ros2-support (the robotics extra): pip install 'agos[robotics]'"
    assert not (tmp_path / "rec").exists()
    evaluated = agos("eval", "--split", str(tmp_path / "none.jsonl"), "--record", str(tmp_path / "rec"),
                     "--record-format", "mcap")
    assert evaluated.returncode == 2 and "pip install 'agos[robotics]'" in evaluated.stderr


def test_agos_eval_record_format_mcap_starts_the_recorder_with_it(tmp_path: Path) -> None:
    """``agos eval/demo --record DIR --record-format mcap`` starts ``agos record ... --format mcap``."""
    from agos.deploy.cli import build_parser
    from agos.deploy.cli.recordings import recording_of
    from agos.deploy.run.local import Recording, start_recorder
    from agos.runtime.settings import AgosConfig

    args = build_parser().parse_args(["eval", "--split", "x.jsonl", "--record", str(tmp_path), "--record-format", "mcap",
                                      "--record-full"])
    recording = recording_of(args)
    assert recording == Recording(tmp_path, full=True, fmt="mcap")
    started: list[list[str]] = []

    class Launcher:
        def start(self, name: str, argv: list[str], settings: AgosConfig) -> None:
            started.append(argv)

    start_recorder(Launcher(), recording, AgosConfig())  # type: ignore[arg-type]  (a stand-in launcher)
    record = build_parser().parse_args(started[0])
    assert (record.fmt, record.full, record.out) == ("mcap", True, tmp_path)
    plain = recording_of(build_parser().parse_args(["eval", "--split", "x.jsonl", "--record", str(tmp_path)]))
    assert plain is not None and plain.fmt == "rrd"  # rerun stays the default


def test_agos_view_says_where_to_open_an_mcap_file(agos, played: Played, tmp_path: Path) -> None:
    mcap = _record(played, tmp_path, full=False)
    result = agos("view", str(mcap.path))
    assert result.returncode == 2 and "an MCAP recording: open it in Foxglove" in result.stderr
