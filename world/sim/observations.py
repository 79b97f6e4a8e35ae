"""What each role is shown when it is asked for a decision, and the coordination states.

Contract: :func:`observe` is one decision's sensing for one role: it counts the role's decision,
renders its cameras (the UAV's nadir view with the grid, or the UGV's forward view, or the six
views of its last STOP_OBSERVE), and builds the :class:`Observation` from the role's own view of
the coordination state (never the truth), its waypoint options and the legal actions of
:mod:`agos.world.sim.rules`, the target's references (and for the UAV its teammate's top view,
rendered once at the episode's start), plus the oracle's ground-truth hints when the oracle tool
is on, and the expert's plan when the expert tool is on (made once per episode by the planner
:func:`use_expert_planner` installed: ``agos.world.expert``, a layer above, installs it; this
module only delivers it). It notes in the state what the UAV's camera saw (``uav_target_px``, the oracle-visible step
``tau``) and the role's information age; it moves nothing and sends nothing.
:func:`coordination` builds the truth or a role's view as a :class:`CoordinationState`, with the
decision, annotation and confirmation budgets the world keeps.
"""

from __future__ import annotations

import copy
import math
from collections.abc import Callable

import msgspec

from agos.runtime.codec import encode_png
from agos.runtime.schemas import (
    CoordinationState,
    ExpertHints,
    ImageFrame,
    Observation,
    OracleHints,
    Role,
    Waypoint,
)
from agos.runtime.sensing import Fix
from agos.world.sim import rules, sensors
from agos.world.sim.confirm import check_confirm
from agos.world.sim.localisation import believed_shot
from agos.world.sim.options import uav_options, ugv_options
from agos.world.sim.state import EpisodeState
from agos.world.towns.asset import Town
from agos.world.towns.roadgraph import RoadGraphs


def observe(st: EpisodeState, role: Role) -> Observation:
    """Render ``role``'s cameras and build its observation for its next decision."""
    st.info_age[role] = st.channel.info_age(role, st.sim_time_s)
    cam = st.cfg.cameras
    if role == "uav":
        st.uav.decisions += 1
        shot = sensors.nadir(st.scene, st.uav.position[:2], st.uav.position[2], cam)
        st.uav_target_px = sensors.target_pixels(shot, st.target_uid)
        shot = believed_shot(shot, _decision_fix(st, "uav"), st.uav.position[:2])
        st.uav.last_nadir = shot  # E2A projects the annotated cell from where the UAV believes it looked
        if st.tau is None and st.uav_target_px >= st.cfg.uav_visible_min_px():
            st.tau = st.uav.decisions
        images = sensors.frames_of(shot, st.scene, cam, with_grid=True) + _map_frame(st, "uav")
        options = [uav_waypoint(st.town, n) for n in uav_options(st.town.uav_grid, st.uav.position[:2], st.active_uav)]
        return Observation(
            run_id=st.run_id, episode_id=st.spec.episode_id, role="uav",
            decision_index=st.uav.decisions, sim_time_s=st.sim_time_s, pose=st.believed_pose("uav"),
            mode="aerial", images=images, references=st.references, teammate_reference=st.teammate_reference,
            legal_actions=rules.uav_legal(st, options), waypoint_options=options,
            region_world_m=st.spec.region_world_m,
            active_uav_waypoints=st.searchable_area,
            coordination=coordination(st, "uav"), grid_rows=sensors.GRID_ROWS, grid_cols=sensors.GRID_COLS,
            oracle=_oracle(st, "uav", st.uav_target_px >= st.cfg.uav_visible_min_px()), expert=_expert(st, "uav"))
    st.ugv.decisions += 1
    fix = _decision_fix(st, "ugv")
    shots = st.ugv.six if st.ugv.mode == "stop_6view" else \
        [sensors.ground_view(st.scene, "forward", st.ugv_xy(), st.ugv.heading_rad, cam)]
    images = [f for shot in shots for f in sensors.frames_of(believed_shot(shot, fix, st.ugv_xy()), st.scene, cam)] \
        + _map_frame(st, "ugv")
    road_options = _ugv_options(st)
    return Observation(
        run_id=st.run_id, episode_id=st.spec.episode_id, role="ugv",
        decision_index=st.ugv.decisions, sim_time_s=st.sim_time_s, pose=st.believed_pose("ugv"),
        mode="stop_6view" if st.ugv.mode == "stop_6view" else "driving", images=images,
        references=st.references, legal_actions=rules.ugv_legal(st, road_options), waypoint_options=road_options,
        region_world_m=st.spec.region_world_m, coordination=coordination(st, "ugv"),
        fresh_stop_observe=st.ugv.fresh_stop, oracle=_oracle(st, "ugv", bool(st.ground_visible)),
        expert=_expert(st, "ugv"))


def _decision_fix(st: EpisodeState, role: Role) -> Fix:
    """``role``'s localisation error for the decision being observed, kept for the record."""
    fix = st.fix(role)
    st.decision_fixes[role].append(fix)
    return fix


