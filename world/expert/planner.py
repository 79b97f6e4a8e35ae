"""The expert's plan of one episode: Stage 1 (trajectories) and Stage 2 (actions and messages).

1. **Waypoints** (:mod:`agos.world.expert.coverage`): both roles' waypoints over the region, the
   IoU >= 0.8 pairs and the role-exclusive ones.
2. **mTSP** on the metric closures (:mod:`agos.world.expert.closure`), solved by CP-SAT
   (:mod:`agos.world.expert.fast`; the paper's MILP in :mod:`agos.world.expert.milp` is the
   reference): two open routes of least makespan.
3. **Raw trajectories** ``Tra_0``: each route expanded into the decisions that fly or drive it,
   with the world's arrival times: the UAV by neighbour moves over the active nodes, the UGV by
   the road options the world offers (at each anchor the option farthest along a shortest road
   path to the next waypoint).
4. **t_f**: the first decision point where either role finds the target: the UAV within 50 m
   of it with the target oracle-visible in its nadir view and its centre in the image; the UGV
   within 50 m (the CONFIRM distance) where STOP_OBSERVE then CONFIRM would pass, with the
   heading it arrives with. Ties go to the UGV (no handoff needed). Should neither route find it
   (the cover is of visible ranges, not of every pixel), each role continues from its route's end
   to the nearest place where it would, and the earlier one finds it (the "mop-up").
5. **Truncation and handoff**: both roles stop at t_f (a move that would arrive after t_f is not
   made: the role WAITs). If the UAV finds it, it ANNOTATEs the target's cell with an inspection
   request; the UGV, once it knows the candidate, GO_TO_CANDIDATE (the world's road-graph path
   planning), and, where that anchor cannot verify, drives on by road options to the anchor
   nearest by road that can; it arrives at ``t_arr``. Then STOP_OBSERVE and CONFIRM with the
   confirmation signal. If the UGV finds it, ``t_arr = t_f``.
6. **Wrong candidates** (hard episodes): the first look-alike the UAV sees before t_f is
   annotated; the UGV goes there, STOP_OBSERVEs and REJECTs; then both continue: the mTSP is
   solved again over the waypoints not yet searched, from where each role is and when it is
   free. At most ``MAX_WRONG`` per episode, and only where the plan still fits the decision budget.

Stage 2's timeline (:mod:`agos.world.expert.timeline`) turns this into one step per decision of
each role, with the world's timing, and counts them against the shared budget.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field

from agos.runtime.keys import ROLES
from agos.runtime.schemas import ExpertHints, ExpertStep, ExpertWaypoint, Role
from agos.world.expert.closure import distances_to, uav_flight, uav_path
from agos.world.expert.coverage import CoverageProblem
from agos.world.expert.evidence import Evidence, as_xy
from agos.world.expert.fast import solve_fast
from agos.world.expert.instance import episode_coverage, routing_problem
from agos.world.expert.mtsp import MtspSolution
from agos.world.expert.timeline import Timeline
from agos.world.sim.options import heading_after, shortest_path, ugv_options
from agos.world.sim.rules import approach_anchor
from agos.world.sim.state import EpisodeState
from agos.world.towns.roadgraph import RoadGraphs

log = logging.getLogger(__name__)

FIND_WITHIN_M = 50.0
"""The paper's discovery radius around the target."""
MAX_WRONG = 1
"""Wrong-candidate cases per hard episode."""


class PlanError(RuntimeError):
    """No plan: the episode is not solvable from where the roles are (a sampler bug)."""


@dataclass(frozen=True)
class TrajectoryPoint:
    """One decision point of a trajectory: a UAV grid node or a UGV anchor (``R<n>``), reached at
    ``t_s`` (the role decides there)."""

    waypoint_id: str
    t_s: float
    heading_rad: float | None = None
    """UGV only: the heading it arrives with."""


