"""One episode on a discrete-event simulation clock (DESIGN.md §2).

Each role becomes *ready* when its previous action completes. At the earliest ready time the
runner builds an observation for every ready role, asks the :class:`DecisionSource` for all of
them at once, and applies the actions in a fixed order (UAV, then UGV). Movement takes
simulated time from path length and speed, so the outcome depends only on the episode, its
seed and the policy, never on wall-clock speed or machine load.

Choices where the paper is silent (also in docs/ARCHITECTURE.md):

* The decision budget (80) is shared: every decision of either role, including fallbacks,
  counts. The episode ends when it is spent.
* WAIT lasts until the coordination state changes for that role (a new candidate, a rejection,
  a message) or ``wait_max_s`` passes, whichever is first.
* After ANNOTATE_CANDIDATE the UAV is frozen (asked nothing) until the UGV confirms or
  rejects the candidate.
* An illegal or missing action becomes a logged WAIT and still counts as a decision.
"""

from __future__ import annotations

import copy
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Protocol

import msgspec
import networkx as nx
import numpy as np

from agos.runtime.codec import encode_png
from agos.runtime.geometry import centroid, distance_to_polygon
from agos.runtime.links import IDEAL, CommProfile
from agos.runtime.schemas import (
    Action,
    ActionName,
    AgentMessage,
    Candidate,
    CandidateOutcome,
    CoordinationState,
    EpisodeRecord,
    EpisodeSpec,
    ImageFrame,
    MessageRecord,
    Observation,
    OracleHints,
    Pose,
    Role,
    StepEvent,
    StoredTrace,
    Termination,
    Waypoint,
)
from agos.runtime.traces import trace_stats
from agos.world.sim import sensors
from agos.world.sim.comms import Channel
from agos.world.sim.confirm import ConfirmEvidence, ConfirmSettings, check_confirm
from agos.world.sim.evidence import ground_evidence, line_of_sight, target_points
from agos.world.sim.options import shortest_path, uav_options, ugv_options
from agos.world.sim.scene import Scene
from agos.world.towns.asset import Town
from agos.world.towns.roadgraph import RoadGraphs
from agos.world.towns.topdown import RegionMap

ROLE_ORDER: tuple[Role, Role] = ("uav", "ugv")


@dataclass(frozen=True)
class EpisodeSettings:
    uav_speed_mps: float = 10.0
    ugv_speed_mps: float = 8.0
    wait_max_s: float = 20.0
    stop_observe_s: float = 2.0
    short_action_s: float = 1.0
    uav_visible_min_px: int = 30
    """Oracle threshold for "target visible from the air" at the default 512 x 512 nadir view."""
    max_annotations: int = 5
    sim_time_limit_s: float = 3600.0
    recent_messages: int = 6
    max_freeze_s: float = 120.0
    """A UAV that has not heard its candidate resolved by then is asked again (lossy links)."""
    comm: CommProfile = field(default_factory=lambda: IDEAL)
    timing_mode: str = "lockstep"
    candidates: bool = True
    """Structured candidates: ANNOTATE_CANDIDATE and GO_TO_CANDIDATE exist. Off for the Baseline,
    which coordinates through text messages only."""
    e2a: bool = True
    """Ego-to-Allo projection: a candidate is its grid cell on the ground. Off (no_e2a ablation):
    the candidate centre is the UAV's ground footprint and its polygon the whole view."""
    rgpp: bool = True
    """Road-graph path planning: GO_TO_CANDIDATE exists. Off (no_rgpp): the UGV approaches through
    road waypoints, each with its distance to the candidate as a hint."""
    oracle: bool = False
    """Give observations the ground-truth hints of the oracle policy."""
    link_seed: int = 0
    """Extra seed of the link streams, for repeating an episode under other link randomness."""
    """``lockstep``: the sim clock waits for decisions; ``realtime``: a decision's wall-clock
    latency delays its effect in sim time, while the teammate carries on."""
    confirm: ConfirmSettings = field(default_factory=ConfirmSettings)
    cameras: sensors.CameraSettings = field(default_factory=sensors.CameraSettings)


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


