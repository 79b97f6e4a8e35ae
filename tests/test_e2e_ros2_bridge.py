"""ROS 2 over rmw_zenoh, end to end, with an rmw_zenoh client that is not agos's (docs/DEPLOY.md,
"ROS 2 (rmw_zenoh)").

A router, an evaluator, a world worker, a heuristic UAV agent service and ``agos ros2 bridge --drive
ugv`` run as processes on loopback; ``agos eval --connect`` plays one short episode. The UGV is a
scripted ROS 2 node in this process made with ``zenoh-ros2-sdk`` (a pure-Python rmw_zenoh client
from PyPI, its own key expressions, type hashes computed from the ``.msg`` files in
tests/support/ros2_msgs and CDR read by its own typestore): it subscribes to the UGV's pose, forward
camera and camera info, the UAV's pose and the coordination state, and answers every decision on
``/ugv/decision`` on ``/ugv/action`` (the first road waypoint offered, else WAIT), after one
illegal answer the bridge must refuse. Checked: what it decoded, the graph as its discovery sees
it, the rmw_zenoh attachment on a sample, and the stored record: every UGV decision is the
script's, traced as ``ros2``. No ROS 2 installation is involved (there is none here).

Beside it, without processes: the bridge's type hashes (rosbags') against the SDK's, computed from the
published ``.msg`` files, and its keys, liveliness tokens and attachment against the SDK's builders
(marked e2e too: importing the SDK runs ``git version``, through GitPython).
"""

from __future__ import annotations

import json
import math
import os
import queue
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import pytest

from agos.deploy.ros2 import graph
from agos.deploy.run.launcher import free_port, wait_listening
from agos.evaluator.store import ResultStore

from support.processes import stop_all

pytestmark = pytest.mark.e2e
AGOS = [sys.executable, "-m", "agos.deploy.cli"]
MSGS = Path(__file__).resolve().parent / "support" / "ros2_msgs"
RUN = "ros2"
BUDGET = 10
SHORT_AND_FLAT = {"AGOS_WORLD__LOOK": "flat", "AGOS_WORLD__DECISION_BUDGET": str(BUDGET)}
TYPES = ["std_msgs/msg/String", "geometry_msgs/msg/PoseStamped", "sensor_msgs/msg/CompressedImage", "sensor_msgs/msg/CameraInfo"]


@pytest.mark.parametrize("typename", TYPES)
def test_type_hashes_equal_the_sdks_from_the_msg_files(typename: str) -> None:
    """rosbags' RIHS01 (the bridge's) and zenoh-ros2-sdk's own, computed from the published .msg files."""
    from zenoh_ros2_sdk.message_registry import MessageRegistry
    from zenoh_ros2_sdk.utils import get_type_hash, load_dependencies_recursive

    registry = MessageRegistry(str(MSGS))
    definition = registry.get_msg_file_path(typename).read_text()
    theirs = get_type_hash(typename, msg_definition=definition,
                           dependencies=load_dependencies_recursive(typename, definition, registry))
    assert graph.type_hash(typename) == theirs
    if typename == "std_msgs/msg/String":  # the hash rmw_zenoh's documentation shows for it
        assert theirs == "RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18"


def test_keys_and_tokens_are_the_sdks() -> None:
    from zenoh_ros2_sdk.entity import EndpointEntity, EntityKind, NodeEntity
    from zenoh_ros2_sdk.keyexpr import endpoint_liveliness_keyexpr, node_liveliness_keyexpr, topic_keyexpr
    from zenoh_ros2_sdk.qos import QosProfile
    from zenoh_ros2_sdk.utils import ros2_to_dds_type

    t = "geometry_msgs/msg/PoseStamped"
    assert graph.dds_type_name(t) == ros2_to_dds_type(t) == "geometry_msgs::msg::dds_::PoseStamped_"
    assert graph.topic_key(3, "/ugv/pose", t) == topic_keyexpr(3, "/ugv/pose", ros2_to_dds_type(t), graph.type_hash(t))
    assert QosProfile().encode() == graph.DEFAULT_QOS
    node = NodeEntity(domain_id=0, session_id="a1b2", node_id=0, node_name="agos_bridge", namespace="/")
    assert graph.node_token_key(0, "a1b2", 0, "/", "agos_bridge") == node_liveliness_keyexpr(node)
    for kind, sdk_kind in (("MP", EntityKind.PUBLISHER), ("MS", EntityKind.SUBSCRIPTION)):
        ep = EndpointEntity(node=node, entity_id=4, kind=sdk_kind, name="/ugv/pose", dds_type_name=ros2_to_dds_type(t),
                            type_hash=graph.type_hash(t), qos=graph.DEFAULT_QOS)
        assert graph.endpoint_token_key(0, "a1b2", 0, 4, kind, "/", "agos_bridge", "/ugv/pose", t) == \
            endpoint_liveliness_keyexpr(ep)