@dataclass
class ExpertPlan:
    """Stage 1 and 2 for one episode."""

    steps: dict[Role, list[ExpertStep]]
    """Per role, one step per decision, in order (what the expert policy replays)."""
    raw: dict[Role, list[TrajectoryPoint]]
    """Tra_0: the first mTSP solution's routes expanded into decision points (before truncation)."""
    trajectories: dict[Role, list[TrajectoryPoint]]
    """Tra: where each role actually decides, truncated at t_f, with the UGV's handoff path."""
    t_f_s: float
    t_arr_s: float
    finder: Role
    wrong_candidates: int
    mop_up: bool
    """Neither route found the target: a role went on to the nearest place that does."""
    coverage: CoverageProblem
    solutions: list[MtspSolution] = field(default_factory=list)

    @property
    def decisions(self) -> int:
        return len(self.steps["uav"]) + len(self.steps["ugv"])


def hints_of(st: EpisodeState, plan: ExpertPlan) -> dict[Role, ExpertHints]:
    """What each role's observations carry of ``plan``: its script and its trajectories, with
    positions (UAV nodes at their ground point, UGV anchors where the road graph puts them)."""
    pos = st.roads.positions_world_m

    def where(role: Role, waypoint_id: str) -> tuple[float, float]:
        if role == "uav":
            x, y, _ = st.town.uav_grid.nodes[waypoint_id].position_world_m
        else:
            x, y = pos[RoadGraphs.parse_anchor_id(waypoint_id)][:2]
        return (round(float(x), 3), round(float(y), 3))

    def points(role: Role, trajectory: list[TrajectoryPoint]) -> list[ExpertWaypoint]:
        return [ExpertWaypoint(waypoint_id=p.waypoint_id, position_world_m=where(role, p.waypoint_id), t_s=round(p.t_s, 3))
                for p in trajectory]

    return {role: ExpertHints(steps=plan.steps[role], raw_trajectory=points(role, plan.raw[role]),
                              trajectory=points(role, plan.trajectories[role]), t_f_s=round(plan.t_f_s, 3),
                              t_arr_s=round(plan.t_arr_s, 3), finder=plan.finder, wrong_candidates=plan.wrong_candidates)
            for role in ROLES}


def plan_episode(st: EpisodeState, *, deterministic_time: float = 5.0) -> ExpertPlan:
    """The expert's plan for the episode ``st`` has set up (target and look-alikes in the scene).
    Hard episodes get a wrong-candidate case where it fits the decision budget."""
    evidence = Evidence(st)
    wrong = MAX_WRONG if st.spec.difficulty == "hard" else 0
    plan = _Planner(st, evidence, wrong, deterministic_time).run()
    if plan.decisions > st.spec.decision_budget and wrong:
        plan = _Planner(st, evidence, 0, deterministic_time).run()
    if plan.decisions > st.spec.decision_budget:
        log.warning("%s: the expert's plan takes %d decisions, over the budget of %d", st.spec.episode_id, plan.decisions,
                    st.spec.decision_budget)
    return plan


def _fmt(xy: tuple[float, float]) -> str:
    return f"({xy[0]:.1f}, {xy[1]:.1f})"


@dataclass
class _Event:
    kind: str
    """``uav_found``, ``ugv_found`` or ``wrong`` (the UAV sees a look-alike)."""
    t_s: float
    index: int
    """Index of the finder's trajectory point where it happens."""
    cell: str | None = None
    centre: tuple[float, float] | None = None
    approach: int | None = None
    """The anchor GO_TO_CANDIDATE will drive to (UAV events)."""
    ugv_index: int = 0
    """The UGV's last trajectory point reached by t_s (UAV events)."""


