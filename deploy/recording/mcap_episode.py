"""One episode as an MCAP file (``agos record --format mcap``): what the visualisation stream said about it.

Contract: :class:`McapEpisodeRecording` takes the same calls as the rerun recording
(deploy/recording/episode.py: ``started``, ``episode_spec``, ``step``, ``coordination``, ``frame``,
``result``, ``close``) from the recorder's own thread, and writes ``<dir>/<episode>.mcap`` as they
come, with ROS 2 message schemas (CDR, written by ``mcap-ros2-support``) where ROS 2 has one and
JSON (``jsonschema`` schemas made from runtime/schemas.py's structs) for what is agos's own. It needs
the ``robotics`` extra (``mcap``, ``mcap-ros2-support``); :func:`missing_library` says when it is absent.

Time: every message's log and publish time, and every header stamp, is the episode's simulated time
(``sim_time_s``) in nanoseconds, so the file starts at 0 (a viewer shows 1970-01-01 plus the episode's
seconds). Frames: ``map`` is the world frame (x east, y north, z up, metres; REP-103's ENU),
``<role>/base_link`` the vehicle (x forward, yaw counter-clockwise from east), and each camera's frame
``<role>/camera/<view>_optical_frame`` is OpenCV's, which is ROS's optical frame convention (x right,
y down, z forward): ``world_from_camera`` is its transform from ``map`` as it is.

Channels (``<view>``: ``nadir`` for the UAV; ``forward`` and the six views ``front_left`` ... ``back_right``
for the UGV):

    /<role>/camera/<view>/image/compressed   sensor_msgs/msg/CompressedImage   every frame the stream carried
    /<role>/camera/<view>/camera_info        sensor_msgs/msg/CameraInfo        with each frame that has intrinsics
    /uav/pose, /ugv/pose                     geometry_msgs/msg/PoseStamped     one per applied decision (map frame)
    /tf                                      tf2_msgs/msg/TFMessage            map -> <role>/base_link at each pose,
                                                                               map -> camera frame at each frame
    /agos/episode                            json: EpisodeSpec                 the spec, at 0
    /agos/steps                              json: StepEvent                   one per applied decision
    /agos/coordination                       json: CoordinationState           every coordination truth received
    /agos/messages                           json: AgentMessage                each delivered message, once
                                                                               (at its delivery)
    /agos/link                               json: LedgerEntry                 every link transmission (the record's ledger)
    /agos/record                             json: EpisodeRecord               the record, at its end

The stream is lossy, as for the rerun file; a decision whose step event it lost is written at the close
from the record's step log (its ``/agos/steps`` entry says ``"from_record": true``; its pose has the
position the log holds and the height and heading of that role's last known pose), so the steps and
poses are complete whenever the record arrived. What is written at the close (those steps, a message
delivered as the episode ended, the link ledger) comes after later messages in the file, which MCAP
allows: readers order by log time (``make_reader(...).iter_messages(log_time_order=True)``, Foxglove).

Why from the stream and not an export afterwards: the stored records hold no images, and the rerun
files no intrinsics or camera poses; the stream has both, and the recorder around this class (its
queue, episodes, ``recorder.json``) serves both formats unchanged.
"""

from __future__ import annotations

import importlib.util
import json
import math
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import msgspec

from agos.deploy.recording.episode import Seen
from agos.runtime.schemas import (
    AgentMessage,
    CameraIntrinsics,
    CoordinationState,
    EpisodeRecord,
    EpisodeSpec,
    EpisodeStarted,
    LedgerEntry,
    Pose,
    Role,
    StepEvent,
    VizFrame,
)

if TYPE_CHECKING:
    from mcap.records import Schema
    from mcap_ros2.writer import Writer

    from agos.deploy.reports.episode_map import EpisodeMap

LIBRARIES = {"mcap": "mcap", "mcap_ros2": "mcap-ros2-support"}
"""Module -> the package that installs it (the ``robotics`` extra)."""
EXTRA_HINT = "pip install 'agos[robotics]'"
MAP_FRAME = "map"
STEP_FROM_RECORD = "from_record"
"""The property of an ``/agos/steps`` entry written from the record's step log (its event was lost)."""

