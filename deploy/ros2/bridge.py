"""``agos ros2 bridge``: an agos run as ROS 2 topics over rmw_zenoh, and a role driven from ROS 2.

    agos ros2 bridge --connect tcp/HOST:7447 --run RUN [--worker W] [--drive ugv|uav|both]
                     [--namespace NS] [--domain-id N] [--ros-connect EP]

One process, two zenoh sessions: an agos client of the run's router (the bus, runtime/bus.py), and a
ROS 2 node (``agos_bridge``, deploy/ros2/graph.py) on the same router (or on ``--ros-connect``, a
ROS graph's own router). It republishes the run's observations (every role's, or with ``--worker``
one world worker's), each as a pose, its views and camera info, the reference views, the
transforms and the decision asked (deploy/ros2/topics.py), and the coordination truth after each
tick, all in rmw_zenoh's key layout and CDR.

With ``--drive ROLE`` it is that role's agent service (agents/agent_service.py: the same slot
subscriptions, ``ready`` tokens, attempt handling and answer checks, through
:func:`~agos.agents.agent_service.serve_async` with :class:`Ros2Policy`): each decision of the role is
published on ``ROLE/decision`` and answered by the first acceptable message on ``ROLE/action``
(std_msgs/msg/String holding JSON: ``{"action": "MOVE_TO_ROAD_WAYPOINT", "waypoint_id": "...",
"episode_id": "...", "decision_index": N}``, ``cell``, ``candidate_id``, ``message`` and
``rationale`` as the :class:`~agos.runtime.schemas.Action` has them; ``episode_id`` and
``decision_index`` are optional, and refuse a late answer when given). A message that is not JSON,
names no legal action, or answers a decision that is not pending is refused (logged, counted) and
the decision stays open; the world's decision timeout still applies. Each answer carries a
:class:`~agos.runtime.schemas.DecisionTrace` (``policy`` ``ros2``, ``model`` the action topic), so
the episode's record says which decisions came from ROS 2. The decision is published again every
:data:`REPEAT_S` while unanswered (the topics are volatile: a node that starts late still gets it).
"""

from __future__ import annotations

import asyncio
import contextlib
import functools
import hashlib
import json
import logging
import queue
import threading
import time
from dataclasses import dataclass, field
from typing import Any

from agos.agents.agent_service import serve_async
from agos.agents.contract import Policy, action_for
from agos.deploy.ros2 import topics
from agos.deploy.ros2.graph import Node, read_attachment, typestore
from agos.runtime import keys
from agos.runtime.bus import Bus, Sample, ZenohBus, open_session, session_config, zenoh_config
from agos.runtime.codec import DecodeError, decode
from agos.runtime.process import StopFlag, install_stop_handlers, setup_logging
from agos.runtime.rejections import Rejections, non_finite_field
from agos.runtime.schemas import Action, CoordinationState, DecisionTrace, Observation, Role
from agos.runtime.settings import AgosConfig

log = logging.getLogger("agos.ros2")

REPEAT_S = 2.0
"""Seconds between publications of a decision the ROS side has not answered."""
QUEUE_SAMPLES = 64
"""Observations and coordination states waiting to be republished; beyond it the oldest is dropped."""
CONCURRENCY = 64
"""Decisions of a driven role open at once (one per world worker's slot)."""
_ACTION_FIELDS = ("waypoint_id", "cell", "candidate_id", "message", "rationale")


@dataclass
class _Pending:
    obs: Observation
    future: asyncio.Future[Action]
    decision: str
    received_s: float = field(default_factory=time.monotonic)
    heard: int = 0
    refused: int = 0
    repeats: int = 0