class _Planner:
    def __init__(self, st: EpisodeState, evidence: Evidence, wrong: int, deterministic_time: float) -> None:
        self.st, self.ev, self.wrong_left, self.dt = st, evidence, wrong, deterministic_time
        self.cfg = st.cfg
        self.roads: RoadGraphs = st.roads
        self.grid = st.town.uav_grid
        self.active = set(st.spec.active_uav_waypoints)
        self.timeline = Timeline(st.cfg)
        self.coverage = episode_coverage(st.town, st.spec, st.cfg)
        self.visited_uav: set[str] = set()
        self.visited_ugv: set[int] = set()
        self.solutions: list[MtspSolution] = []
        self.executed: dict[Role, list[TrajectoryPoint]] = {"uav": [], "ugv": []}
        self.greeted: dict[Role, bool] = {"uav": False, "ugv": False}
        self.candidates = 0

    # ----- the whole plan -----------------------------------------------------------------------
    def run(self) -> ExpertPlan:
        st = self.st
        uav_at, uav_t = st.spec.uav_start_waypoint, 0.0
        start = self.roads.parse_anchor_id(st.spec.ugv_start_waypoint)
        ugv_at, ugv_t, heading = start, 0.0, self.roads.heading_at(start)
        raw: dict[Role, list[TrajectoryPoint]] | None = None
        wrong_staged, mop_up = 0, False
        while True:
            uav_pts, ugv_pts, used_mop_up = self._segment(uav_at, uav_t, ugv_at, ugv_t, heading)
            mop_up |= used_mop_up
            if raw is None:
                raw = {"uav": list(uav_pts), "ugv": list(ugv_pts)}
            event = self._first_event(uav_pts, ugv_pts)
            outcome = self._play(event, uav_pts, ugv_pts)
            if outcome is None:
                break
            wrong_staged += 1
            uav_at, uav_t, ugv_at, ugv_t, heading = outcome
        finder: Role = "ugv" if event.kind == "ugv_found" else "uav"
        t_arr = self.timeline.steps["ugv"][-2].sim_time_s  # the STOP_OBSERVE before CONFIRM
        return ExpertPlan(steps=self.timeline.steps, raw=raw, trajectories=self.executed, t_f_s=event.t_s,
                          t_arr_s=t_arr, finder=finder, wrong_candidates=wrong_staged, mop_up=mop_up,
                          coverage=self.coverage, solutions=self.solutions)

    # ----- one mTSP solve and its expansion -----------------------------------------------------
    def _segment(self, uav_at: str, uav_t: float, ugv_at: int, ugv_t: float, heading: float,
                 ) -> tuple[list[TrajectoryPoint], list[TrajectoryPoint], bool]:
        self.visited_uav.add(uav_at)
        self.visited_ugv.add(ugv_at)
        problem = routing_problem(self.st.town, self.st.spec, self.cfg, self.coverage, uav_at=uav_at, uav_t=uav_t,
                                  ugv_at=ugv_at, ugv_t=ugv_t, visited_uav=self.visited_uav, visited_ugv=self.visited_ugv)
        uav_nodes, ugv_nodes, inst = problem.uav_nodes, problem.ugv_nodes, problem.instance
        sol = solve_fast(inst, deterministic_time=self.dt)
        self.solutions.append(sol)
        uav_pts = self._fly([uav_nodes[i] for i in sol.uav_route], uav_t)
        ugv_pts = self._drive([ugv_nodes[i] for i in sol.ugv_route], ugv_t, heading)
        if self._found_uav(uav_pts) is None and self._found_ugv(ugv_pts) is None:
            return self._mop_up(uav_pts), self._mop_up_ugv(ugv_pts), True
        return uav_pts, ugv_pts, False

    def _fly(self, route: list[str], t0: float) -> list[TrajectoryPoint]:
        """Decision points of a UAV flying ``route`` by neighbour moves, from time ``t0``."""
        points = [TrajectoryPoint(route[0], t0)]
        for a, b in zip(route, route[1:], strict=False):
            _, before = uav_flight(self.grid, self.active, a)
            for node in uav_path(before, a, b)[1:]:
                points.append(TrajectoryPoint(node, points[-1].t_s + self._flight_s(points[-1].waypoint_id, node)))
        return points

    def _flight_s(self, a: str, b: str) -> float:
        pa, pb = self.grid.nodes[a].position_world_m, self.grid.nodes[b].position_world_m
        return math.dist(pa[:2], pb[:2]) / self.cfg.uav_speed_mps

    def _drive(self, route: list[int], t0: float, heading: float) -> list[TrajectoryPoint]:
        """Decision points of a UGV driving ``route`` by road options, from time ``t0``."""
        points = [TrajectoryPoint(RoadGraphs.anchor_id(route[0]), t0, heading)]
        for goal in route[1:]:
            points += self._hops(RoadGraphs.parse_anchor_id(points[-1].waypoint_id), goal, points[-1].t_s,
                                 points[-1].heading_rad or 0.0)
        return points

    def _hops(self, node: int, goal: int, t0: float, heading: float) -> list[TrajectoryPoint]:
        """Option moves from ``node`` to ``goal``: at each anchor the offered option that lies on a
        shortest road path to ``goal`` and gets closest to it (ties by anchor id)."""
        to_goal = distances_to(self.roads, goal)
        out: list[TrajectoryPoint] = []
        t = t0
        while node != goal:
            best: tuple[float, int, list[int]] | None = None
            for option in ugv_options(self.roads, node, []):
                left = to_goal.get(option.anchor)
                if left is None or left >= to_goal[node] - 1e-9:
                    continue
                path = shortest_path(self.roads, node, option.anchor)
                on_shortest = self.roads.path_length_m(path) + left <= to_goal[node] + 1e-6
                if on_shortest and (best is None or (left, option.anchor) < best[:2]):
                    best = (left, option.anchor, path)
            if best is None:
                raise PlanError(f"no road option from {RoadGraphs.anchor_id(node)} makes progress to {RoadGraphs.anchor_id(goal)}")
            _, node, path = best
            t = t + max(self.roads.path_length_m(path) / self.cfg.ugv_speed_mps, self.cfg.short_action_s)
            heading = heading_after(self.roads, path, heading)
            out.append(TrajectoryPoint(RoadGraphs.anchor_id(node), t, heading))
        return out

    # ----- finding the target -------------------------------------------------------------------
    def _found_uav(self, points: list[TrajectoryPoint]) -> int | None:
        for k, p in enumerate(points):
            if self.ev.uav_cell(p.waypoint_id, self.st.target_uid, self.ev.target_xy, FIND_WITHIN_M) is not None:
                return k
        return None

    def _found_ugv(self, points: list[TrajectoryPoint]) -> int | None:
        for k, p in enumerate(points):
            if self.ev.verifies(RoadGraphs.parse_anchor_id(p.waypoint_id), p.heading_rad or 0.0):
                return k
        return None

    def _mop_up(self, points: list[TrajectoryPoint]) -> list[TrajectoryPoint]:
        """The UAV's route continued to the nearest node (by flight) that finds the target."""
        end = points[-1].waypoint_id
        lengths, before = uav_flight(self.grid, self.active, end)
        for node in sorted(lengths, key=lambda n: (lengths[n], n)):
            if self.ev.uav_cell(node, self.st.target_uid, self.ev.target_xy, FIND_WITHIN_M) is not None:
                return points + self._fly(uav_path(before, end, node), points[-1].t_s)[1:]
        return points

    def _mop_up_ugv(self, points: list[TrajectoryPoint]) -> list[TrajectoryPoint]:
        """The UGV's route continued to the anchor nearest by road where it would confirm."""
        end = RoadGraphs.parse_anchor_id(points[-1].waypoint_id)
        goal = self.ev.nearest_verifying(end, points[-1].heading_rad or 0.0)
        if goal is None:
            return points
        return points + self._hops(end, goal, points[-1].t_s, points[-1].heading_rad or 0.0)

    def _first_event(self, uav_pts: list[TrajectoryPoint], ugv_pts: list[TrajectoryPoint]) -> _Event:
        k_uav, k_ugv = self._found_uav(uav_pts), self._found_ugv(ugv_pts)
        if k_uav is None and k_ugv is None:
            raise PlanError("neither role can find the target from where it is")
        ugv_first = k_ugv is not None and (k_uav is None or ugv_pts[k_ugv].t_s <= uav_pts[k_uav].t_s)
        t_f = ugv_pts[k_ugv].t_s if ugv_first and k_ugv is not None else uav_pts[k_uav or 0].t_s
        if self.wrong_left > 0:
            for k, p in enumerate(uav_pts):
                if p.t_s >= t_f:
                    break
                wrong = self._wrong_candidate(p, k, ugv_pts)
                if wrong is not None:
                    return wrong
        if ugv_first and k_ugv is not None:
            return _Event("ugv_found", t_f, k_ugv)
        assert k_uav is not None
        cell = self.ev.uav_cell(uav_pts[k_uav].waypoint_id, self.st.target_uid, self.ev.target_xy, FIND_WITHIN_M)
        assert cell is not None
        centre, _ = self.ev.candidate_centre(uav_pts[k_uav].waypoint_id, cell)
        ugv_index = max(k for k, p in enumerate(ugv_pts) if p.t_s <= t_f or k == 0)
        approach = approach_anchor(self.roads, RoadGraphs.parse_anchor_id(ugv_pts[ugv_index].waypoint_id), centre)
        return _Event("uav_found", t_f, k_uav, cell, centre, approach, ugv_index)

    def _wrong_candidate(self, point: TrajectoryPoint, k: int, ugv_pts: list[TrajectoryPoint]) -> _Event | None:
        """A wrong-candidate case at the UAV's point ``k``, when a look-alike is in view there, its
        cell holds no target, and the anchor the UGV would verify it from does not show the target."""
        for uid, xy in self.ev.lookalikes():
            cell = self.ev.uav_cell(point.waypoint_id, uid, xy, math.inf)
            if cell is None:
                continue
            centre, holds_target = self.ev.candidate_centre(point.waypoint_id, cell)
            if holds_target:
                continue
            ugv_index = max(j for j, p in enumerate(ugv_pts) if p.t_s <= point.t_s or j == 0)
            node = RoadGraphs.parse_anchor_id(ugv_pts[ugv_index].waypoint_id)
            approach = approach_anchor(self.roads, node, centre)
            if approach is None:
                continue
            path = shortest_path(self.roads, node, approach)
            if self.ev.verifies(approach, heading_after(self.roads, path, ugv_pts[ugv_index].heading_rad or 0.0)):
                continue
            return _Event("wrong", point.t_s, k, cell, centre, approach, ugv_index)
        return None

    # ----- Stage 2: the decisions --------------------------------------------------------------
    def _play(self, event: _Event, uav_pts: list[TrajectoryPoint], ugv_pts: list[TrajectoryPoint],
              ) -> tuple[str, float, int, float, float] | None:
        """Run the timeline through ``event``; None when the episode ends (CONFIRM), else where
        and when both roles are free again after a rejected wrong candidate."""
        uav_last = event.index if event.kind != "ugv_found" else max(k for k, p in enumerate(uav_pts) if p.t_s <= event.t_s)
        uav = _UavAgenda(self, uav_pts[:uav_last + 1], event)
        if event.kind == "ugv_found":
            ugv_agenda: _UgvAgenda = _UgvAgenda(self, ugv_pts[:event.index + 1], event, [])
        else:
            node = RoadGraphs.parse_anchor_id(ugv_pts[event.ugv_index].waypoint_id)
            heading = ugv_pts[event.ugv_index].heading_rad or 0.0
            tail = self._approach(node, heading, event)
            ugv_agenda = _UgvAgenda(self, ugv_pts[:event.ugv_index + 1], event, tail)
        self.timeline.run({"uav": uav, "ugv": ugv_agenda}, until_reject=event.kind == "wrong")
        for role, reached in zip(ROLES, (uav.reached, ugv_agenda.reached), strict=True):
            self.executed[role] += reached[1:] if self.executed[role] else reached  # a segment starts where the last ended
        self.visited_uav |= {p.waypoint_id for p in uav.reached}
        self.visited_ugv |= {RoadGraphs.parse_anchor_id(p.waypoint_id) for p in ugv_agenda.reached}
        if event.kind != "wrong":
            return None
        self.wrong_left -= 1
        last = ugv_agenda.reached[-1]
        return (uav.reached[-1].waypoint_id, self.timeline.clocks["uav"].ready_s,
                RoadGraphs.parse_anchor_id(last.waypoint_id), self.timeline.clocks["ugv"].ready_s, last.heading_rad or 0.0)

    def _approach(self, node: int, heading: float, event: _Event) -> list[TrajectoryPoint]:
        """The UGV's handoff path from ``node``: GO_TO_CANDIDATE's anchor, then (the true target,
        where that anchor cannot verify) road options to the nearest anchor that can. Times are
        relative to the GO_TO_CANDIDATE decision (0)."""
        if event.approach is None:
            raise PlanError("the candidate has no road approach")
        path = shortest_path(self.roads, node, event.approach)
        length = self.roads.path_length_m(path)
        heading = heading_after(self.roads, path, heading)
        first = TrajectoryPoint(RoadGraphs.anchor_id(event.approach), max(length / self.cfg.ugv_speed_mps, self.cfg.short_action_s),
                                heading)
        if event.kind == "wrong" or self.ev.verifies(event.approach, heading):
            return [first]
        goal = self.ev.nearest_verifying(event.approach, heading)
        if goal is None:
            raise PlanError(f"no anchor verifies the target from {first.waypoint_id}")
        return [first, *self._hops(event.approach, goal, first.t_s, heading)]

    def greeting(self, role: Role, xy: tuple[float, float]) -> str | None:
        """The initial position exchange, on each role's first decision."""
        if self.greeted[role]:
            return None
        self.greeted[role] = True
        return f"{role.upper()} at {_fmt(xy)}, starting the search."