_SEP = "=" * 80
_TIME = "int32 sec\nuint32 nanosec\n"
_HEADER = "builtin_interfaces/Time stamp\nstring frame_id\n"
_VECTOR = "float64 x\nfloat64 y\nfloat64 z\n"
_QUATERNION = "float64 x 0\nfloat64 y 0\nfloat64 z 0\nfloat64 w 1\n"
_ROI = "uint32 x_offset\nuint32 y_offset\nuint32 height\nuint32 width\nbool do_rectify\n"
_TRANSFORM_STAMPED = "std_msgs/Header header\nstring child_frame_id\ngeometry_msgs/Transform transform\n"


def _msgdef(main: str, *deps: tuple[str, str]) -> str:
    """A ROS 2 concatenated message definition: the message's own text, then each type it uses (all the
    way down) in an ``=====`` separated ``MSG: pkg/Name`` block, as rosbag2 writes them."""
    return main + "".join(f"{_SEP}\nMSG: {name}\n{text}" for name, text in deps)


MSGDEFS: dict[str, str] = {
    "sensor_msgs/msg/CompressedImage": _msgdef(
        "std_msgs/Header header\nstring format\nuint8[] data\n",
        ("std_msgs/Header", _HEADER), ("builtin_interfaces/Time", _TIME)),
    "sensor_msgs/msg/CameraInfo": _msgdef(
        "std_msgs/Header header\nuint32 height\nuint32 width\nstring distortion_model\nfloat64[] d\nfloat64[9] k\n"
        "float64[9] r\nfloat64[12] p\nuint32 binning_x\nuint32 binning_y\nsensor_msgs/RegionOfInterest roi\n",
        ("std_msgs/Header", _HEADER), ("builtin_interfaces/Time", _TIME), ("sensor_msgs/RegionOfInterest", _ROI)),
    "geometry_msgs/msg/PoseStamped": _msgdef(
        "std_msgs/Header header\ngeometry_msgs/Pose pose\n",
        ("std_msgs/Header", _HEADER), ("builtin_interfaces/Time", _TIME),
        ("geometry_msgs/Pose", "geometry_msgs/Point position\ngeometry_msgs/Quaternion orientation\n"),
        ("geometry_msgs/Point", _VECTOR), ("geometry_msgs/Quaternion", _QUATERNION)),
    "tf2_msgs/msg/TFMessage": _msgdef(
        "geometry_msgs/TransformStamped[] transforms\n",
        ("geometry_msgs/TransformStamped", _TRANSFORM_STAMPED), ("std_msgs/Header", _HEADER),
        ("builtin_interfaces/Time", _TIME),
        ("geometry_msgs/Transform", "geometry_msgs/Vector3 translation\ngeometry_msgs/Quaternion rotation\n"),
        ("geometry_msgs/Vector3", _VECTOR), ("geometry_msgs/Quaternion", _QUATERNION)),
}
"""The ROS 2 types the file uses, by name, as concatenated definitions (every dependency included)."""

JSON_CHANNELS: dict[str, type[msgspec.Struct]] = {
    "/agos/episode": EpisodeSpec, "/agos/steps": StepEvent, "/agos/coordination": CoordinationState,
    "/agos/messages": AgentMessage, "/agos/link": LedgerEntry, "/agos/record": EpisodeRecord}
"""agos's own channels: JSON messages, their JSON Schema made from the struct (runtime/schemas.py)."""


def missing_library() -> str | None:
    """One line saying what to install when the MCAP libraries are absent; None when they are here."""
    missing = [package for module, package in LIBRARIES.items() if importlib.util.find_spec(module) is None]
    if not missing:
        return None
    return f"--format mcap needs {' and '.join(missing)} (the robotics extra): {EXTRA_HINT}"


def json_schema(struct: type[msgspec.Struct]) -> dict[str, Any]:
    """``struct``'s JSON Schema with ``"type": "object"`` at its top (as Foxglove asks) and its parts
    under ``$defs`` (internal ``$ref``\\ s, which Foxglove resolves). The steps' schema also allows
    :data:`STEP_FROM_RECORD`."""
    made = msgspec.json.schema(struct)
    defs: dict[str, Any] = made["$defs"]
    top = dict(defs[struct.__name__])
    if struct is StepEvent:
        top["properties"] = {**top["properties"], STEP_FROM_RECORD: {
            "type": "boolean", "description": "written from the record's step log: the stream lost the step event"}}
    return {"$schema": "https://json-schema.org/draft/2020-12/schema", **top, "$defs": defs}


