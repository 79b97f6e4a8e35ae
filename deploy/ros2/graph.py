"""One ROS 2 node on zenoh, as rmw_zenoh lays it out: topics in its key layout, messages in CDR.

No ROS installation: the messages are the ROS 2 Jazzy types ``rosbags`` ships (its typestore
serialises and reads CDR, and computes each type's RIHS01 hash from its type description, as
``rosidl`` does), and the graph is the zenoh keys rmw_zenoh_cpp (Jazzy, Rolling) declares, as its
design document (ros2/rmw_zenoh, docs/design.md) describes them:

* data: ``<domain>/<topic without its leading slash>/<DDS type name>/<type hash>``, for example
  ``0/ugv/pose/geometry_msgs::msg::dds_::PoseStamped_/RIHS01_10f3786d...``; the payload is the CDR
  message (little-endian, with its 4-byte encapsulation header), encoding ``application/cdr``;
* every sample's attachment: the publisher's sequence number (int64), the source timestamp
  (int64, ns since the epoch) and its 16-byte GID, serialised with zenoh-ext's serializer
  (``zenoh.ext.z_serialize``), which is what rmw_zenoh_cpp and ros-z write and read;
* liveliness tokens that put the node and each of its endpoints on the ROS graph (``ros2 topic
  list``): ``@ros2_lv/<domain>/<zid>/<nid>/<nid>/NN/<enclave>/<namespace>/<node>`` for the node,
  ``@ros2_lv/<domain>/<zid>/<nid>/<eid>/MP|MS/<enclave>/<namespace>/<node>/<topic>/<DDS type
  name>/<type hash>/<qos>`` for a publisher or subscription, names with ``/`` written as ``%``
  (an empty namespace or enclave is ``%``) and the QoS in rmw_zenoh's compact form (the fields equal
  to ROS's default profile left empty: ``::,10:,:,:,,`` is reliable, volatile, keep last 10).

rmw_zenoh_cpp takes an entity's GID from an XXH3 hash of its token key; here it is the first 16 bytes
of the key's SHA-256 (any 16 bytes unique to the endpoint do: subscribers only compare them).
Checked against ``zenoh-ros2-sdk``'s subscriber, publisher and discovery (tests/test_e2e_ros2_bridge.py),
not against a ROS 2 installation (docs/DEPLOY.md, "ROS 2 (rmw_zenoh)").

These keys are ROS 2's key space, not agos's, so they are built here and not in runtime/keys.py.
"""

from __future__ import annotations

import functools
import hashlib
import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import zenoh
import zenoh.ext

log = logging.getLogger("agos.ros2")

ADMIN_SPACE = "@ros2_lv"
DEFAULT_QOS = "::,10:,:,:,,"
"""ROS 2's default QoS profile (reliable, volatile, keep last 10) in rmw_zenoh's token form."""
CDR = zenoh.Encoding("application/cdr")


@functools.cache
def typestore() -> Any:
    """The ROS 2 Jazzy message types of ``rosbags`` (the ``robotics`` extra)."""
    try:
        from rosbags.typesys import Stores, get_typestore
    except ImportError as exc:  # the robotics extra is not installed
        raise RuntimeError("agos ros2 needs rosbags: pip install 'agos[robotics]'") from exc
    return get_typestore(Stores.ROS2_JAZZY)


def msg(typename: str, **fields: Any) -> Any:
    """A ROS 2 message of ``typename`` (``geometry_msgs/msg/PoseStamped``), as rosbags builds it."""
    return typestore().types[typename](**fields)


def dds_type_name(typename: str) -> str:
    """``geometry_msgs/msg/PoseStamped`` -> ``geometry_msgs::msg::dds_::PoseStamped_`` (the name rmw_zenoh keys by)."""
    package, kind, name = typename.split("/")
    return f"{package}::{kind}::dds_::{name}_"


