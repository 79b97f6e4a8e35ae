"""The ROS 2 bridge's parts without a bus (deploy/ros2/): topic names, the messages an observation
becomes (read back from CDR), and how the ROS side's answers are taken or refused. rmw_zenoh's keys,
hashes and attachments compared with zenoh-ros2-sdk's, and the whole bridge on a real router with
that client as the ROS 2 node: tests/test_e2e_ros2_bridge.py (the SDK runs ``git`` when imported)."""

from __future__ import annotations

import asyncio
import json
import math
from typing import Any

import msgspec
import numpy as np
import pytest

from agos.deploy.ros2 import graph, topics
from agos.deploy.ros2.bridge import Decisions


def test_topic_names() -> None:
    assert topics.namespace("") == "" and topics.namespace("/run a/b/") == "/run_a/b"
    assert topics.ros_name("front-left") == "front_left" and topics.ros_name("3d") == "_3d"
    for bad in ("ugv/pose", "/ugv//pose", "/ugv/pose/", "/1ugv", "/ugv/po-se"):
        with pytest.raises(ValueError):
            graph.check_topic(bad)


def test_rotations_become_unit_quaternions() -> None:
    rng = np.random.default_rng(7)
    for _ in range(200):
        m, _r = np.linalg.qr(rng.normal(size=(3, 3)))
        m *= np.sign(np.linalg.det(m))  # a proper rotation
        x, y, z, w = topics.matrix_quaternion(m)
        back = np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                         [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                         [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])
        assert np.abs(back - m).max() < 1e-9
    q = topics.yaw_quaternion(math.pi / 2)
    assert math.isclose(q.z, math.sqrt(0.5)) and math.isclose(q.w, math.sqrt(0.5))


def test_an_observation_becomes_topics_read_back_from_cdr(observations) -> None:
    store = graph.typestore()
    for obs in (next(o for o in observations if o.role == "uav"), next(o for o in observations if o.mode == "stop_6view")):
        published = topics.observation_topics(obs, worker="w1", answer_on=None, ns="/run1")
        by_topic = {topic: (kind, store.deserialize_cdr(bytes(store.serialize_cdr(m, kind)), kind)) for topic, kind, m in published}
        role = obs.role
        kind, pose = by_topic[f"/run1/{role}/pose"]
        assert kind == topics.POSE and pose.header.frame_id == "map"
        assert (pose.pose.position.x, pose.pose.position.y) == obs.pose.position_world_m[:2]
        assert pose.header.stamp.sec + pose.header.stamp.nanosec / 1e9 == pytest.approx(obs.sim_time_s)
        for frame in obs.images:
            _, image = by_topic[topics.image_topic("/run1", role, frame)]
            assert image.format == frame.encoding and bytes(image.data) == frame.data
        rgb = [f for f in obs.images if f.kind == "rgb"]
        assert rgb and all(f"/run1/{role}/{f.name}/camera_info" in by_topic for f in rgb)
        _, info = by_topic[f"/run1/{role}/{rgb[0].name}/camera_info"]
        assert (info.width, info.height, info.k[0]) == (rgb[0].intrinsics.width_px, rgb[0].intrinsics.height_px,
                                                        rgb[0].intrinsics.fx_px)
        _, tf = by_topic["/run1/tf"]
        assert {t.child_frame_id for t in tf.transforms} == {role} | {f"{role}/{f.name}" for f in rgb}
        assert published[-1][0] == f"/run1/{role}/decision"  # the decision last, after what it refers to
        decision = json.loads(by_topic[f"/run1/{role}/decision"][1].data)
        assert decision["decision_index"] == obs.decision_index and decision["legal_actions"] == obs.legal_actions
        assert decision["answer_on"] is None and decision["worker_id"] == "w1"
        assert "oracle" not in decision and "expert" not in decision and len(decision["images"]) == len(obs.images)
        assert decision["references"][0]["topic"].startswith("/run1/agos/reference/")


class _Node:
    def __init__(self) -> None:
        self.sent: list[tuple[str, Any]] = []

    def publish(self, topic: str, typename: str, message: Any) -> None:
        self.sent.append((topic, message))


def test_the_ros_side_answers_only_the_open_decision_with_a_legal_action(observations) -> None:
    ugv = [o for o in observations if o.role == "ugv"]
    first, other = ugv[0], msgspec.structs.replace(ugv[1], episode_id="another-episode")

    async def play() -> None:
        node = _Node()
        decisions = Decisions(node, "", asyncio.get_running_loop())  # type: ignore[arg-type]
        asked = asyncio.create_task(decisions.ask(first))
        await asyncio.sleep(0)
        assert node.sent[-1][0] == "/ugv/decision" and json.loads(node.sent[-1][1].data)["answer_on"] == "/ugv/action"
        decisions.answer("ugv", "WAIT", None)  # not JSON
        decisions.answer("ugv", json.dumps({"action": "ANNOTATE_CANDIDATE", "cell": "A1"}), None)  # not a UGV action
        decisions.answer("ugv", json.dumps({"action": "WAIT", "decision_index": first.decision_index + 1}), None)  # stale
        decisions.answer("ugv", json.dumps({"action": "WAIT", "episode_id": "nowhere"}), None)
        decisions.answer("ugv", json.dumps({"action": "WAIT", "message": 7}), None)
        assert not asked.done()
        decisions.answer("ugv", json.dumps({"action": "WAIT", "message": "hold", "episode_id": first.episode_id}), None)
        action = await asked
        assert (action.action, action.message, action.decision_index, action.episode_id) == (
            "WAIT", "hold", first.decision_index, first.episode_id)
        assert action.trace is not None and (action.trace.policy, action.trace.model) == ("ros2", "ros2:/ugv/action")
        assert (action.trace.reasks, action.trace.http_attempts) == (3, 4)
        assert sum(decisions.rejections.counts.values()) == 5 and not decisions.pending

        # Two episodes open at once: an answer must name its episode; the world moving on closes one.
        a, b = asyncio.create_task(decisions.ask(first)), asyncio.create_task(decisions.ask(other))
        await asyncio.sleep(0)
        decisions.answer("ugv", json.dumps({"action": "WAIT"}), None)
        assert ("action", "several decisions are open: name episode_id") in decisions.rejections.counts
        decisions.answer("ugv", json.dumps({"action": "WAIT", "episode_id": "another-episode"}), None)
        assert (await b).episode_id == "another-episode"
        decisions.forget("ugv", first.episode_id)
        with pytest.raises(asyncio.CancelledError):
            await a
        assert not decisions.pending

    asyncio.run(play())


def test_the_cli_refuses_bad_names(agos) -> None:
    out = agos("ros2", "bridge", "--run", "r", "--node-name", "no-dashes")
    assert out.returncode == 2 and "not a ROS node name" in out.stderr
    out = agos("ros2", "bridge", "--run", "r", "--domain-id", "300")
    assert out.returncode == 2 and "not in 0..232" in out.stderr
