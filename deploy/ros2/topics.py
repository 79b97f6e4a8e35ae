"""What the bridge publishes: agos messages as ROS 2 messages, and the topic each goes on.

Topics (``NS`` is ``--namespace``, empty by default; ``ROLE`` is ``uav`` or ``ugv``; ``CAM`` a view's
name: ``nadir``, ``forward``, ``front_left`` ... at a STOP_OBSERVE):

========================================  ===============================  ============================================
topic                                     type                             from
========================================  ===============================  ============================================
``NS/ROLE/pose``                          geometry_msgs/msg/PoseStamped    each observation's pose, frame ``map``
``NS/ROLE/CAM/image_raw/compressed``      sensor_msgs/msg/CompressedImage  each observation's RGB view (``jpeg``)
``NS/ROLE/CAM/image_grid/compressed``     sensor_msgs/msg/CompressedImage  the UAV's view with the grid drawn on it
``NS/ROLE/CAM/depth/compressed``          sensor_msgs/msg/CompressedImage  16-bit PNG depth (scale in the decision)
``NS/ROLE/CAM/semantic/compressed``       sensor_msgs/msg/CompressedImage  8-bit PNG class map
``NS/ROLE/map/image/compressed``          sensor_msgs/msg/CompressedImage  the top-down map the role is shown
``NS/ROLE/CAM/camera_info``               sensor_msgs/msg/CameraInfo       the view's pinhole intrinsics
``NS/ROLE/decision``                      std_msgs/msg/String (JSON)       the decision asked: legal actions, waypoint
                                                                           options, the role's coordination view ...
``NS/ROLE/action`` (subscribed)           std_msgs/msg/String (JSON)       the ROS side's answer (a driven role only)
``NS/agos/coordination``                  std_msgs/msg/String (JSON)       the coordination truth after each tick
``NS/agos/reference/NAME/compressed``     sensor_msgs/msg/CompressedImage  the target's reference views
``NS/tf``                                 tf2_msgs/msg/TFMessage           map -> ROLE (the pose), map -> ROLE/CAM
========================================  ===============================  ============================================

Stamps are simulated time (the episode's clock, from 0 at its start; there is no ``/clock``).
Positions are agos's world frame, x east, y north, z up (REP 103's ENU), so ``map`` is that frame;
the camera frames ``ROLE/CAM`` are optical frames (x right, y down, z forward), as agos's
``world_from_camera`` and ROS's ``*_optical_frame`` convention both are.
"""

from __future__ import annotations

import math
import re
from typing import Any

import msgspec
import numpy as np

from agos.deploy.ros2.graph import msg
from agos.runtime.schemas import CameraIntrinsics, CoordinationState, ImageFrame, Observation, Pose

POSE = "geometry_msgs/msg/PoseStamped"
IMAGE = "sensor_msgs/msg/CompressedImage"
CAMERA_INFO = "sensor_msgs/msg/CameraInfo"
STRING = "std_msgs/msg/String"
TF = "tf2_msgs/msg/TFMessage"
MAP_FRAME = "map"

_IMAGE_TOPIC = {"rgb": "image_raw", "rgb_grid": "image_grid", "depth": "depth", "semantic": "semantic", "map": "image"}
_NOT_A_NAME = re.compile(r"[^A-Za-z0-9_]")

Published = list[tuple[str, str, Any]]
"""(topic, type, rosbags message) to publish."""


def ros_name(name: str) -> str:
    """``name`` as one ROS name token: letters, digits and ``_``, not starting with a digit."""
    token = _NOT_A_NAME.sub("_", name) or "_"
    return f"_{token}" if token[0].isdigit() else token


def namespace(ns: str | None) -> str:
    """``--namespace`` as a topic prefix: '' or ``/a/b``."""
    parts = [ros_name(p) for p in (ns or "").split("/") if p]
    return "".join(f"/{p}" for p in parts)


def action_topic(ns: str, role: str) -> str:
    return f"{ns}/{role}/action"


def decision_topic(ns: str, role: str) -> str:
    return f"{ns}/{role}/decision"