@functools.cache
def type_hash(typename: str) -> str:
    """The type's RIHS01 hash (``RIHS01_<sha256 hex>``), from rosbags' type description of it."""
    return str(typestore().hash_rihs01(typename))


def mangle(name: str) -> str:
    """A ROS name as one key chunk: ``/`` -> ``%``; empty or ``/`` is ``%``."""
    return "%" if name in ("", "/") else name.replace("/", "%")


def topic_key(domain: int, topic: str, typename: str) -> str:
    """The data key of ``topic`` carrying ``typename`` in ROS domain ``domain``."""
    return f"{domain}/{topic.strip('/')}/{dds_type_name(typename)}/{type_hash(typename)}"


def node_token_key(domain: int, zid: str, node_id: int, namespace: str, node: str) -> str:
    """The liveliness key that puts a node on the graph."""
    return f"{ADMIN_SPACE}/{domain}/{zid}/{node_id}/{node_id}/NN/%/{mangle(namespace)}/{mangle(node)}"


def endpoint_token_key(domain: int, zid: str, node_id: int, entity_id: int, kind: str, namespace: str, node: str,
                       topic: str, typename: str, qos: str = DEFAULT_QOS) -> str:
    """The liveliness key of a node's publisher (``kind`` ``MP``) or subscription (``MS``) on ``topic``."""
    return (f"{ADMIN_SPACE}/{domain}/{zid}/{node_id}/{entity_id}/{kind}/%/{mangle(namespace)}/{mangle(node)}/"
            f"{mangle(topic)}/{dds_type_name(typename)}/{type_hash(typename)}/{qos}")


def check_topic(topic: str) -> str:
    """``topic`` if it is a fully qualified ROS topic name (``/a/b_c``), else ``ValueError``."""
    parts = topic.split("/")
    if (not topic.startswith("/") or topic.endswith("/") or
            not all(p and (p[0].isalpha() or p[0] == "_") and p.replace("_", "").isalnum() and p.isascii()
                    for p in parts[1:])):
        raise ValueError(f"{topic!r} is not a ROS topic name (/word/word..., letters, digits and '_')")
    return topic


def gid_of(token_key: str) -> bytes:
    return hashlib.sha256(token_key.encode()).digest()[:16]


def attachment(sequence: int, gid: bytes, timestamp_ns: int | None = None) -> bytes:
    """rmw_zenoh's per-sample attachment: sequence number, source timestamp (ns), GID."""
    stamp = time.time_ns() if timestamp_ns is None else timestamp_ns
    return bytes(zenoh.ext.z_serialize((zenoh.ext.Int64(sequence), zenoh.ext.Int64(stamp), bytes(gid))).to_bytes())


def read_attachment(data: bytes) -> tuple[int, int, bytes]:
    """(sequence number, source timestamp ns, GID) of an rmw_zenoh attachment."""
    seq, stamp, gid = zenoh.ext.z_deserialize(tuple[zenoh.ext.Int64, zenoh.ext.Int64, bytes], zenoh.ZBytes(data))
    return int(seq), int(stamp), bytes(gid)


@dataclass
class Publisher:
    """One ROS 2 publisher: its zenoh publisher on the topic's data key and its ``MP`` token."""

    topic: str
    typename: str
    key: str
    gid: bytes
    _publisher: Any
    _token: Any
    _lock: threading.Lock
    sequence: int = 0

    def publish(self, message: Any) -> None:
        """Serialise ``message`` (a rosbags message of this publisher's type) to CDR and put it."""
        payload = bytes(typestore().serialize_cdr(message, self.typename))
        with self._lock:  # one sequence number per sample, in order
            self.sequence += 1
            self._publisher.put(payload, encoding=CDR, attachment=attachment(self.sequence, self.gid))

    def close(self) -> None:
        self._token.undeclare()
        self._publisher.undeclare()


