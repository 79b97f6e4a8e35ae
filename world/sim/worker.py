"""The world worker process: lease an episode, simulate it, submit its record; repeat.

    agos world --connect tcp/HOST:PORT --run RUN

A worker holds one *slot* of the run's key space for its whole session (``agos/<run>/slot/<worker>/``,
runtime/keys.py): whatever episode it runs, observations go to ``.../obs/<role>``, actions are awaited
on ``.../act/<role>`` (a wall-clock deadline turns a missing action into a logged WAIT), and the record
is published on ``.../result`` until the evaluator acknowledges it on ``.../ack``. The episode and the
attempt travel in every payload; what names another is refused.
"""

from __future__ import annotations

import logging
import resource
import threading
import time
import traceback

from agos.runtime import keys
from agos.runtime.bus import Bus, Inbox, Sample, ZenohBus
from agos.runtime.codec import DecodeError, decode, decode_as, encode, encode_into
from agos.runtime.episode_config import EpisodeConfig, StoredConfigError, read_config
from agos.runtime.failure_records import failure_record
from agos.runtime.health import announce, host_prefix, unique_id
from agos.runtime.process import StopFlag, install_stop_handlers, setup_logging
from agos.runtime.rejections import Rejections, non_finite_field
from agos.runtime.schemas import (
    Action,
    AgentMessage,
    CoordinationState,
    EpisodeRecord,
    EpisodeSpec,
    EpisodeStarted,
    EpisodeStatus,
    JobGrant,
    JobRequest,
    Observation,
    ResultAck,
    Role,
    RunManifest,
    StepEvent,
)
from agos.runtime.settings import DEFAULTS, AgosConfig
from agos.runtime.viz import FrameStream, full_frames
from agos.world.sim import egl_device
from agos.world.sim.engine import EpisodeRunner
from agos.world.sim.episode_vehicles import LookMismatch
from agos.world.sim.scene import Scene
from agos.world.towns.asset import AssetError, AssetMismatch, Town, town_for

log = logging.getLogger("agos.world")
ACK_WAIT_S = 3.0
SUBMIT_ATTEMPTS = 20
RESEND_S = 5.0
"""An observation still unanswered after this long is published again (same decision index), so
an agent service that restarted picks it up; the decision is counted once."""
STOP_WITHIN_S = 3.0
"""A worker asked to stop (Ctrl-C, or its launcher's SIGTERM) that is still busy this long after, in
a computation that does not look at its stop flag (an expert's plan, a scene being built), ends
itself: an interrupted episode is never submitted, so nothing is lost, and ``agos eval`` and
``agos dataset build`` stop within seconds (runtime/process.py)."""


class BusSink:
    """Publishes the runner's reports on the worker's slot, and mirrors steps and the coordination
    truth on the visualisation stream (lossy, only while watched). The payloads name their episode."""

    def __init__(self, bus: Bus, run_id: str, worker_id: str) -> None:
        self.bus, self.run_id, self.worker_id = bus, run_id, worker_id
        self.events_key, self.viz_events_key = keys.events(run_id, worker_id), keys.viz_events(run_id, worker_id)
        self.truth_key, self.viz_coord_key = keys.coord_truth(run_id, worker_id), keys.viz_coord(run_id, worker_id)
        self.view_keys = {role: keys.coord_view(run_id, worker_id, role) for role in keys.ROLES}

    def step(self, event: StepEvent) -> None:
        payload = encode(event)
        self.bus.publish(self.events_key, payload)
        self.bus.publish_viz(self.viz_events_key, payload)

    def coordination(self, truth: CoordinationState, views: dict[Role, CoordinationState]) -> None:
        payload = encode(truth)
        self.bus.publish(self.truth_key, payload)
        self.bus.publish_viz(self.viz_coord_key, payload)
        for role, view in views.items():
            self.bus.publish(self.view_keys[role], view)

    def message(self, message: AgentMessage) -> None:
        self.bus.publish(keys.message(self.run_id, self.worker_id, message.sender, message.receiver), message)