def pose_topic(ns: str, role: str) -> str:
    return f"{ns}/{role}/pose"


def image_topic(ns: str, role: str, frame: ImageFrame) -> str:
    return f"{ns}/{role}/{ros_name(frame.name)}/{_IMAGE_TOPIC.get(frame.kind, ros_name(frame.kind))}/compressed"


def camera_info_topic(ns: str, role: str, name: str) -> str:
    return f"{ns}/{role}/{ros_name(name)}/camera_info"


def coordination_topic(ns: str) -> str:
    return f"{ns}/agos/coordination"


def reference_topic(ns: str, name: str) -> str:
    """A reference view of the target (``ref_top`` ... in observations) on ``NS/agos/reference/top/compressed`` ...."""
    return f"{ns}/agos/reference/{ros_name(name.removeprefix('ref_'))}/compressed"


def tf_topic(ns: str) -> str:
    return f"{ns}/tf"


def stamp(sim_time_s: float) -> Any:
    """builtin_interfaces/msg/Time of a simulated time (seconds)."""
    sec = math.floor(sim_time_s)
    return msg("builtin_interfaces/msg/Time", sec=int(sec), nanosec=min(round((sim_time_s - sec) * 1e9), 999_999_999))


def header(sim_time_s: float, frame_id: str) -> Any:
    return msg("std_msgs/msg/Header", stamp=stamp(sim_time_s), frame_id=frame_id)


def yaw_quaternion(yaw_rad: float) -> Any:
    return msg("geometry_msgs/msg/Quaternion", x=0.0, y=0.0, z=math.sin(yaw_rad / 2), w=math.cos(yaw_rad / 2))