class Decisions:
    """The driven roles' open decisions, one per (role, episode): asked on the service's loop
    (:meth:`ask`), answered from the ROS subscription's thread (:meth:`heard`, handed to the loop)."""

    def __init__(self, node: Node, ns: str, loop: asyncio.AbstractEventLoop) -> None:
        self.node, self.ns, self.loop = node, ns, loop
        self.pending: dict[tuple[str, str], _Pending] = {}
        self.rejections = Rejections(log)

    async def ask(self, obs: Observation) -> Action:
        """Publish ``obs`` as topics (its decision last) and wait for the ROS side's answer."""
        answer_on = topics.action_topic(self.ns, obs.role)
        published = topics.observation_topics(obs, worker=None, answer_on=answer_on, ns=self.ns)
        key = (obs.role, obs.episode_id)
        if (earlier := self.pending.pop(key, None)) is not None:  # the world moved on (its decision timeout)
            log.warning("%s %s #%d closed unanswered: the world asks #%d now", obs.episode_id, obs.role,
                        earlier.obs.decision_index, obs.decision_index)
            earlier.future.cancel()
        future: asyncio.Future[Action] = self.loop.create_future()
        self.pending[key] = _Pending(obs, future, published[-1][2].data)
        for topic, typename, message in published:
            self.node.publish(topic, typename, message)
        try:
            return await future
        finally:
            if self.pending.get(key) is not None and self.pending[key].future is future:
                del self.pending[key]

    def forget(self, role: str, episode_id: str) -> None:
        """The episode is over for ``role`` (or re-leased): its open decision closes."""
        if (p := self.pending.pop((role, episode_id), None)) is not None:
            p.future.cancel()

    def heard(self, role: str, message: Any, attachment: bytes | None) -> None:
        """A message on ``role``'s action topic (zenoh's thread): answered on the loop."""
        with contextlib.suppress(RuntimeError):  # the loop is closed: the bridge is stopping
            self.loop.call_soon_threadsafe(self.answer, role, str(message.data), attachment)

    def answer(self, role: str, text: str, attachment: bytes | None) -> None:
        topic = topics.action_topic(self.ns, role)
        try:
            fields = json.loads(text)
        except ValueError as exc:
            self.rejections.reject(topic, "not JSON", exc)
            return
        if not isinstance(fields, dict) or not isinstance(fields.get("action"), str):
            self.rejections.reject(topic, "not an object with an action", text[:200])
            return
        p = self._target(role, fields, topic)
        if p is None:
            return
        p.heard += 1
        obs = p.obs
        asked = (obs.decision_index, obs.attempt)
        if (fields.get("decision_index", asked[0]), fields.get("attempt", asked[1])) != asked:
            p.refused += 1
            self.rejections.reject(topic, "answers another decision than the one asked",
                                   f"{fields.get('decision_index')} (attempt {fields.get('attempt')}) for {obs.decision_index}")
            return
        if fields["action"] not in obs.legal_actions:
            p.refused += 1
            self.rejections.reject(topic, "not a legal action now", f"{fields['action']} (legal: {', '.join(obs.legal_actions)})")
            return
        extra = {name: fields.get(name) for name in _ACTION_FIELDS}
        if any(value is not None and not isinstance(value, str) for value in extra.values()):
            p.refused += 1
            self.rejections.reject(topic, "a field that is not a string", text[:200])
            return
        action = action_for(obs, fields["action"], **extra)
        action.trace = DecisionTrace(
            policy="ros2", model=f"ros2:{topic}", stage=obs.mode, prompt_sha256=hashlib.sha256(p.decision.encode()).hexdigest(),
            image_bytes={f"{f.name}/{f.kind}": len(f.data) for f in obs.images}, raw_reply=text[:2000],
            parsed_action=action.action, fallback=False, reasks=p.refused, http_attempts=p.heard,
            latency_s=round(time.monotonic() - p.received_s, 3))
        if not p.future.done():
            p.future.set_result(action)
        if attachment is not None:
            with contextlib.suppress(Exception):
                _seq, _stamp, gid = read_attachment(attachment)
                log.debug("%s %s #%d answered by the ROS publisher %s", obs.episode_id, role, obs.decision_index, gid.hex())

    def _target(self, role: str, fields: dict[str, Any], topic: str) -> _Pending | None:
        """The open decision a message answers: its ``episode_id``'s, else the role's only one."""
        episode = fields.get("episode_id")
        if episode is not None:
            p = self.pending.get((role, str(episode)))
            if p is None or p.future.done():
                self.rejections.reject(topic, "no decision of that episode is open", episode)
            return p if p is not None and not p.future.done() else None
        open_ = [p for (r, _), p in self.pending.items() if r == role and not p.future.done()]
        if len(open_) != 1:
            self.rejections.reject(topic, "no decision is open" if not open_ else "several decisions are open: name episode_id")
            return None
        return open_[0]

    async def repeat(self, stop: StopFlag) -> None:
        """Publish every unanswered decision again each :data:`REPEAT_S`, until ``stop``."""
        while not stop.is_set():
            await asyncio.sleep(0.25)
            now = time.monotonic()
            for p in list(self.pending.values()):
                if not p.future.done() and now >= p.received_s + REPEAT_S * (p.repeats + 1):
                    p.repeats += 1
                    self.node.publish(topics.decision_topic(self.ns, p.obs.role), topics.STRING, topics.json_string(p.decision))


class Ros2Policy(Policy):
    """The policy an agent service holds for a role driven from ROS 2: each decision is asked on the
    ROS graph and answered by its action topic (:class:`Decisions`)."""

    name = "ros2"
    inline = False

    def __init__(self, role: Role, decisions: Decisions) -> None:
        super().__init__(role)
        self.decisions = decisions

    async def act_async(self, obs: Observation) -> Action:
        return await self.decisions.ask(obs)

    def end_episode(self, episode_id: str) -> None:
        self.decisions.forget(self.role, episode_id)