def uav_waypoint(town: Town, node_id: str) -> Waypoint:
    """A UAV grid node as a waypoint option."""
    return Waypoint(waypoint_id=node_id, position_world_m=town.uav_grid.nodes[node_id].position_world_m,
                    kind="uav_grid")


def coordination(st: EpisodeState, role: Role | None = None) -> CoordinationState:
    """The truth (role None) or what ``role`` knows: its view's candidates and messages, its
    own pose and its teammate's last reported pose."""
    if role is None:
        candidates, messages = st.candidates, st.messages
        poses = {"uav": st.uav_pose(), "ugv": st.ugv_pose()}
    else:
        view = st.channel.views[role]
        candidates = [c for _, c in sorted(view.candidates.items())]
        messages = view.messages
        other = "ugv" if role == "uav" else "uav"
        poses = {role: st.believed_pose(role)}
        if view.teammate_pose is not None:
            poses[other] = view.teammate_pose
    return CoordinationState(
        run_id=st.run_id, episode_id=st.spec.episode_id, sim_time_s=st.sim_time_s,
        candidates=[copy.copy(c) for c in candidates], messages=messages[-st.cfg.recent_messages:],
        poses=poses, decisions_used=st.decisions_used, decision_budget=st.spec.decision_budget,
        annotations_used=len(st.candidates), max_annotations=st.cfg.max_annotations,
        confirmations_used=st.n_confirm, max_confirmations=rules.MAX_CONFIRMATIONS)


def _map_frame(st: EpisodeState, role: Role) -> list[ImageFrame]:
    """M: the episode region from above (north up) with ``role``'s own marker where it is and its
    teammate's where the link last reported it (none before the first report): the map must not
    carry what the link did not (docs/COMMS.md)."""
    if st.region_map is None:
        return []
    own = st.believed_pose(role)
    own_xy = own.position_world_m[:2]
    reported = st.channel.views[role].teammate_pose
    mate_xy = None if reported is None else reported.position_world_m[:2]
    if role == "uav":
        rgb = st.region_map.render(uav_xy=own_xy, ugv_xy=mate_xy,
                                   ugv_yaw_rad=0.0 if reported is None else reported.yaw_rad)
    else:
        rgb = st.region_map.render(uav_xy=mate_xy, ugv_xy=own_xy, ugv_yaw_rad=st.ugv.heading_rad + st.fix("ugv").dyaw_rad)
    return [ImageFrame(name="map", kind="map", encoding="png", data=encode_png(rgb),
                       metres_per_px=st.region_map.metres_per_px)]


def _ugv_options(st: EpisodeState) -> list[Waypoint]:
    """The UGV's road options; without RGPP each carries its distance to the active candidate."""
    pos = st.roads.positions_world_m
    cand = None if st.cfg.tools.rgpp else st.active_candidate("ugv")
    return [Waypoint(waypoint_id=RoadGraphs.anchor_id(o.anchor),
                     position_world_m=(float(pos[o.anchor][0]), float(pos[o.anchor][1]), 0.0),
                     kind=st.roads.anchors[o.anchor], path_length_m=o.path_length_m, option=o.option,
                     distance_to_candidate_m=None if cand is None else round(math.dist(pos[o.anchor], cand.center_world_m), 2))
            for o in ugv_options(st.roads, st.ugv.node, st.ugv.route)]


def _oracle(st: EpisodeState, role: Role, target_in_view: bool) -> OracleHints | None:
    if not st.cfg.tools.oracle:
        return None
    would = role == "ugv" and st.ugv.mode == "stop_6view" and not check_confirm(
        rules.confirm_evidence(st), st.cfg.confirm_at_view_size())
    return OracleHints(target_world_m=st.target_xy, target_in_view=target_in_view, confirm_would_succeed=would)


ExpertPlanner = Callable[[EpisodeState], dict[Role, ExpertHints]]
"""Makes the expert's plan of an episode (its decision script and trajectories per role) from its
state (ground truth and scene)."""

_expert_planner: ExpertPlanner | None = None


def use_expert_planner(planner: ExpertPlanner | None) -> None:
    """Install the planner whose plan observations carry when the expert tool is on (the expert's
    package, agos.world.expert, sits above this one and installs itself: ``agos.world.expert.install``)."""
    global _expert_planner
    _expert_planner = planner


def _expert(st: EpisodeState, role: Role) -> ExpertHints | None:
    """The expert's script for ``role``, planned at the episode's first observation."""
    if not st.cfg.tools.expert:
        return None
    if st.expert_plan is None:
        if _expert_planner is None:
            raise RuntimeError("the expert tool is on but this process has no expert planner: "
                               "call agos.world.expert.install() before running episodes")
        st.expert_plan = _expert_planner(st)
    passed, st.passed[role] = st.passed[role], []
    return msgspec.structs.replace(st.expert_plan[role], passed=passed) if passed else st.expert_plan[role]