def ns(sim_time_s: float) -> int:
    """A simulated time as the file's nanoseconds (never below 0)."""
    return max(0, round(sim_time_s * 1e9))


def stamp(sim_time_s: float) -> dict[str, int]:
    """builtin_interfaces/Time of a simulated time."""
    sec, nanosec = divmod(ns(sim_time_s), 1_000_000_000)
    return {"sec": sec, "nanosec": nanosec}


def yaw_quaternion(yaw_rad: float) -> dict[str, float]:
    """The rotation by ``yaw_rad`` about +z."""
    return {"x": 0.0, "y": 0.0, "z": math.sin(yaw_rad / 2), "w": math.cos(yaw_rad / 2)}


def matrix_quaternion(m: Sequence[Sequence[float]]) -> dict[str, float]:
    """The unit quaternion of a 3x3 rotation matrix (rows), w >= 0."""
    trace = m[0][0] + m[1][1] + m[2][2]
    if trace > 0:
        s = 2.0 * math.sqrt(trace + 1.0)
        w, x, y, z = 0.25 * s, (m[2][1] - m[1][2]) / s, (m[0][2] - m[2][0]) / s, (m[1][0] - m[0][1]) / s
    elif m[0][0] > m[1][1] and m[0][0] > m[2][2]:
        s = 2.0 * math.sqrt(1.0 + m[0][0] - m[1][1] - m[2][2])
        w, x, y, z = (m[2][1] - m[1][2]) / s, 0.25 * s, (m[0][1] + m[1][0]) / s, (m[0][2] + m[2][0]) / s
    elif m[1][1] > m[2][2]:
        s = 2.0 * math.sqrt(1.0 + m[1][1] - m[0][0] - m[2][2])
        w, x, y, z = (m[0][2] - m[2][0]) / s, (m[0][1] + m[1][0]) / s, 0.25 * s, (m[1][2] + m[2][1]) / s
    else:
        s = 2.0 * math.sqrt(1.0 + m[2][2] - m[0][0] - m[1][1])
        w, x, y, z = (m[1][0] - m[0][1]) / s, (m[0][2] + m[2][0]) / s, (m[1][2] + m[2][1]) / s, 0.25 * s
    norm = math.sqrt(w * w + x * x + y * y + z * z) * (1.0 if w >= 0 else -1.0)
    return {"x": x / norm, "y": y / norm, "z": z / norm, "w": w / norm}


def camera_frame(role: str, view: str) -> str:
    """The optical frame of a role's camera (OpenCV axes: ROS's optical frame convention)."""
    return f"{role}/camera/{view}_optical_frame"


def camera_info(frame_id: str, sim_time_s: float, k: CameraIntrinsics) -> dict[str, Any]:
    """sensor_msgs/CameraInfo of a pinhole camera without distortion (plumb_bob, D all zero)."""
    return {"header": {"stamp": stamp(sim_time_s), "frame_id": frame_id}, "height": k.height_px, "width": k.width_px,
            "distortion_model": "plumb_bob", "d": [0.0] * 5,
            "k": [k.fx_px, 0.0, k.cx_px, 0.0, k.fy_px, k.cy_px, 0.0, 0.0, 1.0],
            "r": [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0],
            "p": [k.fx_px, 0.0, k.cx_px, 0.0, 0.0, k.fy_px, k.cy_px, 0.0, 0.0, 0.0, 1.0, 0.0],
            "binning_x": 0, "binning_y": 0,
            "roi": {"x_offset": 0, "y_offset": 0, "height": 0, "width": 0, "do_rectify": False}}