class Republisher:
    """The roles not driven and the coordination truth, republished on a thread of its own: zenoh's
    callbacks only queue (at most :data:`QUEUE_SAMPLES`; a full queue drops the oldest, counted), so
    a slow ROS side never holds up the bus."""

    def __init__(self, node: Node, run_id: str, ns: str) -> None:
        self.node, self.run_id, self.ns = node, run_id, ns
        self.samples: queue.Queue[Sample | None] = queue.Queue(QUEUE_SAMPLES)
        self.dropped = 0
        self.rejections = Rejections(log)
        self.thread = threading.Thread(target=self._run, name="ros2-out", daemon=True)
        self.thread.start()

    def put(self, sample: Sample) -> None:
        while True:
            try:
                self.samples.put_nowait(sample)
                return
            except queue.Full:
                with contextlib.suppress(queue.Empty):
                    self.samples.get_nowait()
                    self.dropped += 1

    def close(self) -> None:
        with contextlib.suppress(queue.Full):
            self.samples.put(None, timeout=1.0)
        self.thread.join(timeout=5.0)
        self.rejections.log_summary()
        if self.dropped:
            log.warning("dropped %d observations and coordination states the ROS side was too slow for", self.dropped)

    def _run(self) -> None:
        while (sample := self.samples.get()) is not None:
            try:
                self.republish(sample)
            except Exception:  # one bad sample costs that sample
                log.exception("could not republish %s", sample.key)

    def republish(self, sample: Sample) -> None:
        """One observation or coordination state from the bus, checked as an agent checks what it hears."""
        try:
            message = decode(sample.payload)
        except DecodeError as exc:
            self.rejections.reject(sample.key, "unreadable", exc)
            return
        worker = keys.slot_of(sample.key)
        if isinstance(message, Observation):
            if message.run_id != self.run_id or sample.key != keys.obs(self.run_id, worker, message.role):
                self.rejections.reject(sample.key, "names another run or role than its key")
            elif where := non_finite_field(message):
                self.rejections.reject(sample.key, "a number that is not finite", where)
            else:
                for topic, typename, ros in topics.observation_topics(message, worker=worker, answer_on=None, ns=self.ns):
                    self.node.publish(topic, typename, ros)
        elif isinstance(message, CoordinationState):
            if message.run_id != self.run_id:
                self.rejections.reject(sample.key, "names another run than its key")
            else:
                self.node.publish(topics.coordination_topic(self.ns), topics.STRING,
                                  topics.json_string(topics.coordination_json(message, worker)))
        else:
            self.rejections.reject(sample.key, "wrong message type for the key", type(message).__name__)


async def serve(bus: Bus, node: Node, run_id: str, stop: StopFlag, *, drive: tuple[Role, ...], worker: str = "*",
                ns: str = "", reconnect_grace_s: float) -> int:
    """Bridge run ``run_id`` (one worker's slot, or every slot) to ``node`` until ``stop``."""
    loop = asyncio.get_running_loop()
    decisions = Decisions(node, ns, loop)
    for role in drive:
        node.subscribe(topics.action_topic(ns, role), topics.STRING, functools.partial(decisions.heard, role))
    republisher = Republisher(node, run_id, ns)
    handles = [bus.subscribe(keys.obs(run_id, worker, role), republisher) for role in keys.ROLES if role not in drive]
    handles.append(bus.subscribe(keys.coord_truth(run_id, worker), republisher))
    log.info("ROS 2 bridge of run %s%s: node %s in domain %d (zenoh session %s)%s", run_id,
             "" if worker == "*" else f", worker {worker}", node.name, node.domain, node.zid,
             "".join(f"; {r.upper()} driven from {topics.action_topic(ns, r)}" for r in drive) or "; observing only")
    try:
        served = [serve_async(bus, Ros2Policy(role, decisions), run_id, stop, concurrency=CONCURRENCY,
                              reconnect_grace_s=reconnect_grace_s, worker=worker) for role in drive]
        codes = await asyncio.gather(decisions.repeat(stop), *served)
    finally:
        for handle in handles:
            bus.unsubscribe(handle)
        republisher.close()
        decisions.rejections.log_summary()
    return max((c for c in codes[1:] if c), default=0)


def main(cfg: AgosConfig, *, drive: tuple[Role, ...] = (), worker: str | None = None, ns: str | None = None,
         domain: int = 0, ros_connect: str | None = None, node_name: str = "agos_bridge") -> int:
    """Run the bridge of the configured run until stopped: 130 after Ctrl-C, 0 after SIGTERM."""
    setup_logging("ros2-bridge")
    stop = install_stop_handlers()
    typestore()  # the robotics extra, before connecting
    with ZenohBus.from_settings(cfg.zenoh) as bus:
        ros_config = zenoh_config(connect=[ros_connect]) if ros_connect else session_config(cfg.zenoh)
        session = open_session(ros_config, retry_for_s=cfg.zenoh.connect_timeout_s)
        node = Node(session, node_name, domain=domain)
        try:
            code = asyncio.run(serve(bus, node, cfg.run.run_id, stop, drive=drive, worker=worker or "*",
                                     ns=topics.namespace(ns), reconnect_grace_s=cfg.run.reconnect_grace_s))
        finally:
            node.close()
            session.close()
    return code or stop.exit_code()
