"""One episode on a discrete-event simulation clock.

Each role becomes *ready* when its previous action completes. At the earliest ready time the
runner builds an observation for every ready role, asks the :class:`DecisionSource` for all of
them at once, and applies the actions in a fixed order (UAV, then UGV). Movement takes
simulated time from path length and speed, so the outcome depends only on the episode, its
seed and the policy, never on wall-clock speed or machine load.

Contract: :class:`EpisodeRunner` owns the loop and its clock (which event comes next: a link
delivery, a beacon, the frozen UAV's timeout, or decisions), the shared decision budget, the
fallback of a missing or refused action to a counted WAIT, the syncs and messages each applied
decision sends through the link model, and everything reported to the :class:`EpisodeSink`.
What an action may be and what it does is :mod:`agos.world.sim.rules`; what a role is shown is
:mod:`agos.world.sim.observations`; the record and SPL's shortest path are
:mod:`agos.world.sim.record`; the state they share is :mod:`agos.world.sim.state`. The loop runs
whole (:meth:`EpisodeRunner.run`, asking a :class:`DecisionSource`: world workers, sweeps) or one
decision round at a time (:meth:`~EpisodeRunner.start`, :meth:`~EpisodeRunner.advance`,
:meth:`~EpisodeRunner.finish`: ``agos.Env``); ``run`` is those three, so both give the same record.

Choices where the paper is silent (also in docs/ARCHITECTURE.md):

* The decision budget (80) is shared: every decision of either role, including fallbacks,
  counts. The episode ends when it is spent.
* WAIT lasts until the coordination state changes for that role (a new candidate, a rejection,
  a message) or ``wait_max_s`` passes, whichever is first.
* After ANNOTATE_CANDIDATE the UAV is frozen (asked nothing) until it hears that the UGV
  confirmed or rejected the candidate, when ``uav_during_verification`` is ``frozen`` (the
  default); with ``active`` it keeps deciding, limited to moving and waiting (rules.py).
* An illegal or missing action becomes a logged WAIT and still counts as a decision.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Protocol

import msgspec
import numpy as np

from agos.runtime.episode_config import EpisodeConfig
from agos.runtime.keys import ROLES
from agos.runtime.schemas import (
    Action,
    ActionName,
    AgentMessage,
    CoordinationState,
    EpisodeRecord,
    EpisodeSpec,
    ImageFrame,
    Observation,
    Role,
    StepEvent,
    StoredTrace,
)
from agos.world.sim import capture, model_link, rules, sensors
from agos.world.sim.comms import Channel
from agos.world.sim.episode_vehicles import add_episode_vehicles
from agos.world.sim.observations import coordination, observe, uav_waypoint
from agos.world.sim.record import decision_pose_error_m, episode_record, logged_step, shortest_confirmable_path
from agos.world.sim.rules import IllegalAction
from agos.world.sim.scene import STUDIO_OFFSET_M, Scene
from agos.world.sim.state import EpisodeState, UavState, UgvState
from agos.world.sim.teammate import teammate_top_view
from agos.world.towns.asset import Town
from agos.world.towns.roadgraph import RoadGraphs
from agos.world.towns.topdown import RegionMap

__all__ = ["ROLE_ORDER", "DecisionSource", "EpisodeRunner", "EpisodeSink", "IllegalAction",
           "NullSink"]

ROLE_ORDER: tuple[Role, Role] = ROLES
"""The order the world applies a round's actions in: :data:`~agos.runtime.keys.ROLES`' order."""


class DecisionSource(Protocol):
    """Where actions come from: agents over zenoh, or policies called in-process in tests."""

    def decide(self, observations: dict[Role, Observation]) -> dict[Role, Action | None]:
        """Return one action per observed role; ``None`` when none arrived in time."""
        ...


class EpisodeSink(Protocol):
    """Where the runner reports what happens (the bus, or a list in tests)."""

    def step(self, event: StepEvent) -> None: ...
    def coordination(self, truth: CoordinationState, views: dict[Role, CoordinationState]) -> None: ...
    def message(self, message: AgentMessage) -> None: ...


class NullSink:
    def step(self, event: StepEvent) -> None:
        pass

    def coordination(self, truth: CoordinationState, views: dict[Role, CoordinationState]) -> None:
        pass

    def message(self, message: AgentMessage) -> None:
        pass


@dataclass(frozen=True)
class SetupMemo:
    """What setting up one episode in one configuration renders and never changes (``setup_memo``)."""

    references: list[ImageFrame]
    teammate: ImageFrame
    shortest_path_m: float | None


MOVES = frozenset({"MOVE_TO_UAV_WAYPOINT", "MOVE_TO_ROAD_WAYPOINT", "GO_TO_CANDIDATE"})
"""The actions that carry a platform somewhere (the views along them are captured in dataset builds)."""


class EpisodeRunner:
    """Runs one :class:`EpisodeSpec` in a :class:`Scene` of its town. Without ``config``, the
    defaults in the scene's look; a ``config`` of another look than the scene's is refused (the
    record would name a look its pictures were not drawn in)."""

    def __init__(self, scene: Scene, town: Town, spec: EpisodeSpec, *, run_id: str, worker_id: str,
                 config: EpisodeConfig | None = None, sink: EpisodeSink | None = None,
                 clock: Callable[[], float] = time.monotonic, setup_memo: dict[bytes, SetupMemo] | None = None) -> None:
        """``setup_memo``: where to keep, across runners of one scene, what setting an episode up renders
        that depends only on the episode and the configuration (the target's reference views, the
        teammate's top view, SPL's shortest path); an episode played again skips those renders and
        gives the same record. None: render them every time."""
        config = config or EpisodeConfig(look=scene.look)
        if config.look != scene.look:
            raise ValueError(f"episode {spec.episode_id}: the configuration's look is {config.look!r} but the scene "
                             f"was built {scene.look!r}; build the scene with look=config.look")
        if config.decision_budget is not None:  # a configured budget replaces the episode's own
            spec = msgspec.structs.replace(spec, decision_budget=config.decision_budget)
        self.state = EpisodeState(scene, town, spec, run_id=run_id, worker_id=worker_id, config=config)
        self.state.searchable_area = [uav_waypoint(town, n) for n in sorted(self.state.active_uav)]
        self.sink = sink or NullSink()
        self._clock = clock
        self._memo = setup_memo
        self._wall_start: float | None = None
        self._round_time_s = 0.0
        self.pending: dict[Role, Observation] = {}
        """The observations of the decision round in play, awaiting :meth:`advance` (in role order)."""

    # ----- set-up ---------------------------------------------------------------------------
    def _setup(self) -> None:
        st = self.state
        spec, scene, cfg = st.spec, st.scene, st.cfg
        st.added = add_episode_vehicles(scene, spec)  # LookMismatch for what this look cannot draw
        st.target_uid = st.added[0]
        st.target_xy = (spec.target.position_world_m[0], spec.target.position_world_m[1])
        st.region_map = RegionMap(st.town.layout, spec.region_world_m, size_px=cfg.cameras.map_px) \
            if cfg.cameras.map_px else None
        start_uav = st.town.uav_grid.nodes[spec.uav_start_waypoint]
        st.uav = UavState(start_uav.node_id, start_uav.position_world_m)
        start = RoadGraphs.parse_anchor_id(spec.ugv_start_waypoint)
        st.ugv = UgvState(start, st.roads.heading_at(start), route=[start])
        st.start_node = start
        key = msgspec.json.encode((spec, cfg.config_hash(), st.town.sha256))
        memo = None if self._memo is None else self._memo.get(key)
        if memo is not None:  # the reference views' trip to the studio and back, whose rounding moves the target
            scene.move(st.target_uid, np.asarray(STUDIO_OFFSET_M))  # by a few ulp: the same as when rendered
            scene.move(st.target_uid, -np.asarray(STUDIO_OFFSET_M))
        else:
            memo = SetupMemo(
                sensors.reference_views(scene, st.target_uid, spec.target.position_world_m, spec.target.yaw_rad,
                                        cfg.cameras),
                teammate_top_view(scene, cfg.cameras),
                shortest_confirmable_path(scene, st.town, start, spec.target, st.target_uid, cfg.confirm_at_view_size(),
                                          cfg.cameras))
            if self._memo is not None:
                self._memo[key] = memo
        st.references, st.teammate_reference, st.shortest_path_m = memo.references, memo.teammate, memo.shortest_path_m
        st.channel = Channel(cfg.comm, spec.seed + 7919 * cfg.link_seed,
                             {"uav": st.believed_pose("uav"), "ugv": st.believed_pose("ugv")})
        st.info_age = {"uav": None, "ugv": None}

    def teardown(self) -> None:
        for uid in self.state.added:
            self.state.scene.remove(uid)
        self.state.added = []

    # ----- main loop ------------------------------------------------------------------------
    def run(self, source: DecisionSource) -> EpisodeRecord:
        """Play the whole episode, asking ``source`` at every decision; the record."""
        observations = self.start()
        try:
            while observations:
                observations = self.advance(source.decide(observations))
        finally:
            self.teardown()
        return self.finish()

    # ----- the same loop, one decision round at a time (agos.Env) ----------------------------
    def start(self) -> dict[Role, Observation]:
        """Set the episode up in the scene and play it to its first decision round: the observations
        of the roles asked then (both at the start), or ``{}`` if the episode ended before any.
        Then :meth:`advance` with their actions, until it returns ``{}``; then :meth:`finish`."""
        if self._wall_start is not None:
            raise RuntimeError(f"episode {self.state.spec.episode_id}: this runner has already started (build a new one)")
        self._wall_start = self._clock()
        try:
            self._setup()
            self._publish_coordination()
            return self._next_round()
        except BaseException:
            self.teardown()
            raise

    def advance(self, actions: Mapping[Role, Action | None]) -> dict[Role, Observation]:
        """Apply the actions answering :attr:`pending` (a role missing from ``actions``, or None, had no
        action: a counted WAIT, as an illegal action is), then play on to the next decision round: its
        observations, or ``{}`` when the episode has ended."""
        if not self.pending:
            raise RuntimeError(f"episode {self.state.spec.episode_id}: no decision is pending (call start() first; "
                               "once start() or advance() returned no observations the episode is over)")
        st = self.state
        observations, self.pending = self.pending, {}
        now = self._round_time_s
        for role in observations:
            st.sim_time_s = now
            self._apply(role, observations[role], actions.get(role))
            if st.termination is not None:
                break
        st.sim_time_s = now
        self._publish_coordination()
        return self._next_round()

    def finish(self) -> EpisodeRecord:
        """Take the episode's vehicles out of the scene (again: harmless) and return its record; the
        record of an episode that did not end says ``termination = "error"``."""
        self.teardown()
        return episode_record(self.state, self._clock() - (self._wall_start or self._clock()))

    def _next_round(self) -> dict[Role, Observation]:
        """Handle events (deliveries, beacons, the frozen UAV's timeout) until some roles are due to
        decide: render their observations (they are now :attr:`pending`). ``{}`` when the episode ends
        first (the budget spent, the sim-time limit passed, or a CONFIRM)."""
        st = self.state
        while st.termination is None:
            remaining = st.spec.decision_budget - st.decisions_used
            if remaining <= 0:
                st.termination = "budget_exhausted"
                break
            ready = {"uav": math.inf if st.uav.frozen else st.uav.ready_at, "ugv": st.ugv.ready_at}
            t_ready = min(ready.values())
            t_arrival, t_beacon = st.channel.next_arrival_s(), st.channel.next_beacon_s()
            t_unfreeze = st.uav.frozen_since + st.cfg.max_freeze_s if st.uav.frozen else math.inf
            now = min(t_ready, t_arrival, t_beacon, t_unfreeze)
            if now > st.cfg.sim_time_limit_s:
                st.termination = "sim_time_limit"
                break
            st.sim_time_s = max(st.sim_time_s, now)
            if t_arrival <= now:
                self._deliver()
            elif t_unfreeze <= now:
                self._unfreeze()
            elif t_beacon <= now:
                for role in ROLE_ORDER:
                    if st.channel.next_beacon[role] <= now:
                        st.channel.sync(role, now, st.believed_pose(role), st.link_geometry(), kind="beacon")
                        st.channel.next_beacon[role] += st.cfg.comm.beacon_s
            else:
                due = [r for r in ROLE_ORDER if ready[r] <= now + 1e-9][:remaining]
                self._round_time_s = st.sim_time_s
                self.pending = {r: observe(st, r) for r in due}
                return dict(self.pending)
        return {}

    def _deliver(self) -> None:
        st = self.state
        for arrival in st.channel.deliver_until(st.sim_time_s):
            if arrival.message is not None:
                st.messages.append(arrival.message)
                self.sink.message(AgentMessage(run_id=st.run_id, episode_id=st.spec.episode_id,
                                               **msgspec.structs.asdict(arrival.message)))
            if arrival.changed:
                self._wake(arrival.receiver)
            if (arrival.receiver == "uav" and st.uav.frozen
                    and st.channel.views["uav"].active_candidate() is None):
                self._unfreeze()
        self._publish_coordination()

    def _unfreeze(self) -> None:
        uav = self.state.uav
        uav.frozen = False
        uav.waiting = False
        uav.ready_at = self.state.sim_time_s

    def _wake(self, role: Role) -> None:
        """A coordination change reached ``role``: end its WAIT now."""
        st = self.state
        agent = st.uav if role == "uav" else st.ugv
        if agent.waiting and agent.ready_at > st.sim_time_s:
            agent.ready_at = st.sim_time_s
        agent.waiting = False

    def _apply(self, role: Role, obs: Observation, action: Action | None) -> None:
        """One decision of ``role``: counted, applied by the rules or turned into a WAIT, then
        its message and a sync of the role's knowledge sent through the link, and its step reported."""
        st = self.state
        st.decisions_used += 1
        route_before = len(st.ugv.route)
        uav_before = st.uav.position[:2]
        decided_s = st.sim_time_s
        if st.cfg.timing_mode == "realtime" and action is not None and action.agent_wall_latency_s:
            # A slow decision takes effect late; the teammate's schedule is unaffected.
            st.sim_time_s += max(0.0, action.agent_wall_latency_s)
        trip = model_link.exchange(st, role, action, st.sim_time_s - decided_s)  # the link to the model, both modes
        if trip is not None:
            st.sim_time_s += trip.link_s
        applied: ActionName = "WAIT"
        candidate_id: str | None = None
        fallback = model_link.failure(st, trip) or rules.refusal(role, obs, action)
        if fallback is None and action is not None:
            try:
                candidate_id = rules.apply_action(st, role, action, obs)
                applied = action.action
            except IllegalAction as exc:
                fallback = str(exc)
        if fallback is not None:
            st.fallbacks += 1
            rules.wait(st, role)
        if st.cfg.capture_every_m is not None and st.cfg.tools.expert and applied in MOVES:  # only experts get them
            self._capture_move(role, uav_before, route_before, st.cfg.capture_every_m)
        if action is not None and action.trace is not None:
            st.traces.append(StoredTrace(role=role, decision_index=obs.decision_index, **msgspec.structs.asdict(action.trace)))
        if action is not None and action.message and fallback is None:
            st.channel.message(role, st.sim_time_s, action.message, st.link_geometry())
        st.channel.sync(role, st.sim_time_s, st.believed_pose(role), st.link_geometry())
        st.step_log.append(logged_step(st, role, obs.decision_index, applied, candidate_id, route_before, trip))
        self.sink.step(StepEvent(
            run_id=st.run_id, episode_id=st.spec.episode_id, role=role, decision_index=obs.decision_index,
            episode_step=st.decisions_used, sim_time_s=st.sim_time_s, requested=action, applied=applied,
            fallback_reason=fallback, pose_after=st.uav_pose() if role == "uav" else st.ugv_pose(),
            target_visible_uav=st.uav_target_px >= st.cfg.uav_visible_min_px() if role == "uav" else None,
            target_visible_ugv=st.ground_visible if role == "ugv" and applied == "STOP_OBSERVE" else None,
            candidate_id=candidate_id, info_age_s=st.info_age[role], pose_error_m=decision_pose_error_m(st, role),
            model_link_s=None if trip is None else round(trip.link_s, 4)))

    def _capture_move(self, role: Role, uav_before: tuple[float, float], route_before: int, every_m: float) -> None:
        """Dataset builds: the role's views along the move just applied, for its next observation."""
        st = self.state
        if role == "uav":
            line = [(uav_before[0], uav_before[1]), (st.uav.position[0], st.uav.position[1])]
        else:
            pos = st.roads.positions_world_m
            line = [(float(pos[n][0]), float(pos[n][1])) for n in st.ugv.route[route_before - 1:]]
        st.passed[role] = capture.views_along(st, role, line, st.sim_time_s, every_m)

    def _publish_coordination(self) -> None:
        st = self.state
        self.sink.coordination(coordination(st),
                               {"uav": coordination(st, "uav"), "ugv": coordination(st, "ugv")})