class IllegalAction(ValueError):
    """The action is not legal now; the text says why (it becomes a WAIT)."""


@dataclass
class _Uav:
    node: str
    position: tuple[float, float, float]
    ready_at: float = 0.0
    frozen: bool = False
    frozen_since: float = 0.0
    waiting: bool = False
    decisions: int = 0
    last_nadir: sensors.Shot | None = None


@dataclass
class _Ugv:
    node: int
    heading_rad: float
    ready_at: float = 0.0
    waiting: bool = False
    decisions: int = 0
    mode: str = "driving"
    fresh_stop: bool = False
    six: list[sensors.Shot] = field(default_factory=list)
    path_length_m: float = 0.0
    route: list[int] = field(default_factory=list)


class EpisodeRunner:
    """Runs one :class:`EpisodeSpec` in a :class:`Scene` of its town."""

    def __init__(self, scene: Scene, town: Town, spec: EpisodeSpec, *, run_id: str, worker_id: str,
                 settings: EpisodeSettings | None = None, sink: EpisodeSink | None = None,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.scene, self.town, self.spec = scene, town, spec
        self.roads: RoadGraphs = town.roads
        self.run_id, self.worker_id = run_id, worker_id
        self.cfg = settings or EpisodeSettings()
        self.sink = sink or NullSink()
        self._clock = clock
        self.sim_time_s = 0.0
        self.candidates: list[Candidate] = []
        self.messages: list[MessageRecord] = []
        self.decisions_used = 0
        self.fallbacks = 0
        self.traces: list[StoredTrace] = []
        self.n_confirm = 0
        self.tau: int | None = None
        self.ground_observed = False
        self.termination: Termination | None = None
        self.active_uav = set(spec.active_uav_waypoints)
        # The searchable area never changes within an episode: built once, so every UAV
        # observation carries the same Waypoint objects.
        self.searchable_area = [self._uav_waypoint(n) for n in sorted(self.active_uav)]
        self.confirm_failure: str | None = None
        self._uav_target_px = 0
        self._ground_visible: bool | None = None
        self._added: list[int] = []

    # ----- set-up ---------------------------------------------------------------------------
    def _setup(self) -> None:
        spec = self.spec
        self.target_uid = self.scene.add_vehicle(spec.target.model, spec.target.colour,
                                                 spec.target.position_world_m, spec.target.yaw_rad)
        self._added = [self.target_uid] + [
            self.scene.add_vehicle(d.model, d.colour, d.position_world_m, d.yaw_rad) for d in spec.distractors]
        self.target_xy = (spec.target.position_world_m[0], spec.target.position_world_m[1])
        self.region_map = RegionMap(self.town.layout, spec.region_world_m, size_px=self.cfg.cameras.map_px) \
            if self.cfg.cameras.map_px else None
        self.references: list[ImageFrame] = sensors.reference_views(
            self.scene, self.target_uid, spec.target.position_world_m, spec.target.yaw_rad, self.cfg.cameras)
        start_uav = self.town.uav_grid.nodes[spec.uav_start_waypoint]
        self.uav = _Uav(start_uav.node_id, start_uav.position_world_m)
        start = RoadGraphs.parse_anchor_id(spec.ugv_start_waypoint)
        self.ugv = _Ugv(start, self.roads.heading_at(start), route=[start])
        self.start_node = start
        self.shortest_path_m = self._shortest_confirmable_path()
        self.channel = Channel(self.cfg.comm, spec.seed + 7919 * self.cfg.link_seed,
                               {"uav": self._uav_pose(), "ugv": self._ugv_pose()})
        self._info_age: dict[str, float | None] = {"uav": None, "ugv": None}

    def teardown(self) -> None:
        for uid in self._added:
            self.scene.remove(uid)
        self._added = []

    # ----- main loop ------------------------------------------------------------------------
    def run(self, source: DecisionSource) -> EpisodeRecord:
        wall_start = self._clock()
        self._setup()
        try:
            self._publish_coordination()
            while self.termination is None:
                self._step(source)
        finally:
            self.teardown()
        return self._record(self._clock() - wall_start)

    def _step(self, source: DecisionSource) -> None:
        """Advance to the next event: a delivery, a beacon, a freeze timeout, or decisions."""
        remaining = self.spec.decision_budget - self.decisions_used
        if remaining <= 0:
            self.termination = "budget_exhausted"
            return
        ready = {"uav": math.inf if self.uav.frozen else self.uav.ready_at, "ugv": self.ugv.ready_at}
        t_ready = min(ready.values())
        t_arrival, t_beacon = self.channel.next_arrival_s(), self.channel.next_beacon_s()
        t_unfreeze = self.uav.frozen_since + self.cfg.max_freeze_s if self.uav.frozen else math.inf
        now = min(t_ready, t_arrival, t_beacon, t_unfreeze)
        if now > self.cfg.sim_time_limit_s:
            self.termination = "sim_time_limit"
            return
        self.sim_time_s = max(self.sim_time_s, now)
        if t_arrival <= now:
            self._deliver()
        elif t_unfreeze <= now:
            self._unfreeze()
        elif t_beacon <= now:
            for role in ROLE_ORDER:
                if self.channel.next_beacon[role] <= now:
                    self.channel.sync(role, now, self._pose(role), self._link_geometry(), kind="beacon")
                    self.channel.next_beacon[role] += self.cfg.comm.beacon_s
        else:
            self._decide(source, [r for r in ROLE_ORDER if ready[r] <= now + 1e-9][:remaining])

    def _deliver(self) -> None:
        for arrival in self.channel.deliver_until(self.sim_time_s):
            if arrival.message is not None:
                self.messages.append(arrival.message)
                self.sink.message(AgentMessage(run_id=self.run_id, episode_id=self.spec.episode_id,
                                               **msgspec.structs.asdict(arrival.message)))
            if arrival.changed:
                self._wake(arrival.receiver)
            if (arrival.receiver == "uav" and self.uav.frozen
                    and self.channel.views["uav"].active_candidate() is None):
                self._unfreeze()
        self._publish_coordination()

    def _unfreeze(self) -> None:
        self.uav.frozen = False
        self.uav.waiting = False
        self.uav.ready_at = self.sim_time_s

    def _decide(self, source: DecisionSource, due: list[Role]) -> None:
        now = self.sim_time_s
        observations = {r: self._observe(r) for r in due}
        actions = source.decide(observations)
        for role in due:
            self.sim_time_s = now
            self._apply(role, observations[role], actions.get(role))
            if self.termination is not None:
                break
        self.sim_time_s = now
        self._publish_coordination()

    # ----- observations ---------------------------------------------------------------------
    def _observe(self, role: Role) -> Observation:
        self._info_age[role] = self.channel.info_age(role, self.sim_time_s)
        cam = self.cfg.cameras
        if role == "uav":
            self.uav.decisions += 1
            shot = sensors.nadir(self.scene, self.uav.position[:2], self.uav.position[2], cam)
            self.uav.last_nadir = shot
            self._uav_target_px = sensors.target_pixels(shot, self.target_uid)
            if self.tau is None and self._uav_target_px >= self.cfg.uav_visible_min_px:
                self.tau = self.uav.decisions
            images = sensors.frames_of(shot, self.scene, cam, with_grid=True) + self._map_frame()
            options = [self._uav_waypoint(n) for n in self._uav_options()]
            return Observation(
                run_id=self.run_id, episode_id=self.spec.episode_id, role="uav",
                decision_index=self.uav.decisions, sim_time_s=self.sim_time_s, pose=self._uav_pose(),
                mode="aerial", images=images, references=self.references,
                legal_actions=self._uav_legal(options), waypoint_options=options,
                region_world_m=self.spec.region_world_m,
                active_uav_waypoints=self.searchable_area,
                coordination=self._coordination("uav"), grid_rows=sensors.GRID_ROWS, grid_cols=sensors.GRID_COLS,
                oracle=self._oracle("uav", self._uav_target_px >= self.cfg.uav_visible_min_px))
        self.ugv.decisions += 1
        if self.ugv.mode == "stop_6view":
            images = [f for shot in self.ugv.six for f in sensors.frames_of(shot, self.scene, cam)] + self._map_frame()
        else:
            shot = sensors.ground_view(self.scene, "forward", self._ugv_xy(), self.ugv.heading_rad, cam)
            images = sensors.frames_of(shot, self.scene, cam) + self._map_frame()
        options = self._ugv_options()
        return Observation(
            run_id=self.run_id, episode_id=self.spec.episode_id, role="ugv",
            decision_index=self.ugv.decisions, sim_time_s=self.sim_time_s, pose=self._ugv_pose(),
            mode="stop_6view" if self.ugv.mode == "stop_6view" else "driving", images=images,
            references=self.references, legal_actions=self._ugv_legal(options), waypoint_options=options,
            region_world_m=self.spec.region_world_m, coordination=self._coordination("ugv"),
            fresh_stop_observe=self.ugv.fresh_stop, oracle=self._oracle("ugv", bool(self._ground_visible)))

    def _map_frame(self) -> list[ImageFrame]:
        """M: the episode region from above with both agents' markers (north up)."""
        if self.region_map is None:
            return []
        rgb = self.region_map.render(uav_xy=self.uav.position[:2], ugv_xy=self._ugv_xy(), ugv_yaw_rad=self.ugv.heading_rad)
        return [ImageFrame(name="map", kind="map", encoding="png", data=encode_png(rgb),
                           metres_per_px=self.region_map.metres_per_px)]

    def _uav_options(self) -> list[str]:
        return uav_options(self.town.uav_grid, self.uav.position[:2], self.active_uav)

    def _uav_waypoint(self, node_id: str) -> Waypoint:
        return Waypoint(waypoint_id=node_id, position_world_m=self.town.uav_grid.nodes[node_id].position_world_m,
                        kind="uav_grid")

    def _active_candidate(self, role: Role) -> Candidate | None:
        """The candidate ``role`` believes is being handled (from its own view)."""
        return self.channel.views[role].active_candidate()

    def _uav_legal(self, options: list[Waypoint]) -> list[ActionName]:
        legal: list[ActionName] = ["MOVE_TO_UAV_WAYPOINT"] if options else []
        if (self.cfg.candidates and self._active_candidate("uav") is None
                and len(self.candidates) < self.cfg.max_annotations):
            legal.append("ANNOTATE_CANDIDATE")
        return [*legal, "NO_RELIABLE_CANDIDATE", "WAIT"]

    def _ugv_options(self) -> list[Waypoint]:
        pos = self.roads.positions_world_m
        cand = None if self.cfg.rgpp else self._active_candidate("ugv")
        return [Waypoint(waypoint_id=RoadGraphs.anchor_id(o.anchor),
                         position_world_m=(float(pos[o.anchor][0]), float(pos[o.anchor][1]), 0.0),
                         kind=self.roads.anchors[o.anchor], path_length_m=o.path_length_m, option=o.option,
                         distance_to_candidate_m=None if cand is None else round(math.dist(pos[o.anchor], cand.center_world_m), 2))
                for o in ugv_options(self.roads, self.ugv.node, self.ugv.route)]

    def _oracle(self, role: Role, target_in_view: bool) -> OracleHints | None:
        if not self.cfg.oracle:
            return None
        would = role == "ugv" and self.ugv.mode == "stop_6view" and not check_confirm(self._evidence(), self.cfg.confirm)
        return OracleHints(target_world_m=self.target_xy, target_in_view=target_in_view, confirm_would_succeed=would)

    def _ugv_legal(self, options: list[Waypoint]) -> list[ActionName]:
        legal: list[ActionName] = ["MOVE_TO_ROAD_WAYPOINT"] if options else []
        if self._active_candidate("ugv") is not None and self.cfg.rgpp:
            legal.append("GO_TO_CANDIDATE")
        legal += ["STOP_OBSERVE", "CONFIRM"]
        if self._active_candidate("ugv") is not None or self.ugv.mode == "stop_6view":
            legal.append("REJECT")
        return [*legal, "WAIT"]

    # ----- actions --------------------------------------------------------------------------
    def _apply(self, role: Role, obs: Observation, action: Action | None) -> None:
        self.decisions_used += 1
        if self.cfg.timing_mode == "realtime" and action is not None and action.agent_wall_latency_s:
            # A slow decision takes effect late; the teammate's schedule is unaffected.
            self.sim_time_s += max(0.0, action.agent_wall_latency_s)
        fallback: str | None = None
        applied: ActionName = "WAIT"
        candidate_id: str | None = None
        if action is None:
            fallback = "no action before the deadline"
        elif action.decision_index != obs.decision_index or action.role != role:
            fallback = f"action answers decision {action.role}#{action.decision_index}, not {role}#{obs.decision_index}"
        elif action.action not in obs.legal_actions:
            fallback = f"{action.action} is not legal now (legal: {', '.join(obs.legal_actions)})"
        else:
            try:
                candidate_id = (self._apply_uav if role == "uav" else self._apply_ugv)(action, obs)
                applied = action.action
            except IllegalAction as exc:
                fallback = str(exc)
        if fallback is not None:
            self.fallbacks += 1
            self._wait(role)
        if action is not None and action.trace is not None:
            self.traces.append(StoredTrace(role=role, decision_index=obs.decision_index, **msgspec.structs.asdict(action.trace)))
        if action is not None and action.message and fallback is None:
            self.channel.message(role, self.sim_time_s, action.message, self._link_geometry())
        self.channel.sync(role, self.sim_time_s, self._pose(role), self._link_geometry())
        self.sink.step(StepEvent(
            run_id=self.run_id, episode_id=self.spec.episode_id, role=role, decision_index=obs.decision_index,
            episode_step=self.decisions_used, sim_time_s=self.sim_time_s, requested=action, applied=applied,
            fallback_reason=fallback, pose_after=self._uav_pose() if role == "uav" else self._ugv_pose(),
            target_visible_uav=self._uav_target_px >= self.cfg.uav_visible_min_px if role == "uav" else None,
            target_visible_ugv=self._ground_visible if role == "ugv" and applied == "STOP_OBSERVE" else None,
            candidate_id=candidate_id, info_age_s=self._info_age[role]))

    def _wait(self, role: Role) -> None:
        agent = self.uav if role == "uav" else self.ugv
        agent.ready_at = self.sim_time_s + self.cfg.wait_max_s
        agent.waiting = True

    def _wake(self, role: Role) -> None:
        """A coordination change reached ``role``: end its WAIT now."""
        agent = self.uav if role == "uav" else self.ugv
        if agent.waiting and agent.ready_at > self.sim_time_s:
            agent.ready_at = self.sim_time_s
        agent.waiting = False

    def _apply_uav(self, action: Action, obs: Observation) -> str | None:
        uav, now = self.uav, self.sim_time_s
        uav.waiting = False
        if action.action == "MOVE_TO_UAV_WAYPOINT":
            if action.waypoint_id not in {w.waypoint_id for w in obs.waypoint_options}:
                raise IllegalAction(f"waypoint {action.waypoint_id!r} is not a UAV option now")
            node = self.town.uav_grid.nodes[action.waypoint_id]
            dist = math.dist(uav.position[:2], node.position_world_m[:2])
            uav.node, uav.position = node.node_id, node.position_world_m
            uav.ready_at = now + dist / self.cfg.uav_speed_mps
            return None
        if action.action == "ANNOTATE_CANDIDATE":
            try:
                cell = (action.cell or "").upper()
                sensors.parse_cell(cell)
            except ValueError as exc:
                raise IllegalAction(str(exc)) from None
            assert uav.last_nadir is not None
            if self.cfg.e2a:
                polygon = sensors.cell_polygon_world(cell, uav.last_nadir.world_from_camera, uav.last_nadir.intrinsics)
                centre = centroid(polygon)
            else:  # the cell is kept as metadata; the candidate is the UAV's whole ground footprint
                polygon = sensors.footprint_world(uav.last_nadir.world_from_camera, uav.last_nadir.intrinsics)
                centre = (float(uav.position[0]), float(uav.position[1]))
            approach = self._approach_anchor(centre)
            cand = Candidate(candidate_id=f"C{len(self.candidates) + 1:03d}", cell=cell,
                             polygon_world_m=[(round(x, 3), round(y, 3)) for x, y in polygon],
                             center_world_m=(round(centre[0], 3), round(centre[1], 3)), status="pending",
                             created_sim_time_s=now,
                             approach_waypoint_id=RoadGraphs.anchor_id(approach) if approach is not None else None)
            self.candidates.append(cand)
            self.channel.views["uav"].candidates[cand.candidate_id] = copy.copy(cand)
            uav.frozen, uav.frozen_since = True, now
            uav.ready_at = now + self.cfg.short_action_s
            return cand.candidate_id
        if action.action == "NO_RELIABLE_CANDIDATE":
            uav.ready_at = now + self.cfg.short_action_s
            return None
        self._wait("uav")
        return None

    def _apply_ugv(self, action: Action, obs: Observation) -> str | None:
        ugv, now = self.ugv, self.sim_time_s
        ugv.waiting = False
        kind = action.action
        if kind == "MOVE_TO_ROAD_WAYPOINT":
            if action.waypoint_id not in {w.waypoint_id for w in obs.waypoint_options}:
                raise IllegalAction(f"waypoint {action.waypoint_id!r} is not a road option now")
            self._drive_to(RoadGraphs.parse_anchor_id(action.waypoint_id))
            return None
        if kind == "GO_TO_CANDIDATE":
            cand = self._candidate(action.candidate_id)
            if cand.approach_waypoint_id is None:
                raise IllegalAction(f"candidate {cand.candidate_id} has no reachable road approach")
            self._drive_to(RoadGraphs.parse_anchor_id(cand.approach_waypoint_id))
            self._set_status(cand.candidate_id, "arrived")
            return cand.candidate_id
        if kind == "STOP_OBSERVE":
            ugv.mode, ugv.fresh_stop = "stop_6view", True
            ugv.six = sensors.six_views(self.scene, self._ugv_xy(), ugv.heading_rad, self.cfg.cameras)
            self._ground_visible = not check_confirm(self._evidence(), self.cfg.confirm)
            self.ground_observed |= self._ground_visible
            ugv.ready_at = now + self.cfg.stop_observe_s
            return None
        if kind == "CONFIRM":
            self.n_confirm += 1
            reasons = check_confirm(self._evidence(), self.cfg.confirm)
            cand = self._active_candidate("ugv")
            if cand is not None:
                self._set_status(cand.candidate_id, "false_confirm" if reasons else "confirmed")
            self.termination = "false_confirm" if reasons else "confirmed"
            self.confirm_failure = "; ".join(reasons) or None
            return cand.candidate_id if cand else None
        if kind == "REJECT":
            cand = self._active_candidate("ugv") if action.candidate_id is None else self._candidate(action.candidate_id)
            ugv.mode, ugv.fresh_stop = "driving", False
            ugv.ready_at = now + self.cfg.short_action_s
            if cand is not None:
                self._set_status(cand.candidate_id, "rejected")  # the UAV learns it through the link
                return cand.candidate_id
            return None
        self._wait("ugv")
        return None

    def _candidate(self, candidate_id: str | None) -> Candidate:
        """A candidate the UGV knows of (its own view) and can still act on."""
        cand = self.channel.views["ugv"].candidates.get(candidate_id or "")
        if cand is None:
            raise IllegalAction(f"no candidate {candidate_id!r} known to the UGV")
        if cand.status not in ("pending", "arrived"):
            raise IllegalAction(f"candidate {candidate_id} is {cand.status}")
        return cand

    def _set_status(self, candidate_id: str, status: str) -> None:
        """A UGV status change: in the truth and in the UGV's own view at once."""
        for cand in self.candidates:
            if cand.candidate_id == candidate_id:
                cand.status = status
        view = self.channel.views["ugv"].candidates.get(candidate_id)
        if view is not None:
            view.status = status

    def _drive_to(self, target: int) -> None:
        ugv = self.ugv
        try:
            path = shortest_path(self.roads, ugv.node, target)
        except nx.NetworkXNoPath:
            raise IllegalAction(f"no road path to {RoadGraphs.anchor_id(target)}") from None
        length = self.roads.path_length_m(path)
        ugv.route.extend(path[1:])
        ugv.node = target
        if len(path) > 1:
            a, b = self.roads.positions_world_m[path[-2]], self.roads.positions_world_m[path[-1]]
            ugv.heading_rad = math.atan2(b[1] - a[1], b[0] - a[0])
        ugv.path_length_m += length
        ugv.mode, ugv.fresh_stop, ugv.six = "driving", False, []
        ugv.ready_at = self.sim_time_s + max(length / self.cfg.ugv_speed_mps, self.cfg.short_action_s)

    def _approach_anchor(self, centre: tuple[float, float], radius_m: float = 20.0) -> int | None:
        """Road-graph path planning: the reachable decision anchor that best trades closeness to
        the candidate centre against road distance from the UGV (1 m closer is worth 20 m of
        driving); the nearest reachable anchor if none lies within ``radius_m``."""
        lengths = nx.single_source_dijkstra_path_length(self.roads.fine, self.ugv.node, weight="length_m")
        ids, xy = self.roads.anchor_array()
        dist = np.hypot(xy[:, 0] - centre[0], xy[:, 1] - centre[1])
        near = [(float(d) + 0.05 * lengths[int(n)], int(n)) for n, d in zip(ids, dist, strict=True)
                if d <= radius_m and int(n) in lengths]
        if near:
            return min(near)[1]
        return next((int(ids[i]) for i in np.argsort(dist) if int(ids[i]) in lengths), None)

    # ----- checker --------------------------------------------------------------------------
    def _evidence(self) -> ConfirmEvidence:
        """Checker evidence for the UGV as it is now (its last six views)."""
        xy = self._ugv_xy()
        return ConfirmEvidence(
            fresh_stop=self.ugv.fresh_stop,
            max_target_pixels=max((sensors.target_pixels(s, self.target_uid) for s in self.ugv.six), default=0),
            distance_m=math.dist(xy, self.target_xy), line_of_sight=self._line_of_sight(xy))

    def _line_of_sight(self, xy: tuple[float, float]) -> bool:
        t = self.spec.target
        return line_of_sight(self.scene, xy, self.target_uid, target_points(t.position_world_m, t.yaw_rad))

    def _shortest_confirmable_path(self, max_checks: int = 30) -> float | None:
        """SPL's shortest path: road distance from the UGV start to the nearest fine node from
        which a STOP_OBSERVE then CONFIRM would be accepted (nodes in Dijkstra order; distance
        and line of sight are checked before rendering)."""
        lengths = nx.single_source_dijkstra_path_length(self.roads.fine, self.start_node, weight="length_m")
        pos = self.roads.positions_world_m
        t = self.spec.target
        points = target_points(t.position_world_m, t.yaw_rad)
        checks = 0
        for node, dist in sorted(lengths.items(), key=lambda kv: (kv[1], kv[0])):
            xy = (float(pos[node][0]), float(pos[node][1]))
            if math.dist(xy, self.target_xy) > self.cfg.confirm.max_distance_m:
                continue
            if not line_of_sight(self.scene, xy, self.target_uid, points):
                continue
            checks += 1
            evidence = ground_evidence(self.scene, self.town, node, self.target_uid, points, self.target_xy,
                                       self.cfg.cameras)
            if not check_confirm(evidence, self.cfg.confirm):
                return round(float(dist), 3)
            if checks >= max_checks:
                break
        return None

    # ----- state views ----------------------------------------------------------------------
    def _ugv_xy(self) -> tuple[float, float]:
        p = self.roads.positions_world_m[self.ugv.node]
        return (float(p[0]), float(p[1]))

    def _ugv_pose(self) -> Pose:
        x, y = self._ugv_xy()
        return Pose(position_world_m=(x, y, 0.0), yaw_rad=round(self.ugv.heading_rad, 6))

    def _uav_pose(self) -> Pose:
        return Pose(position_world_m=self.uav.position, yaw_rad=math.pi / 2)

    def _pose(self, role: Role) -> Pose:
        return self._uav_pose() if role == "uav" else self._ugv_pose()

    def _link_geometry(self) -> tuple[float, bool]:
        """Distance between the two agents and, where the profile uses it, line of sight."""
        ux, uy, uz = self.uav.position
        gx, gy = self._ugv_xy()
        distance = math.dist((ux, uy, uz), (gx, gy, 2.0))
        if self.cfg.comm.range.nlos_loss == 0:
            return distance, True
        return distance, self.scene.clear_line(np.array([ux, uy, uz]), np.array([gx, gy, 2.0]))

    def _coordination(self, role: Role | None = None) -> CoordinationState:
        """The truth (role None) or what ``role`` knows: its view's candidates and messages, its
        own pose and its teammate's last reported pose."""
        if role is None:
            candidates, messages = self.candidates, self.messages
            poses = {"uav": self._uav_pose(), "ugv": self._ugv_pose()}
        else:
            view = self.channel.views[role]
            candidates = [c for _, c in sorted(view.candidates.items())]
            messages = view.messages
            other = "ugv" if role == "uav" else "uav"
            poses = {role: self._pose(role)}
            if view.teammate_pose is not None:
                poses[other] = view.teammate_pose
        return CoordinationState(
            run_id=self.run_id, episode_id=self.spec.episode_id, sim_time_s=self.sim_time_s,
            candidates=[copy.copy(c) for c in candidates], messages=messages[-self.cfg.recent_messages:],
            poses=poses, decisions_used=self.decisions_used, decision_budget=self.spec.decision_budget,
            annotations_used=len(self.candidates), max_annotations=self.cfg.max_annotations)

    def _publish_coordination(self) -> None:
        self.sink.coordination(self._coordination(), {"uav": self._coordination("uav"), "ugv": self._coordination("ugv")})

    def _record(self, wall_time_s: float) -> EpisodeRecord:
        outcomes = [CandidateOutcome(
            candidate_id=c.candidate_id, cell=c.cell, center_world_m=c.center_world_m, status=c.status,
            distance_to_polygon_m=round(distance_to_polygon(self.target_xy, c.polygon_world_m), 3),
            center_error_m=round(math.dist(c.center_world_m, self.target_xy), 3)) for c in self.candidates]
        return EpisodeRecord(
            run_id=self.run_id, episode_id=self.spec.episode_id, difficulty=self.spec.difficulty,
            status="finished", termination=self.termination or "error",
            success=self.termination == "confirmed", ground_observed=self.ground_observed,
            n_confirm=self.n_confirm, ugv_path_length_m=round(self.ugv.path_length_m, 3),
            shortest_path_length_m=self.shortest_path_m,
            final_distance_m=round(math.dist(self._ugv_xy(), self.target_xy), 3),
            uav_budget=self.spec.decision_budget, uav_first_visible_step=self.tau, candidates=outcomes,
            decisions_uav=self.uav.decisions, decisions_ugv=self.ugv.decisions, fallbacks=self.fallbacks,
            sim_time_s=round(self.sim_time_s, 3), wall_time_s=round(wall_time_s, 3), worker_id=self.worker_id,
            town_id=self.town.town_id, asset_sha256=self.town.sha256, seed=self.spec.seed,
            renderer=self.scene.renderer_name(), comm_profile=self.cfg.comm.name, timing_mode=self.cfg.timing_mode,
            link=self.channel.stats(self.candidates), ledger=self.channel.ledger, confirm_rejection=self.confirm_failure,
            tools={"candidates": self.cfg.candidates, "e2a": self.cfg.e2a, "rgpp": self.cfg.rgpp, "oracle": self.cfg.oracle},
            agent_stats=trace_stats(self.traces), decision_traces=self.traces)