def _join(*parts: str | None) -> str | None:
    text = " ".join(p for p in parts if p)
    return text or None


class _UavAgenda:
    """The UAV: fly its points up to the event; there ANNOTATE the cell (a UAV event), else WAIT."""

    def __init__(self, planner: _Planner, points: list[TrajectoryPoint], event: _Event) -> None:
        self.p, self.points, self.event = planner, points, event
        self.k = 0
        self.reached: list[TrajectoryPoint] = [points[0]]
        self.done = False

    def next_step(self, now: float, knows_candidate: bool) -> tuple[ExpertStep, float]:
        grid = self.p.grid
        here = self.points[self.k].waypoint_id
        hello = self.p.greeting("uav", grid.nodes[here].position_world_m[:2])
        if not self.done and self.event.kind != "ugv_found" and self.k == len(self.points) - 1 and now == self.points[-1].t_s:
            self.done = True
            self.p.candidates += 1
            cell, centre = self.event.cell, self.event.centre
            assert cell is not None and centre is not None
            request = f"Possible target in cell {cell} near {_fmt(centre)}; please verify."
            return ExpertStep(sim_time_s=now, action="ANNOTATE_CANDIDATE", cell=cell, message=_join(hello, request)), 0.0
        if not self.done and self.k + 1 < len(self.points):
            nxt = self.points[self.k + 1]
            self.k += 1
            self.reached.append(nxt)
            return (ExpertStep(sim_time_s=now, action="MOVE_TO_UAV_WAYPOINT", waypoint_id=nxt.waypoint_id, message=hello),
                    self.p._flight_s(here, nxt.waypoint_id))
        self.done = True
        return ExpertStep(sim_time_s=now, action="WAIT", message=hello), 0.0