class McapEpisodeRecording:
    """One episode's ``.mcap``: call the methods as the stream's messages arrive, then :meth:`close`."""

    def __init__(self, out_dir: Path, run_id: str, episode_id: str, *, full: bool,
                 map_source: Callable[[EpisodeSpec], EpisodeMap] | None = None) -> None:
        """``map_source`` is taken for the rerun recording's signature and not used: the file has no town image."""
        from mcap_ros2.writer import Writer

        self.path = out_dir / f"{episode_id}.mcap"
        self.run_id, self.episode_id, self.full = run_id, episode_id, full
        self._file = self.path.open("wb")
        self.writer: Writer = Writer(self._file)
        self._mcap = self.writer._writer  # the plain MCAP writer under the ROS 2 one: the JSON channels
        self.schemas: dict[str, Schema] = {name: self.writer.register_msgdef(name, text) for name, text in MSGDEFS.items()}
        self._json_channels: dict[str, int] = {}
        self._sequence: dict[str, int] = {}
        self.seen = Seen()
        self.record: EpisodeRecord | None = None
        self.stepped: set[tuple[str, int]] = set()
        """(role, role's decision index) of the step events written."""
        self.last_pose: dict[str, Pose] = {}
        self.messages_seen: set[tuple[str, float, str]] = set()
        self.said: list[tuple[Role, float, str]] = []
        """(sender, sim time, text) of every message a step event says was sent."""
        self._mcap.add_metadata("agos", {"run_id": run_id, "episode_id": episode_id,
                                         "time": "log time = the episode's simulated time (sim_time_s) in ns",
                                         "images": "full resolution" if full else "thumbnails"})

    # ----- the stream's messages --------------------------------------------------------------
    def started(self, msg: EpisodeStarted) -> None:
        """The episode starts. Again, on a new attempt (the world of the last one died): what follows is
        written on the same time base, after the earlier attempt's messages; only its own steps count."""
        if self.stepped:
            self.stepped.clear()
            self.last_pose.clear()
            self.messages_seen.clear()
            self.said.clear()

    def episode_spec(self, spec: EpisodeSpec) -> None:
        self._json("/agos/episode", 0.0, spec)

    def step(self, ev: StepEvent) -> None:
        self.seen.steps += 1
        self.stepped.add((ev.role, ev.decision_index))
        self._json("/agos/steps", ev.sim_time_s, ev)
        self._pose(ev.role, ev.sim_time_s, ev.pose_after)
        if ev.requested is not None and ev.requested.message and not ev.fallback_reason:
            self.said.append((ev.role, ev.sim_time_s, ev.requested.message))

    def coordination(self, state: CoordinationState) -> None:
        self.seen.coords += 1
        self._json("/agos/coordination", state.sim_time_s, state)
        for msg in state.messages:
            self._message(msg.sender, msg.receiver, msg.text, msg.sent_sim_time_s, msg.delivered_sim_time_s)

    def frame(self, frame: VizFrame) -> None:
        """One view, at the time of the observation it was shown in."""
        image, t = frame.image, frame.sim_time_s
        frame_id = camera_frame(frame.role, image.name)
        base = f"/{frame.role}/camera/{image.name}"
        header = {"stamp": stamp(t), "frame_id": frame_id}
        self._ros(f"{base}/image/compressed", "sensor_msgs/msg/CompressedImage", t,
                  {"header": header, "format": image.encoding, "data": image.data})
        if image.intrinsics is not None:
            self._ros(f"{base}/camera_info", "sensor_msgs/msg/CameraInfo", t, camera_info(frame_id, t, image.intrinsics))
        m = image.world_from_camera
        if m is not None and len(m) == 16:
            rows = [m[0:3], m[4:7], m[8:11]]
            self._tf(t, frame_id, {"x": m[3], "y": m[7], "z": m[11]}, matrix_quaternion(rows))
        self.seen.frames[frame.role] += 1

    def result(self, record: EpisodeRecord) -> None:
        self.record = record

    def close(self) -> Seen:
        """Write what only the record holds (lost steps, the link ledger, the record) and finish the file."""
        record = self.record
        if record is not None:
            self._steps_lost_on_the_stream(record)
            self._messages_delivered_at_the_end(record)
            for entry in record.ledger:
                self._json("/agos/link", entry.sent_s, entry)
            self._json("/agos/record", record.sim_time_s, record)
            self._mcap.add_metadata("outcome", {
                "termination": record.termination, "success": str(record.success).lower(), "status": record.status,
                "sim_time_s": f"{record.sim_time_s:.3f}", "decisions": str(record.decisions_uav + record.decisions_ugv)})
        self.writer.finish()
        self._file.close()
        return self.seen

    # ----- helpers ----------------------------------------------------------------------------
    def _steps_lost_on_the_stream(self, record: EpisodeRecord) -> None:
        for k, s in enumerate(record.step_log, start=1):
            if (s.role, s.decision_index) in self.stepped:
                continue
            last = self.last_pose.get(s.role)
            pose = Pose(position_world_m=(s.position_world_m[0], s.position_world_m[1],
                                          last.position_world_m[2] if last else 0.0), yaw_rad=last.yaw_rad if last else 0.0)
            ev = StepEvent(run_id=record.run_id, episode_id=record.episode_id, role=s.role, decision_index=s.decision_index,
                           episode_step=k, sim_time_s=s.sim_time_s, requested=None, applied=s.applied, pose_after=pose,
                           candidate_id=s.candidate_id, pose_error_m=s.pose_error_m, model_link_s=s.model_link_s)
            self.stepped.add((s.role, s.decision_index))
            self._json("/agos/steps", s.sim_time_s, {**msgspec.to_builtins(ev), STEP_FROM_RECORD: True})
            self._pose(s.role, s.sim_time_s, pose)

    def _messages_delivered_at_the_end(self, record: EpisodeRecord) -> None:
        """Messages the ledger says were delivered that no coordination state showed (one that arrives as
        the episode ends, e.g. with its CONFIRM, is in no state): their text from the sender's step event."""
        shown = {(sender, sent) for sender, sent, _ in self.messages_seen}
        for e in record.ledger:
            if e.kind != "message" or not e.delivered or e.fault == "duplicate" or e.arrive_s is None:
                continue
            if any(sender == e.sender and abs(sent - e.sent_s) < 1e-3 for sender, sent in shown):
                continue
            text = next((text for role, t, text in self.said if role == e.sender and abs(t - e.sent_s) < 1e-3), None)
            if text is not None:  # else its step event was lost too: nothing says what it said
                self._message(e.sender, e.receiver, text[:500], e.sent_s, e.arrive_s)

    def _message(self, sender: Role, receiver: Role, text: str, sent_s: float, delivered_s: float) -> None:
        """A delivered message, once (the coordination states repeat the recent ones)."""
        ident = (sender, sent_s, text)
        if ident in self.messages_seen:
            return
        self.messages_seen.add(ident)
        self._json("/agos/messages", delivered_s, AgentMessage(
            run_id=self.run_id, episode_id=self.episode_id, sender=sender, receiver=receiver, text=text,
            sent_sim_time_s=sent_s, delivered_sim_time_s=delivered_s))

    def _pose(self, role: Role, t: float, pose: Pose) -> None:
        self.last_pose[role] = pose
        x, y, z = pose.position_world_m
        q = yaw_quaternion(pose.yaw_rad)
        self._ros(f"/{role}/pose", "geometry_msgs/msg/PoseStamped", t,
                  {"header": {"stamp": stamp(t), "frame_id": MAP_FRAME},
                   "pose": {"position": {"x": x, "y": y, "z": z}, "orientation": q}})
        self._tf(t, f"{role}/base_link", {"x": x, "y": y, "z": z}, q)

    def _tf(self, t: float, child: str, translation: dict[str, float], rotation: dict[str, float]) -> None:
        self._ros("/tf", "tf2_msgs/msg/TFMessage", t, {"transforms": [{
            "header": {"stamp": stamp(t), "frame_id": MAP_FRAME}, "child_frame_id": child,
            "transform": {"translation": translation, "rotation": rotation}}]})

    def _next(self, topic: str) -> int:
        self._sequence[topic] = self._sequence.get(topic, 0) + 1
        return self._sequence[topic]

    def _ros(self, topic: str, datatype: str, t: float, message: dict[str, Any]) -> None:
        self.writer.write_message(topic, self.schemas[datatype], message, log_time=ns(t), publish_time=ns(t),
                                  sequence=self._next(topic))

    def _json(self, topic: str, t: float, message: msgspec.Struct | dict[str, Any]) -> None:
        channel = self._json_channels.get(topic)
        if channel is None:
            struct = JSON_CHANNELS[topic]
            schema = self._mcap.register_schema(f"agos.{struct.__name__}", "jsonschema",
                                                json.dumps(json_schema(struct)).encode())
            channel = self._json_channels[topic] = self._mcap.register_channel(topic, "json", schema)
        self._mcap.add_message(channel, log_time=ns(t), data=msgspec.json.encode(message), publish_time=ns(t),
                               sequence=self._next(topic))