def test_the_attachment_is_the_sdks() -> None:
    from zenoh_ros2_sdk.attachment import Attachment

    gid = graph.gid_of("@ros2_lv/0/x")
    assert len(gid) == 16
    ours = graph.attachment(41, gid, 1_700_000_000_123_456_789)
    assert ours == Attachment(sequence_id=41, timestamp_ns=1_700_000_000_123_456_789, gid=gid).to_bytes()
    assert graph.read_attachment(ours) == (41, 1_700_000_000_123_456_789, gid)


class ScriptedUgv:
    """A ROS 2 node of zenoh-ros2-sdk's making: subscriptions that keep what they decode, and the UGV's
    answers, decided on the test's thread (never in a zenoh callback)."""

    def __init__(self, port: int) -> None:
        from zenoh_ros2_sdk import ROS2Publisher, ROS2Subscriber, ZenohSession
        from zenoh_ros2_sdk.message_registry import get_registry

        # The SDK's registry reads the .msg files here instead of cloning ROS's repositories from GitHub.
        assert get_registry(str(MSGS)).messages_dir == MSGS, "the SDK's message registry was made elsewhere first"
        self.got: dict[str, list[Any]] = {}
        self.decisions: queue.Queue[dict[str, Any]] = queue.Queue()
        self.subs = []
        wanted = {"/ugv/pose": "geometry_msgs/msg/PoseStamped", "/uav/pose": "geometry_msgs/msg/PoseStamped",
                  "/ugv/forward/image_raw/compressed": "sensor_msgs/msg/CompressedImage",
                  "/ugv/forward/camera_info": "sensor_msgs/msg/CameraInfo",
                  "/agos/coordination": "std_msgs/msg/String", "/ugv/decision": "std_msgs/msg/String"}
        for topic, kind in wanted.items():
            self.got[topic] = []
            self.subs.append(ROS2Subscriber(topic, kind, self._keeper(topic), node_name="scripted_ugv", router_port=port))
        self.action = ROS2Publisher("/ugv/action", "std_msgs/msg/String", node_name="scripted_ugv", router_port=port)
        # The raw samples on the pose's key, for their attachment (the SDK's subscriber passes only the message on).
        self.attachments: list[bytes] = []
        self.raw = ZenohSession.get_instance().session.declare_subscriber(
            self.subs[0].keyexpr, lambda s: self.attachments.append(bytes(s.attachment.to_bytes()) if s.attachment else b""))
        self.answered: dict[tuple[str, int, int], str] = {}
        self.answers: list[tuple[int, str]] = []

    def _keeper(self, topic: str):
        def keep(message: Any) -> None:
            self.got[topic].append(message)
            if topic == "/ugv/decision":
                self.decisions.put(json.loads(message.data))
        return keep

    def answer_pending(self) -> None:
        """Answer each decision asked of the UGV once (the bridge publishes an open one again every 2 s)."""
        while True:
            try:
                d = self.decisions.get_nowait()
            except queue.Empty:
                return
            key = (d["episode_id"], d["attempt"], d["decision_index"])
            if d["answer_on"] != "/ugv/action" or key in self.answered:
                continue
            if not self.answered:  # the very first answer is illegal for a UGV: refused, the decision stays open
                self.action.publish(data=json.dumps({"action": "ANNOTATE_CANDIDATE", "cell": "A1"}))
            options = d["waypoint_options"]
            if "MOVE_TO_ROAD_WAYPOINT" in d["legal_actions"] and options:
                answer = {"action": "MOVE_TO_ROAD_WAYPOINT", "waypoint_id": options[0]["waypoint_id"]}
            else:
                answer = {"action": "WAIT"}
            answer |= {"episode_id": d["episode_id"], "decision_index": d["decision_index"], "rationale": "scripted ROS 2 UGV"}
            self.answered[key] = answer["action"]
            self.answers.append((d["decision_index"], answer["action"]))
            self.action.publish(data=json.dumps(answer))

    def close(self) -> None:
        from zenoh_ros2_sdk import ZenohSession

        self.raw.undeclare()
        for sub in self.subs:
            sub.close()
        self.action.close()
        ZenohSession.get_instance().close()