class AgentPresence:
    """Which agent services have subscribed to a slot's observations, by role: kept from their ``ready``
    tokens (``keys.slot_ready``) for the slot's whole life. A token that vanishes and comes back is the
    same service (a router restarted, a session reconnected: its memory is intact); another id is
    another service."""

    def __init__(self) -> None:
        self._changed = threading.Condition()
        self.ready: dict[str, set[str]] = {role: set() for role in keys.ROLES}

    def put(self, change: Sample) -> None:
        """One change of a ``ready`` token, ``.../ready/<role>/<agent>``: ``+`` or ``-`` (zenoh's thread)."""
        role, agent = keys.ready_of(change.key)
        with self._changed:
            if role not in self.ready:
                return
            (self.ready[role].add if change.payload == b"+" else self.ready[role].discard)(agent)
            self._changed.notify_all()

    def serving(self, role: str) -> set[str]:
        with self._changed:
            return set(self.ready[role])

    def wait_for(self, roles: list[Role], timeout_s: float, stop: StopFlag) -> list[Role]:
        """Wait up to ``timeout_s`` until an agent of each role is ready; the roles still missing."""
        deadline = time.monotonic() + timeout_s
        with self._changed:
            while (missing := [role for role in roles if not self.ready[role]]) and not stop.is_set():
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    break
                self._changed.wait(min(remaining, 0.5))
            return missing


class WorkerSlot:
    """What a world worker declares once for its session (runtime/keys.py: no key names an episode):
    the action and acknowledgement subscriptions, the agents' ``ready`` watch, the observation and
    visualisation keys, and last the slot's liveliness token, on which agent services subscribe to
    its observations. Episodes come and go on it; :meth:`close` when the worker stops."""

    def __init__(self, bus: Bus, run_id: str, worker_id: str) -> None:
        self.bus, self.run_id, self.worker_id = bus, run_id, worker_id
        self.actions, self.acks, self.agents = Inbox(), Inbox(), AgentPresence()
        # One exact subscription per role, not ``act/*``: zenoh delivers to an exact key expression
        # more cheaply, 6-15 us per decision in situ (docs/ARCHITECTURE.md §6, "Decision round trip").
        self.act_keys = {role: keys.act(run_id, worker_id, role) for role in keys.ROLES}
        self._handles = [bus.subscribe(key, self.actions) for key in self.act_keys.values()]
        self._handles.append(bus.subscribe(keys.result_ack(run_id, worker_id), self.acks))
        self._handles.append(bus.watch_liveliness(keys.slot_ready(run_id, worker_id, "*", "*"), self.agents))
        self.obs_keys = {role: keys.obs(run_id, worker_id, role) for role in keys.ROLES}
        self.viz_keys = {role: keys.viz_frame(run_id, worker_id, role) for role in keys.ROLES}
        # Full-resolution views go out only while something subscribes to them (agos record --full);
        # asked now, so that the matching flag is current by the first decision.
        self.full_keys = {role: keys.viz_full(run_id, worker_id, role) for role in keys.ROLES}
        for key in self.full_keys.values():
            bus.watched(key)
        self._token = bus.declare_token(keys.slot_live(run_id, worker_id))

    def close(self) -> None:
        self.bus.undeclare_token(self._token)
        for handle in self._handles:
            self.bus.unsubscribe(handle)


class MissingAgent(RuntimeError):
    """No agent service of some role answers for this run."""

    def __init__(self, roles: list[Role], run_id: str, waited_s: float) -> None:
        names = " and ".join(r.upper() for r in roles)
        hint = "; ".join(f"agos agent --role {r} --run {run_id} --connect <router> --policy <name>" for r in roles)
        super().__init__(f"no {names} agent service subscribed to run {run_id!r} within {waited_s:.0f} s "
                         f"(start one: {hint})")
        self.roles = roles


class AgentVanished(RuntimeError):
    """Mid-episode, the last agent service of a role serving this episode went away: the agents'
    memory of the episode is gone with it, so the attempt is given back to be run afresh."""

    def __init__(self, roles: list[Role]) -> None:
        super().__init__(f"the {' and '.join(r.upper() for r in roles)} agent service of this episode vanished")
        self.roles = roles


class ModelOutage(RuntimeError):
    """An agent answered a decision with ``Action.outage``: its model endpoint gave no answer after its
    retries. Nothing is applied or counted; the attempt is abandoned and given back (the orchestrator
    pauses the episode, then leases it afresh: deploy/run/orchestrator.py)."""

    def __init__(self, role: Role, line: str) -> None:
        super().__init__(f"{role.upper()} agent: {line}")
        self.role, self.line = role, line