def matrix_quaternion(m: np.ndarray) -> tuple[float, float, float, float]:
    """(x, y, z, w) of a 3x3 rotation matrix (Shepperd's method: the largest of the four first)."""
    t = float(np.trace(m))
    if t > 0:
        s = math.sqrt(t + 1.0) * 2
        return ((m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s, 0.25 * s)
    i = int(np.argmax(np.diag(m)))
    j, k = (i + 1) % 3, (i + 2) % 3
    s = math.sqrt(1.0 + m[i, i] - m[j, j] - m[k, k]) * 2
    q = [0.0, 0.0, 0.0, 0.0]
    q[i] = 0.25 * s
    q[j] = (m[j, i] + m[i, j]) / s
    q[k] = (m[k, i] + m[i, k]) / s
    q[3] = (m[k, j] - m[j, k]) / s
    return q[0], q[1], q[2], q[3]


def pose_stamped(pose: Pose, sim_time_s: float) -> Any:
    x, y, z = pose.position_world_m
    return msg(POSE, header=header(sim_time_s, MAP_FRAME),
               pose=msg("geometry_msgs/msg/Pose", position=msg("geometry_msgs/msg/Point", x=float(x), y=float(y), z=float(z)),
                        orientation=yaw_quaternion(pose.yaw_rad)))


def compressed_image(frame: ImageFrame, sim_time_s: float, frame_id: str) -> Any:
    return msg(IMAGE, header=header(sim_time_s, frame_id), format=frame.encoding,
               data=np.frombuffer(frame.data, dtype=np.uint8))


def camera_info(k: CameraIntrinsics, sim_time_s: float, frame_id: str) -> Any:
    """A pinhole camera without distortion (agos renders ideal pinhole views)."""
    fx, fy, cx, cy = k.fx_px, k.fy_px, k.cx_px, k.cy_px
    return msg(CAMERA_INFO, header=header(sim_time_s, frame_id), height=k.height_px, width=k.width_px,
               distortion_model="plumb_bob", d=np.zeros(5, dtype=np.float64),
               k=np.array([fx, 0, cx, 0, fy, cy, 0, 0, 1], dtype=np.float64),
               r=np.eye(3, dtype=np.float64).reshape(9),
               p=np.array([fx, 0, cx, 0, 0, fy, cy, 0, 0, 0, 1, 0], dtype=np.float64),
               binning_x=0, binning_y=0,
               roi=msg("sensor_msgs/msg/RegionOfInterest", x_offset=0, y_offset=0, height=0, width=0, do_rectify=False))


def transform(sim_time_s: float, child: str, xyz: tuple[float, float, float], q: tuple[float, float, float, float]) -> Any:
    return msg("geometry_msgs/msg/TransformStamped", header=header(sim_time_s, MAP_FRAME), child_frame_id=child,
               transform=msg("geometry_msgs/msg/Transform",
                             translation=msg("geometry_msgs/msg/Vector3", x=float(xyz[0]), y=float(xyz[1]), z=float(xyz[2])),
                             rotation=msg("geometry_msgs/msg/Quaternion", x=float(q[0]), y=float(q[1]), z=float(q[2]),
                                          w=float(q[3]))))


def json_string(data: str) -> Any:
    return msg(STRING, data=data)


def decision_json(obs: Observation, *, worker: str | None, answer_on: str | None, ns: str) -> str:
    """The decision asked, as JSON: the observation without its image bytes (those go on the image
    topics, named here), and whether and where the ROS side answers it. Oracle and expert hints are
    never published."""
    plain = msgspec.structs.replace(obs, images=[], references=[], teammate_reference=None, oracle=None, expert=None)
    d: dict[str, Any] = msgspec.to_builtins(plain)
    for field in ("type", "v", "images", "references", "teammate_reference", "oracle", "expert"):
        d.pop(field, None)
    d["worker_id"] = worker
    d["images"] = [{"name": f.name, "kind": f.kind, "encoding": f.encoding, "topic": image_topic(ns, obs.role, f),
                    "depth_scale_m": f.depth_scale_m, "metres_per_px": f.metres_per_px} for f in obs.images]
    d["references"] = [{"name": f.name, "topic": reference_topic(ns, f.name)} for f in obs.references]
    d["answer_on"] = answer_on
    return msgspec.json.encode(d).decode()


def coordination_json(state: CoordinationState, worker: str | None) -> str:
    d: dict[str, Any] = msgspec.to_builtins(state)
    d.pop("v", None)
    d["worker_id"] = worker
    return msgspec.json.encode(d).decode()


def observation_topics(obs: Observation, *, worker: str | None, answer_on: str | None, ns: str = "") -> Published:
    """Everything one observation becomes: pose, every view and its camera info, the reference views,
    the transforms, and last the decision (so a node that acts on the decision has the rest already)."""
    role, t = obs.role, obs.sim_time_s
    out: Published = [(pose_topic(ns, role), POSE, pose_stamped(obs.pose, t))]
    x, y, z = obs.pose.position_world_m
    transforms = [transform(t, role, (x, y, z), (0.0, 0.0, math.sin(obs.pose.yaw_rad / 2), math.cos(obs.pose.yaw_rad / 2)))]
    infos: set[str] = set()
    for frame in obs.images:
        camera = f"{role}/{ros_name(frame.name)}"
        frame_id = MAP_FRAME if frame.kind == "map" else camera
        out.append((image_topic(ns, role, frame), IMAGE, compressed_image(frame, t, frame_id)))
        if frame.intrinsics is not None and frame.name not in infos:
            infos.add(frame.name)
            out.append((camera_info_topic(ns, role, frame.name), CAMERA_INFO, camera_info(frame.intrinsics, t, camera)))
            if frame.world_from_camera is not None and len(frame.world_from_camera) == 16:
                m = np.asarray(frame.world_from_camera, dtype=np.float64).reshape(4, 4)
                transforms.append(transform(t, camera, (m[0, 3], m[1, 3], m[2, 3]), matrix_quaternion(m[:3, :3])))
    for ref in obs.references:
        out.append((reference_topic(ns, ref.name), IMAGE, compressed_image(ref, t, "")))
    out.append((tf_topic(ns), TF, msg(TF, transforms=transforms)))
    out.append((decision_topic(ns, role), STRING, json_string(decision_json(obs, worker=worker, answer_on=answer_on, ns=ns))))
    return out