@pytest.mark.timeout(180)
def test_a_ros2_node_drives_the_ugv_through_the_bridge(tmp_path: Path) -> None:
    from agos.deploy.cli import main

    started = time.monotonic()
    split = tmp_path / "eps.jsonl"
    assert main(["episodes", "sample", "--town", "grid-s7", "--difficulty", "mid", "-n", "1", "--seed", "5",
                 "--look", "flat", "--out", str(split)]) == 0
    port = free_port(24100 + os.getpid() % 400)
    endpoint = f"tcp/127.0.0.1:{port}"
    logs = tmp_path / "logs"
    logs.mkdir()

    def start(name: str, *argv: str) -> subprocess.Popen:
        log = (logs / f"{name}.log").open("wb")
        return subprocess.Popen([*AGOS, *argv], cwd=tmp_path, stdout=log, stderr=subprocess.STDOUT)

    procs = [start("router", "router", "--listen", endpoint)]
    client = None
    try:
        assert wait_listening("127.0.0.1", port, 15)
        procs.append(start("evaluator", "evaluator", "--connect", endpoint, "--runs-dir", "runs"))
        procs.append(start("world", "world", "--connect", endpoint, "--run", RUN, "--worker-id", "w1"))
        procs.append(start("agent-uav", "agent", "--role", "uav", "--policy", "heuristic", "--connect", endpoint, "--run", RUN))
        bridge = start("bridge", "ros2", "bridge", "--connect", endpoint, "--run", RUN, "--drive", "ugv", "--worker", "w1")
        procs.append(bridge)
        client = ScriptedUgv(port)
        ev = subprocess.Popen([*AGOS, "eval", "--connect", endpoint, "--run", RUN, "--split", str(split), "--runs-dir", "runs"],
                              cwd=tmp_path, env={**os.environ, **SHORT_AND_FLAT}, stdout=(logs / "eval.log").open("wb"),
                              stderr=subprocess.STDOUT)
        procs.append(ev)
        deadline = time.monotonic() + 120
        while ev.poll() is None and time.monotonic() < deadline:
            client.answer_pending()
            time.sleep(0.05)
        out = (logs / "eval.log").read_text()
        bridge_log = (logs / "bridge.log").read_text()
        assert ev.returncode == 0, out + "\n--- bridge:\n" + bridge_log

        # ----- the graph as the SDK's discovery sees it: the bridge's node, its publishers and subscription.
        from zenoh_ros2_sdk import get_topic_info, get_topic_names_and_types

        graph = dict(get_topic_names_and_types(router_port=port, timeout=2.0))
        assert graph["/ugv/pose"] == ["geometry_msgs/msg/PoseStamped"]
        assert graph["/ugv/forward/image_raw/compressed"] == ["sensor_msgs/msg/CompressedImage"]
        assert graph["/ugv/forward/camera_info"] == ["sensor_msgs/msg/CameraInfo"]
        assert graph["/ugv/action"] == ["std_msgs/msg/String"]
        action_info = get_topic_info("/ugv/action", router_port=port, timeout=2.0, verbose=True)
        assert "agos_bridge" in {s.node_name for s in action_info.subscribers}
        pose_info = get_topic_info("/ugv/pose", router_port=port, timeout=2.0, verbose=True)
        assert {(p.node_name, p.qos) for p in pose_info.publishers} == {("agos_bridge", "::,10:,:,:,,")}
    finally:
        stop_all(procs)
        if client is not None:
            client.close()
    print(f"\nROS 2 bridge e2e: {time.monotonic() - started:.1f} s, {len(client.answers)} UGV decisions from ROS 2")

    # ----- what the SDK decoded, by its own CDR path and its own type hashes.
    got = client.got
    poses = got["/ugv/pose"]
    assert poses and all(p.header.frame_id == "map" for p in poses)
    q = poses[0].pose.orientation
    assert math.isclose(q.x ** 2 + q.y ** 2 + q.z ** 2 + q.w ** 2, 1.0, rel_tol=1e-9)
    assert got["/uav/pose"] and got["/uav/pose"][0].pose.position.z > 10  # the UAV, republished from its observations
    import cv2
    import numpy as np

    images, infos = got["/ugv/forward/image_raw/compressed"], got["/ugv/forward/camera_info"]
    assert images and infos and images[0].format == "jpeg" and images[0].header.frame_id == "ugv/forward"
    pixels = cv2.imdecode(np.asarray(images[0].data, dtype=np.uint8), cv2.IMREAD_COLOR)
    assert pixels is not None and pixels.shape[:2] == (infos[0].height, infos[0].width)
    assert infos[0].k[0] > 0 and infos[0].k[8] == 1.0 and infos[0].distortion_model == "plumb_bob"
    coordination = [json.loads(m.data) for m in got["/agos/coordination"]]
    assert coordination and coordination[-1]["worker_id"] == "w1" and coordination[-1]["run_id"] == RUN

    from zenoh_ros2_sdk.attachment import Attachment

    stamps = [Attachment.from_bytes(a) for a in client.attachments]
    assert stamps and all(len(a.gid) == 16 for a in stamps) and len({a.gid for a in stamps}) == 1
    assert [a.sequence_id for a in stamps] == sorted({a.sequence_id for a in stamps})  # one publisher, in order
    assert abs(stamps[-1].timestamp_ns / 1e9 - time.time()) < 600

    # ----- the stored record: every UGV decision is the script's, answered through ROS 2.
    with ResultStore(tmp_path / "runs" / RUN / "results.sqlite", create=False) as store:
        [record] = store.records()
    assert record.status == "finished" and record.fallbacks == 0
    ugv = [t for t in record.decision_traces if t.role == "ugv"]
    assert [(t.decision_index, t.parsed_action) for t in ugv] == client.answers
    assert record.decisions_ugv == len(client.answers) > 0
    assert {(t.policy, t.model) for t in ugv} == {("ros2", "ros2:/ugv/action")}
    assert (ugv[0].reasks, ugv[0].http_attempts) == (1, 2)  # the illegal first answer was refused, not applied
    assert "refused a message on /ugv/action: not a legal action now" in bridge_log
    applied = [(s.decision_index, s.applied) for s in record.step_log if s.role == "ugv"]
    assert applied == client.answers