class _UgvAgenda:
    """The UGV: drive its points up to the event; a UGV event: STOP_OBSERVE, CONFIRM. A UAV event:
    WAIT until it knows the candidate, GO_TO_CANDIDATE, drive the rest of ``tail``, STOP_OBSERVE,
    then CONFIRM (the target) or REJECT (a look-alike)."""

    def __init__(self, planner: _Planner, points: list[TrajectoryPoint], event: _Event, tail: list[TrajectoryPoint]) -> None:
        self.p, self.points, self.event, self.tail = planner, points, event, tail
        self.k = 0
        self.reached: list[TrajectoryPoint] = [points[0]]
        self.phase = "search"
        self.tail_k = 0

    def next_step(self, now: float, knows_candidate: bool) -> tuple[ExpertStep, float]:
        roads = self.p.roads
        here = self.reached[-1]
        hello = self.p.greeting("ugv", as_xy(roads.positions_world_m[RoadGraphs.parse_anchor_id(here.waypoint_id)]))
        if self.phase == "search":
            if self.event.kind == "ugv_found" and self.k == len(self.points) - 1:
                self.phase = "verdict"
                return ExpertStep(sim_time_s=now, action="STOP_OBSERVE", message=hello), 0.0
            if self.k + 1 < len(self.points):
                nxt = self.points[self.k + 1]
                self.k += 1
                self.reached.append(nxt)
                return (ExpertStep(sim_time_s=now, action="MOVE_TO_ROAD_WAYPOINT", waypoint_id=nxt.waypoint_id, message=hello),
                        self._drive_s(here, nxt))
            self.phase = "await"
        if self.phase == "await":
            if not knows_candidate:
                return ExpertStep(sim_time_s=now, action="WAIT", message=hello), 0.0
            self.phase = "approach"
            first = self.tail[0]
            self.reached.append(TrajectoryPoint(first.waypoint_id, now + first.t_s, first.heading_rad))
            cid = f"C{self.p.candidates:03d}"
            return ExpertStep(sim_time_s=now, action="GO_TO_CANDIDATE", candidate_id=cid, message=hello), first.t_s
        if self.phase == "approach":
            self.tail_k += 1
            if self.tail_k < len(self.tail):
                nxt = self.tail[self.tail_k]
                prev = self.tail[self.tail_k - 1]
                self.reached.append(TrajectoryPoint(nxt.waypoint_id, now + nxt.t_s - prev.t_s, nxt.heading_rad))
                return (ExpertStep(sim_time_s=now, action="MOVE_TO_ROAD_WAYPOINT", waypoint_id=nxt.waypoint_id),
                        self._drive_s(prev, nxt))
            self.phase = "verdict"
            return ExpertStep(sim_time_s=now, action="STOP_OBSERVE"), 0.0
        if self.event.kind == "wrong":
            self.phase = "done"
            return ExpertStep(sim_time_s=now, action="REJECT", candidate_id=f"C{self.p.candidates:03d}"), 0.0
        xy = as_xy(roads.positions_world_m[RoadGraphs.parse_anchor_id(here.waypoint_id)])
        return ExpertStep(sim_time_s=now, action="CONFIRM", message=f"Target confirmed near {_fmt(xy)}; search complete."), 0.0

    def _drive_s(self, a: TrajectoryPoint, b: TrajectoryPoint) -> float:
        path = shortest_path(self.p.roads, RoadGraphs.parse_anchor_id(a.waypoint_id), RoadGraphs.parse_anchor_id(b.waypoint_id))
        return self.p.roads.path_length_m(path) / self.p.cfg.ugv_speed_mps