class BusDecisionSource:
    """Asks the agent services for one episode's decisions over the worker's slot (lockstep: the sim
    clock waits)."""

    def __init__(self, slot: WorkerSlot, episode_id: str, *, timeout_s: float, stop: StopFlag,
                 agent_wait_s: float = DEFAULTS.run.agent_wait_s, frames: FrameStream | None = None, attempt: int = 1,
                 rejections: Rejections | None = None, reconnect_grace_s: float = DEFAULTS.run.reconnect_grace_s) -> None:
        """``attempt``: the lease's attempt number, stamped on every observation. An action counts only
        when it answers the decision asked of its role in this attempt and names this run, episode and
        the role of its key, with finite numbers; anything else (a late answer meant for an earlier
        episode of the slot, or for a world that died, a stray or forged publisher) is refused and
        counted in ``rejections``. ``reconnect_grace_s``: how long the agent services that served this
        episode may all be gone (their tokens) before the attempt is given back (:class:`AgentVanished`);
        back within it, they kept their memory (a router restarted)."""
        self.slot, self.bus, self.run_id, self.episode_id = slot, slot.bus, slot.run_id, episode_id
        self.attempt = attempt
        self.rejections = rejections or Rejections(log)
        self.timeout_s, self.stop, self.agent_wait_s = timeout_s, stop, agent_wait_s
        self.frames = frames  # thumbnails for observers (runtime/viz.py)
        self.inbox = slot.actions
        self.buffers = {role: bytearray() for role in keys.ROLES}  # each role's last observation, reused
        self.reconnect_grace_s = reconnect_grace_s
        self._served_by: dict[str, set[str]] = {}  # role -> the agents ready at its first decision
        self._gone_since: dict[str, float] = {}  # role -> since when none of those is ready (monotonic)

    def close(self) -> None:
        """Nothing to undeclare: the slot outlives the episode."""

    def _check_agents(self, observations: dict[Role, Observation]) -> None:
        """At an episode's first decisions: wait up to ``agent_wait_s`` until an agent service of each
        role has subscribed to this slot (its ``ready`` token); raise :class:`MissingAgent` naming
        the roles nobody serves."""
        first = [role for role, obs in observations.items() if obs.decision_index == 1]
        if not first:  # every later decision: nothing to wait for
            return
        if (missing := self.slot.agents.wait_for(first, self.agent_wait_s, self.stop)) and not self.stop.is_set():
            raise MissingAgent(missing, self.run_id, self.agent_wait_s)
        for role in first:
            self._served_by[role] = self.slot.agents.serving(role)

    def _watch_agents(self) -> None:
        """Raise :class:`AgentVanished` when every agent service that served a role since the episode's
        first decision has withdrawn its ``ready`` token, and another service serves the role in its
        place or none is back within ``reconnect_grace_s`` (a router restart takes every token away for
        seconds; the same service comes back with its memory): a service started in its place would
        answer without the memory the episode so far built up."""
        now, vanished = time.monotonic(), []
        for role, served_by in self._served_by.items():
            serving = self.slot.agents.serving(role)
            if served_by & serving:
                self._gone_since.pop(role, None)
            elif serving or now - self._gone_since.setdefault(role, now) >= self.reconnect_grace_s:
                vanished.append(role)
        if vanished:
            raise AgentVanished(sorted(vanished))  # type: ignore[arg-type]

    def decide(self, observations: dict[Role, Observation]) -> dict[Role, Action | None]:
        """The ``Action`` structs the agents answered (type-checked while read, applied as they are),
        ``None`` for a role that did not answer in time. Raises :class:`ModelOutage` at the first answer
        that says its model endpoint gave none (``Action.outage``)."""
        self._check_agents(observations)
        self._watch_agents()
        for role, obs in observations.items():
            obs.attempt = self.attempt
            obs.decision_timeout_s = self.timeout_s
            encode_into(obs, self.buffers[role])  # zenoh copies it on put; kept for a resend
            self.bus.publish(self.slot.obs_keys[role], self.buffers[role])
            if self.frames is not None:
                self.frames.offer(self.slot.viz_keys[role], obs)
            if self.bus.watched(self.slot.full_keys[role]):
                for frame in full_frames(obs):
                    self.bus.publish_viz(self.slot.full_keys[role], frame)
        pending = {role: obs.decision_index for role, obs in observations.items()}
        actions: dict[Role, Action | None] = dict.fromkeys(observations)
        deadline = time.monotonic() + self.timeout_s
        resend_at = time.monotonic() + RESEND_S
        while pending and not self.stop.is_set():
            sample = self.inbox.get(timeout_s=min(0.5, max(0.0, deadline - time.monotonic())))
            self._watch_agents()
            if time.monotonic() >= resend_at and pending:
                for role in pending:
                    log.info("%s: re-requesting %s decision %d", self.episode_id, role, pending[role])
                    self.bus.publish(self.slot.obs_keys[role], self.buffers[role])
                resend_at = time.monotonic() + RESEND_S
            if sample is None:
                if time.monotonic() >= deadline:
                    break
                continue
            try:
                action = decode_as(sample.payload, Action)
            except DecodeError as exc:
                self.rejections.reject(sample.key, "unreadable", exc)
                continue
            if reason := self._refusal(sample.key, action, pending):
                self.rejections.reject(sample.key, reason, f"{action.role} decision {action.decision_index}, "
                                                           f"attempt {action.attempt}")
            elif action.outage is not None:  # no decision: the attempt ends here, nothing applied
                raise ModelOutage(action.role, action.outage)
            else:
                actions[action.role] = action
                del pending[action.role]
        for role in pending:
            log.warning("%s: no %s action for decision %d within %.0f s", self.episode_id, role,
                        observations[role].decision_index, self.timeout_s)
        return actions


    def _refusal(self, key: str, action: Action, pending: dict[Role, int]) -> str:
        """Why ``action`` heard on ``key`` does not answer a pending decision ('' when it does)."""
        if action.run_id != self.run_id or key != self.slot.act_keys[action.role]:
            return "names another run or role than its key"
        if action.episode_id != self.episode_id:
            return "for another episode than the slot's"
        if action.attempt != self.attempt:
            return "for another attempt of the episode"
        if pending.get(action.role) != action.decision_index:
            return "not the decision asked"
        if non_finite_field(action):
            return "a number that is not finite"
        return ""