class Node:
    """A ROS 2 node on its own zenoh session: its ``NN`` token, publishers made on first use and
    subscriptions, each with its token. ``domain``: the ROS domain id (``ROS_DOMAIN_ID``)."""

    def __init__(self, session: zenoh.Session, name: str = "agos_bridge", *, namespace: str = "/", domain: int = 0,
                 qos: str = DEFAULT_QOS) -> None:
        self.session, self.name, self.namespace, self.domain, self.qos = session, name, namespace, domain, qos
        self.zid = str(session.zid())
        self._ids = 0
        self._lock = threading.Lock()
        self.node_id = self._next_id()
        self._node_token = session.liveliness().declare_token(node_token_key(domain, self.zid, self.node_id, namespace, name))
        self.publishers: dict[str, Publisher] = {}
        self._subscriptions: list[tuple[Any, Any]] = []

    def _next_id(self) -> int:
        with self._lock:
            ident = self._ids
            self._ids += 1
            return ident

    def endpoint_token(self, kind: str, entity_id: int, topic: str, typename: str) -> str:
        """The liveliness key of this node's publisher (``MP``) or subscription (``MS``) on ``topic``."""
        return endpoint_token_key(self.domain, self.zid, self.node_id, entity_id, kind, self.namespace, self.name, topic,
                                  typename, self.qos)

    def publisher(self, topic: str, typename: str) -> Publisher:
        """The node's publisher of ``typename`` on ``topic``, declared (with its token) on first use.
        Congestion control DROP, as rmw_zenoh's keep-last publishers: a slow ROS subscriber loses
        samples instead of slowing the bridge."""
        pub = self.publishers.get(topic)
        if pub is not None:
            return pub
        check_topic(topic)
        token_key = self.endpoint_token("MP", self._next_id(), topic, typename)
        key = topic_key(self.domain, topic, typename)
        zpub = self.session.declare_publisher(key, congestion_control=zenoh.CongestionControl.DROP,
                                              reliability=zenoh.Reliability.RELIABLE)
        pub = Publisher(topic, typename, key, gid_of(token_key), zpub, self.session.liveliness().declare_token(token_key),
                        threading.Lock())
        with self._lock:
            if topic in self.publishers:  # another thread declared it meanwhile
                pub.close()
                return self.publishers[topic]
            self.publishers[topic] = pub
        log.debug("publishing %s (%s) on %s", topic, typename, key)
        return pub

    def publish(self, topic: str, typename: str, message: Any) -> None:
        self.publisher(topic, typename).publish(message)

    def subscribe(self, topic: str, typename: str, callback: Callable[[Any, bytes | None], None]) -> None:
        """Subscribe to ``topic`` of ``typename`` (with an ``MS`` token); ``callback(message, attachment)``
        runs on zenoh's thread with the CDR payload read back as a rosbags message. A sample that is
        not CDR of that type is logged and dropped."""
        check_topic(topic)
        key = topic_key(self.domain, topic, typename)

        def on_sample(sample: zenoh.Sample) -> None:
            try:
                message = typestore().deserialize_cdr(bytes(sample.payload.to_bytes()), typename)
            except Exception as exc:  # another type's bytes, or a truncated sample
                log.warning("a sample on %s that is not CDR of %s: %s", topic, typename, exc)
                return
            extra = sample.attachment
            callback(message, None if extra is None else bytes(extra.to_bytes()))

        subscriber = self.session.declare_subscriber(key, on_sample)
        token = self.session.liveliness().declare_token(self.endpoint_token("MS", self._next_id(), topic, typename))
        self._subscriptions.append((subscriber, token))
        log.info("subscribed to %s (%s) on %s", topic, typename, key)

    def close(self) -> None:
        for subscriber, token in self._subscriptions:
            token.undeclare()
            subscriber.undeclare()
        self._subscriptions.clear()
        for pub in self.publishers.values():
            pub.close()
        self.publishers.clear()
        self._node_token.undeclare()
