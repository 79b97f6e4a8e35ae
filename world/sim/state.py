"""The state of one episode in progress, and the settings that shape it.

Contract: :class:`EpisodeState` is plain data plus read-only views of it (poses, link geometry,
the candidate a role believes active). It never renders, draws a random number or sends through
a link; the modules that change it are named on each field group.

Who changes what:

* :mod:`agos.world.sim.engine` creates the state, sets it up in the scene, advances
  ``sim_time_s`` and the budget, counts fallbacks and traces, logs each applied step, and keeps
  the views along a move for the role's next observation (``passed``, dataset builds);
* :mod:`agos.world.sim.rules` applies actions: poses, readiness, candidates and their status,
  CONFIRM outcome and termination;
* :mod:`agos.world.sim.observations` counts each role's decisions and notes what its cameras saw
  (the UAV's last nadir shot, target pixels, the oracle-visible step ``tau``, information age)
  and keeps the expert's plan (handing ``passed`` over with it).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from agos.runtime.episode_config import EpisodeConfig
from agos.runtime.model_link import model_link_for
from agos.runtime.schemas import (
    Candidate,
    EpisodeSpec,
    ExpertHints,
    ImageFrame,
    LoggedStep,
    MessageRecord,
    PassedView,
    Pose,
    Role,
    StoredTrace,
    Termination,
    Waypoint,
)
from agos.runtime.sensing import Fix, PoseErrors
from agos.world.sim import sensors
from agos.world.sim.comms import Channel
from agos.world.sim.localisation import in_degraded_zone
from agos.world.sim.scene import Scene
from agos.world.towns.asset import Town
from agos.world.towns.roadgraph import RoadGraphs
from agos.world.towns.topdown import RegionMap


@dataclass
class UavState:
    node: str
    position: tuple[float, float, float]
    ready_at: float = 0.0
    frozen: bool = False
    frozen_since: float = 0.0
    waiting: bool = False
    decisions: int = 0
    last_nadir: sensors.Shot | None = None


@dataclass
class UgvState:
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


class EpisodeState:
    """One :class:`EpisodeSpec` in a :class:`Scene` of its town, as far as it has run."""

    # Set up by the engine when the episode starts (vehicles added, references rendered):
    target_uid: int
    target_xy: tuple[float, float]
    region_map: RegionMap | None
    references: list[ImageFrame]
    teammate_reference: ImageFrame
    """The UGV from above, for the UAV's observations (agos.world.sim.teammate)."""
    uav: UavState
    ugv: UgvState
    start_node: int
    shortest_path_m: float | None
    channel: Channel
    info_age: dict[str, float | None]
    searchable_area: list[Waypoint]
    """The UAV's searchable area as options: it never changes within an episode, so it is built
    once and every UAV observation carries the same Waypoint objects."""

    def __init__(self, scene: Scene, town: Town, spec: EpisodeSpec, *, run_id: str, worker_id: str,
                 config: EpisodeConfig) -> None:
        self.scene, self.town, self.spec = scene, town, spec
        self.roads: RoadGraphs = town.roads
        self.run_id, self.worker_id = run_id, worker_id
        self.cfg = config
        self.sim_time_s = 0.0
        self.candidates: list[Candidate] = []
        self.messages: list[MessageRecord] = []
        self.decisions_used = 0
        self.fallbacks = 0
        self.traces: list[StoredTrace] = []
        self.step_log: list[LoggedStep] = []
        self.n_confirm = 0
        self.tau: int | None = None
        self.ground_observed = False
        self.termination: Termination | None = None
        self.active_uav = set(spec.active_uav_waypoints)
        self.confirm_failure: str | None = None
        self.uav_target_px = 0
        self.ground_visible: bool | None = None
        self.added: list[int] = []
        self.expert_plan: dict[Role, ExpertHints] | None = None
        """The expert's script per role, planned at the first observation (runs with the expert tool)."""
        self.passed: dict[Role, list[PassedView]] = {"uav": [], "ugv": []}
        """Views along each role's last move, until its next observation (``capture_every_m``)."""
        self.localisation = PoseErrors(config.pose_error, spec.seed + 7919 * config.link_seed)
        self.decision_fixes: dict[Role, list[Fix]] = {"uav": [], "ugv": []}
        """Each role's localisation error at each of its decisions (the record's ``pose_error``)."""
        self.model_link = model_link_for(config.model_link, spec.seed + 7919 * config.link_seed)
        """The link to the model (None: onboard): what model-backed decisions pay in time."""

    # ----- views ----------------------------------------------------------------------------
    def ugv_xy(self) -> tuple[float, float]:
        p = self.roads.positions_world_m[self.ugv.node]
        return (float(p[0]), float(p[1]))

    def ugv_pose(self) -> Pose:
        x, y = self.ugv_xy()
        return Pose(position_world_m=(x, y, 0.0), yaw_rad=round(self.ugv.heading_rad, 6))

    def uav_pose(self) -> Pose:
        return Pose(position_world_m=self.uav.position, yaw_rad=math.pi / 2)

    def pose(self, role: Role) -> Pose:
        return self.uav_pose() if role == "uav" else self.ugv_pose()

    def fix(self, role: Role) -> Fix:
        """``role``'s localisation error now (runtime/sensing.py; none with exact localisation)."""
        def crowded() -> bool:
            if role == "uav":
                return in_degraded_zone(self.scene, self.uav.position)
            x, y = self.ugv_xy()
            return in_degraded_zone(self.scene, (x, y, sensors.UGV_CAMERA_HEIGHT_M))

        return self.localisation.fix(role, self.sim_time_s, crowded)

    def believed_pose(self, role: Role) -> Pose:
        """The pose ``role`` believes it has now: what it is shown and sends its teammate."""
        true, fix = self.pose(role), self.fix(role)
        if fix.dx_m == fix.dy_m == fix.dyaw_rad == 0.0:
            return true
        x, y, z = true.position_world_m
        return Pose(position_world_m=(round(x + fix.dx_m, 3), round(y + fix.dy_m, 3), z),
                    yaw_rad=round(true.yaw_rad + fix.dyaw_rad, 6))

    def link_geometry(self) -> tuple[float, bool]:
        """Distance between the two agents and, where the profile uses it, line of sight."""
        ux, uy, uz = self.uav.position
        gx, gy = self.ugv_xy()
        distance = math.dist((ux, uy, uz), (gx, gy, 2.0))
        if self.cfg.comm.range.nlos_loss == 0:
            return distance, True
        return distance, self.scene.clear_line(np.array([ux, uy, uz]), np.array([gx, gy, 2.0]))

    def active_candidate(self, role: Role) -> Candidate | None:
        """The candidate ``role`` believes is being handled (from its own view)."""
        return self.channel.views[role].active_candidate()