class WorldWorker:
    def __init__(self, cfg: AgosConfig, bus: Bus, stop: StopFlag, worker_id: str) -> None:
        self.cfg, self.bus, self.stop, self.worker_id = cfg, bus, stop, worker_id
        self.run_id = cfg.run.run_id
        self._scenes: dict[tuple[str, str, str], tuple[Town, Scene]] = {}
        """(asset sha256, renderer, look) -> town and scene: the asset hash names a town (imported towns all share
        one generator and seed)."""
        self._give_back: tuple[str | None, str, bool] = (None, "", False)
        """An episode this worker could not finish, why, and whether a model endpoint's outage was why."""
        self.frames = FrameStream(bus)
        self.rejections = Rejections(log)
        self.slot = WorkerSlot(bus, self.run_id, worker_id)
        self.sink = BusSink(bus, self.run_id, worker_id)

    def serve(self) -> int:
        self.bus.declare_token(keys.live(self.run_id, "world", self.worker_id))
        announce("world", self.worker_id, self.run_id)
        manifests = Inbox()
        self.bus.subscribe(keys.manifest(self.run_id), manifests)
        log.info("world worker %s serving run %s", self.worker_id, self.run_id)
        told_over = served = False
        while not self.stop.is_set():
            told_over = any([self._says_over(m) for m in manifests.drain()]) or told_over
            # A manifest is a hint, not an order (anyone on an open router can publish one): the run is
            # over when the orchestrator says so in a grant, or is gone after a manifest said it was. A
            # worker no orchestrator has answered yet is waiting for the run to start, so no manifest
            # ends it (a forged "finished" one published before the orchestrator starts would).
            if told_over and served and not self.bus.alive_tokens(keys.live(self.run_id, "orchestrator", "*"),
                                                                  timeout_s=1.0):
                log.info("run %s is over; worker exits", self.run_id)
                break
            episode, why, outage = self._give_back
            request = JobRequest(worker_id=self.worker_id, give_back=episode, why=why, outage=outage)
            replies = self.bus.request(keys.jobs(self.run_id), request, timeout_s=5.0)
            if not replies:
                self.stop.wait(1.0)  # no orchestrator yet
                continue
            grant = self._grant(replies)
            if grant is None:
                self.stop.wait(1.0)  # no grant for this worker (something else answers ctl/jobs): ask again
                continue
            self._give_back = (None, "", False)  # the orchestrator has heard it
            served = True
            if grant.run_finished:
                log.info("run %s finished; worker exits", self.run_id)
                break
            if grant.episode is None:
                self.stop.wait(1.0)
                continue
            self.run_episode(grant.episode, grant)
        for _, scene in self._scenes.values():
            scene.close()
        self.slot.close()
        self.frames.close()
        self.rejections.log_summary()
        usage = resource.getrusage(resource.RUSAGE_SELF)  # read by bench/bench_eval.py
        log.info("world worker %s exits: CPU %.1f s, peak RSS %.0f MB", self.worker_id,
                 usage.ru_utime + usage.ru_stime, usage.ru_maxrss / 1024)
        return 0

    def _says_over(self, sample: Sample) -> bool:
        manifest = self._read(sample.payload, sample.key)
        if not isinstance(manifest, RunManifest) or manifest.run_id != self.run_id:
            if manifest is not None:
                self.rejections.reject(sample.key, "not this run's manifest")
            return False
        return manifest.status in ("finished", "interrupted")

    def _grant(self, replies: list[bytes]) -> JobGrant | None:
        """The job grant addressed to this worker among the replies to one request (anything else
        answering on ``ctl/jobs`` is refused and counted)."""
        grant = None
        for payload in replies:
            message = self._read(payload, keys.jobs(self.run_id))
            if isinstance(message, JobGrant) and message.worker_id == self.worker_id and grant is None:
                grant = message
            elif message is not None:
                self.rejections.reject(keys.jobs(self.run_id), "not a job grant for this worker")
        return grant

    def _read(self, payload: bytes, key: str) -> object | None:
        """A received control message, or None for one that cannot be read: logged (the first 5 per key
        kind, then every 100th) and ignored, never fatal; a hostile or broken publisher must not end
        the worker."""
        try:
            return decode(payload)
        except DecodeError as exc:
            self.rejections.reject(key, "unreadable", exc)
            return None

    def _scene(self, spec: EpisodeSpec, renderer: str, look: str) -> tuple[Town, Scene]:
        key = (spec.asset_sha256, renderer, look)
        if key not in self._scenes:
            cpu = time.process_time()
            town = town_for(spec.town.generator, spec.town.seed, spec.asset_sha256, town_id=spec.town.town_id,
                            fetch=self._fetch_asset)
            self._scenes[key] = (town, Scene(town.layout, renderer=renderer, look=look))
            log.info("town %s ready: %.1f s CPU for town and scene, %.1f s CPU since the process started",
                     town.town_id, time.process_time() - cpu, time.process_time())
        return self._scenes[key]

    def _fetch_asset(self, sha256: str) -> bytes:
        """An imported town's asset from whoever serves ``agos/assets/<sha256>`` (the orchestrator)."""
        replies = self.bus.request(keys.asset(sha256), b"", timeout_s=60.0)
        if not replies:
            raise AssetError(f"asset {sha256[:12]} is not served on this zenoh network")
        return replies[0]

    def run_episode(self, spec: EpisodeSpec, grant: JobGrant) -> None:
        started = time.monotonic()
        log.info("episode %s (%s) starts, attempt %d", spec.episode_id, spec.difficulty, grant.attempt)
        source = None
        config = self.cfg.world  # only for the failure record of a grant whose configuration is unreadable
        try:
            config = read_config(grant.config, where="job grant")  # the run's, whatever this host's settings
            town, scene = self._scene(spec, config.renderer, config.look)
            started_msg = encode(EpisodeStarted(
                run_id=self.run_id, episode_id=spec.episode_id, difficulty=spec.difficulty,
                worker_id=self.worker_id, town_id=town.town_id, asset_sha256=town.sha256))
            self.bus.publish(self.sink.events_key, started_msg)
            self.bus.publish_viz(self.sink.viz_events_key, started_msg)
            self.bus.publish_viz(keys.viz_spec(self.run_id, self.worker_id), spec)
            source = BusDecisionSource(self.slot, spec.episode_id, timeout_s=config.decision_timeout_s,
                                       stop=self.stop, agent_wait_s=self.cfg.run.agent_wait_s, frames=self.frames,
                                       attempt=grant.attempt, rejections=self.rejections,
                                       reconnect_grace_s=self.cfg.run.reconnect_grace_s)
            runner = EpisodeRunner(scene, town, spec, run_id=self.run_id, worker_id=self.worker_id,
                                   config=config, sink=self.sink)
            record = runner.run(source)
            if self.stop.is_set():
                log.info("episode %s interrupted; not submitted", spec.episode_id)
                return
        except (AssetMismatch, AssetError, StoredConfigError, LookMismatch) as exc:
            record = self._failed(spec, "invalid", str(exc), started, config)
        except MissingAgent as exc:
            log.error("episode %s: %s", spec.episode_id, exc)
            record = self._failed(spec, "agent_crashed", str(exc), started, config)
        except AgentVanished as exc:
            log.warning("episode %s: %s; giving the attempt back to be run afresh", spec.episode_id, exc)
            self._give_back = (spec.episode_id, str(exc), False)
            return
        except ModelOutage as exc:  # not the model's decision: paused, then run afresh (never a WAIT)
            log.warning("episode %s paused, its attempt given back: the model endpoint gave no answer (%s)",
                        spec.episode_id, exc)
            self._give_back = (spec.episode_id, str(exc), True)
            return
        except Exception as exc:
            log.error("episode %s crashed:\n%s", spec.episode_id, traceback.format_exc())
            record = self._failed(spec, "world_crashed", f"{type(exc).__name__}: {exc}", started, config)
        finally:
            if source is not None:
                source.close()
        # The viewers' copy of the record travels like control traffic (one small message an episode):
        # on the lossy stream a full-resolution recording lost it under load, and the file its outcome.
        self.bus.publish(keys.viz_result(self.run_id, self.worker_id), record)
        self.submit(record)
        log.info("episode %s: %s (%s) in %.1f s", spec.episode_id, record.termination,
                 "success" if record.success else "failure", time.monotonic() - started)

    def _failed(self, spec: EpisodeSpec, status: EpisodeStatus, error: str, started: float,
                config: EpisodeConfig) -> EpisodeRecord:
        return failure_record(self.run_id, spec, status=status, worker_id=self.worker_id, error=error,
                              config=config, wall_time_s=time.monotonic() - started)

    def submit(self, record: EpisodeRecord) -> bool:
        """Publish the record until the evaluator acknowledges it (it stores idempotently). Acks of the
        slot's earlier records (a duplicate submission's) are passed over."""
        self.slot.acks.drain()
        key = keys.result(self.run_id, self.worker_id)
        for attempt in range(1, SUBMIT_ATTEMPTS + 1):
            self.bus.publish(key, record)
            deadline = time.monotonic() + ACK_WAIT_S
            while (remaining := deadline - time.monotonic()) > 0:
                sample = self.slot.acks.get(timeout_s=remaining)
                ack = None if sample is None else self._read(sample.payload, sample.key)
                if isinstance(ack, ResultAck) and (ack.run_id, ack.episode_id) == (record.run_id, record.episode_id):
                    return True
            if self.stop.is_set():
                break
            log.warning("no ack for %s (attempt %d); resubmitting", record.episode_id, attempt)
        log.error("record %s was never acknowledged", record.episode_id)
        return False


def main(cfg: AgosConfig, *, worker_id: str | None = None) -> int:
    setup_logging("world")
    stop = install_stop_handlers(exit_after_s=STOP_WITHIN_S)
    ident = worker_id or unique_id(host_prefix())
    log.info(egl_device.apply(cfg.render.egl_device, ident))  # before any scene loads the EGL plugin
    with ZenohBus.from_settings(cfg.zenoh) as bus:
        return WorldWorker(cfg, bus, stop, keys.check_chunk(ident, what="worker id")).serve()
