"""The expert's Stage 1-2 (world/expert/): the paper's mTSP MILP on hand-made instances whose optimum
is known, CP-SAT against it, pairing and exclusive waypoints on real towns, the world's timing of
the expert's decisions, and truncation at t_f with the handoff on planned episodes."""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass

import numpy as np
import pytest

from agos.runtime.episode_config import EpisodeConfig
from agos.runtime.schemas import DIFFICULTIES, ExpertStep
from agos.world.expert.coverage import PAIR_IOU, coverage_problem, ground_raster, iou, uav_range, ugv_range
from agos.world.expert.fast import solve_fast
from agos.world.expert.milp import solve_milp
from agos.world.expert.mtsp import MtspInstance, check_solution
from agos.world.expert.planner import ExpertPlan
from agos.world.expert.timeline import Timeline


def _times(points: list[tuple[float, float]], speed_mps: float = 1.0) -> np.ndarray:
    p = np.asarray(points, float)
    return np.hypot(p[:, None, 0] - p[None, :, 0], p[:, None, 1] - p[None, :, 1]) / speed_mps


def _brute_force(inst: MtspInstance) -> float:
    """The least makespan by enumerating every pair of routes (tiny instances only)."""
    def routes(n: int, must: set[int]):
        for k in range(n):
            for subset in itertools.combinations(range(1, n), k):
                if must <= set(subset) | {0}:
                    for order in itertools.permutations(subset):
                        yield [0, *order]
    best = math.inf
    for ra in routes(inst.sizes[0], set(inst.exclusive(0))):
        for rg in routes(inst.sizes[1], set(inst.exclusive(1))):
            if all(a in ra or g in rg for a, g in inst.pairs):
                best = min(best, inst.makespan_s(ra, rg))
    return best


# ----- the MILP on instances whose optimum is known --------------------------------------------
def test_milp_visits_a_line_in_order() -> None:
    inst = MtspInstance(_times([(0, 0), (1, 0), (2, 0), (3, 0)]), _times([(0, 0)]))
    sol = solve_milp(inst)
    assert sol.optimal and sol.uav_route == [0, 1, 2, 3] and sol.ugv_route == [0]
    assert sol.makespan_s == pytest.approx(3.0) and check_solution(inst, sol) == []


def test_milp_gives_a_paired_node_to_the_vehicle_that_reaches_it_sooner() -> None:
    # UAV: a1 and a2 lie 4 s away on opposite sides (8 s apart); a2 is paired with the UGV's g1, 3 s away
    uav = _times([(0, 0), (-4, 0), (4, 0)])
    inst = MtspInstance(uav, _times([(0, 0), (0, 3)]), pairs=((2, 1),))
    sol = solve_milp(inst)
    assert sol.optimal and sol.uav_route == [0, 1] and sol.ugv_route == [0, 1]
    assert sol.makespan_s == pytest.approx(4.0)
    # without the pair the UAV must fly both: 4 + 8 s
    alone = solve_milp(MtspInstance(uav, _times([(0, 0), (0, 3)])))
    assert alone.makespan_s == pytest.approx(12.0)


def test_mtz_forbids_the_cheap_subtour() -> None:
    # 0 -> 1 is 1 s; 2 and 3 are 1 s apart but 10 s from the others: degree constraints alone
    # would close 2 <-> 3 as a loop (cost 1 + 2); the one open route costs 1 + 10 + 1
    times = np.array([[0, 1, 10, 10], [1, 0, 10, 10], [10, 10, 0, 1], [10, 10, 1, 0]], float)
    inst = MtspInstance(times, np.zeros((1, 1)))
    sol = solve_milp(inst)
    assert sol.makespan_s == pytest.approx(12.0) and sol.uav_route[:2] == [0, 1] and check_solution(inst, sol) == []


def test_offsets_enter_the_makespan_and_a_vehicle_may_stay_put() -> None:
    # the UGV is free only at 50 s: the UAV takes the paired node itself, the UGV stays at its start
    inst = MtspInstance(_times([(0, 0), (5, 0)]), _times([(0, 0), (1, 0)]), pairs=((1, 1),), ugv_offset_s=50.0)
    for sol in (solve_milp(inst), solve_fast(inst)):
        assert sol.uav_route == [0, 1] and sol.ugv_route == [0]
        assert sol.makespan_s == pytest.approx(50.0)


@pytest.mark.parametrize("seed", range(4))
def test_milp_and_cp_sat_find_the_brute_force_optimum(seed: int) -> None:
    rng = np.random.default_rng(seed)
    na, ng = int(rng.integers(3, 6)), int(rng.integers(2, 5))
    pairs = tuple((a, g) for a, g in zip(rng.permutation(range(1, na)), rng.permutation(range(1, ng)), strict=False))[:2]
    inst = MtspInstance(_times([tuple(p) for p in rng.uniform(0, 100, (na, 2))], 10.0),
                        _times([tuple(p) for p in rng.uniform(0, 100, (ng, 2))], 8.0), pairs=tuple(pairs))
    best = _brute_force(inst)
    milp, fast = solve_milp(inst), solve_fast(inst)
    assert check_solution(inst, milp) == [] and check_solution(inst, fast) == []
    assert milp.makespan_s == pytest.approx(best, abs=1e-4)
    assert fast.makespan_s == pytest.approx(best, abs=0.02)  # centisecond arithmetic
    assert solve_fast(inst).uav_route == fast.uav_route  # deterministic


# ----- visible ranges, pairing and exclusivity -------------------------------------------------
def test_iou_of_cell_sets() -> None:
    assert iou(np.array([1, 2, 3, 4]), np.array([3, 4, 5, 6])) == pytest.approx(2 / 6)
    assert iou(np.array([], int), np.array([], int)) == 0.0


@pytest.fixture(scope="module")
def deck_town():
    from agos.world.towns.asset import open_town

    return open_town("deck-s19")


def _region_around(town, xy: tuple[float, float], size_m: float = 300.0):
    region = (xy[0] - size_m / 2, xy[1] - size_m / 2, xy[0] + size_m / 2, xy[1] + size_m / 2)
    active = town.uav_grid.inside(region)
    ids, pos = town.roads.anchor_array()
    ugv = next(int(n) for n, p in zip(ids, pos, strict=True)
               if region[0] <= p[0] <= region[2] and region[1] <= p[1] <= region[3] and not town.roads.covered[int(n)]
               and town.roads.anchors[int(n)] == "cruise")
    return region, active, ugv


def test_pairs_clear_the_threshold_and_decks_make_ugv_only_waypoints(deck_town) -> None:
    town = deck_town
    deck_xy = tuple(town.layout.decks[0].polygon_m.mean(axis=0))
    region, active, ugv_start = _region_around(town, deck_xy)
    cov = coverage_problem(town, region, active, active[0], ugv_start, nadir_fov_deg=60.0, ugv_reach_m=50.0)
    ground = ground_raster(town, region)
    half = town.uav_grid.altitude_m * math.tan(math.radians(30.0))
    assert cov.pairs, "a 300 m region over a grid of streets pairs some UAV nodes with anchors"
    for a, g in cov.pairs:
        p = town.roads.positions_world_m[g]
        again = iou(uav_range(ground, town.uav_grid.nodes[a].position_world_m[:2], half), ugv_range(ground, (p[0], p[1]), 50.0))
        assert again >= PAIR_IOU and again == pytest.approx(cov.pair_iou[(a, g)], abs=1e-4)
    assert len({a for a, _ in cov.pairs}) == len(cov.pairs) == len({g for _, g in cov.pairs})
    deck = [g for g in cov.ugv_nodes if cov.ugv_reason[g] == "deck"]
    assert deck and all(town.roads.covered[g] for g in deck)
    assert set(deck) <= set(cov.ugv_exclusive)  # the road under a deck: only the UGV sees it
    assert set(cov.uav_exclusive) == set(cov.uav_nodes) - {a for a, _ in cov.pairs}
    # the UAV's waypoints cover (nearly) all the ground it can see from the nodes it can reach
    reach = town.uav_grid.reachable(active[0], set(active))
    seeable = np.unique(np.concatenate([uav_range(ground, town.uav_grid.nodes[n].position_world_m[:2], half) for n in reach]))
    covered = np.unique(np.concatenate([uav_range(ground, town.uav_grid.nodes[n].position_world_m[:2], half)
                                        for n in cov.uav_nodes]))
    assert len(covered) >= 0.97 * len(seeable)


def test_parks_and_plazas_make_uav_only_waypoints() -> None:
    from agos.world.towns.asset import open_town

    town = open_town("parks-s23")
    park = next(s for s in town.layout.surfaces if s.kind in ("park", "plaza"))
    region, active, ugv_start = _region_around(town, tuple(park.polygon_m.mean(axis=0)))
    cov = coverage_problem(town, region, active, active[0], ugv_start, nadir_fov_deg=60.0, ugv_reach_m=50.0)
    offroad = [n for n in cov.uav_nodes if cov.uav_reason[n] == "offroad"]
    assert offroad and set(offroad) <= set(cov.uav_exclusive)
    ground = ground_raster(town, region)
    assert ground.offroad.any() and not (ground.offroad & ground.road).any()


# ----- the world's timing of the expert's decisions --------------------------------------------
class _Script:
    """An agenda that answers from a fixed list, noting when it was asked and what it knew."""

    def __init__(self, steps: list[tuple[str, float]]) -> None:
        self.steps, self.asked = list(steps), []

    def next_step(self, now: float, knows_candidate: bool):
        action, duration = self.steps.pop(0) if self.steps else ("WAIT", 0.0)
        self.asked.append((now, knows_candidate))
        return ExpertStep(sim_time_s=now, action=action), duration  # type: ignore[arg-type]


def test_timeline_a_ugv_asked_with_the_annotation_learns_it_after_and_the_uav_waits_for_the_verdict() -> None:
    cfg = EpisodeConfig()
    uav = _Script([("MOVE_TO_UAV_WAYPOINT", 5.0), ("ANNOTATE_CANDIDATE", 0.0), ("WAIT", 0.0)])
    ugv = _Script([("MOVE_TO_ROAD_WAYPOINT", 5.0), ("WAIT", 0.0), ("GO_TO_CANDIDATE", 30.0), ("STOP_OBSERVE", 0.0),
                   ("REJECT", 0.0)])
    tl = Timeline(cfg)
    tl.run({"uav": uav, "ugv": ugv}, until_reject=True)
    # both asked at 0 and 5; at 5 the UGV decides before it hears of the candidate (WAIT), is woken
    # at once and asked again at 5, now knowing it; the UAV, frozen, is asked only after the REJECT
    assert ugv.asked == [(0.0, False), (5.0, False), (5.0, True), (35.0, True), (37.0, True)]
    assert uav.asked == [(0.0, True), (5.0, True)]
    assert tl.clocks["uav"].ready_s == 37.0 and not tl.clocks["uav"].frozen
    assert tl.clocks["ugv"].ready_s == 37.0 + cfg.short_action_s
    assert tl.decisions == 7


def test_timeline_unfreezes_the_uav_after_max_freeze_and_ends_on_confirm() -> None:
    cfg = EpisodeConfig()
    uav = _Script([("ANNOTATE_CANDIDATE", 0.0)])
    ugv = _Script([("WAIT", 0.0), ("GO_TO_CANDIDATE", 200.0), ("STOP_OBSERVE", 0.0), ("CONFIRM", 0.0)])
    tl = Timeline(cfg)
    tl.run({"uav": uav, "ugv": ugv}, until_reject=False)
    assert tl.confirmed
    # frozen at 0; asked again at max_freeze_s (120 s), WAITs 20 s at a time until the UGV confirms at 202 s
    assert [t for t, _ in uav.asked] == [0.0, 120.0, 140.0, 160.0, 180.0, 200.0]
    assert [s.sim_time_s for s in tl.steps["ugv"]] == [0.0, 0.0, 200.0, 202.0]


# ----- truncation at t_f and the handoff, on planned episodes ----------------------------------
@dataclass
class _Planned:
    spec_budget: int
    target_xy: tuple[float, float]
    node_xy: dict[str, tuple[float, float]]
    plan: ExpertPlan
    again: ExpertPlan
    last_verifies: bool
    """STOP_OBSERVE then CONFIRM where the plan's UGV stops would pass (rendered)."""
    annotation_holds_target: bool | None


@pytest.fixture(scope="module")
def planned() -> list[_Planned]:
    """Plans of an episode of each difficulty on grid-s7 (the UAV finds the target in each) and one on
    parks-s23 where the UGV finds it first: both finders, at a third of the cost of sampling until both
    appear (12 episodes)."""
    from agos.runtime.episode_config import ToolConfig
    from agos.world.episodes.sampling import sample_episode
    from agos.world.expert.evidence import Evidence
    from agos.world.expert.planner import plan_episode
    from agos.world.sim.engine import EpisodeRunner
    from agos.world.sim.scene import Scene
    from agos.world.towns.asset import open_town

    out: list[_Planned] = []
    for name, cases in (("grid-s7", [("easy", 0), ("mid", 0), ("hard", 0)]), ("parks-s23", [("hard", 1)])):
        town = open_town(name)
        with Scene(town.layout, look="flat") as scene:
            for difficulty, index in cases:
                d = DIFFICULTIES.index(difficulty)
                spec = sample_episode(town, scene, difficulty, index, seed=5, stream=d)
                runner = EpisodeRunner(scene, town, spec, run_id="t", worker_id="t",
                                       config=EpisodeConfig(look="flat", tools=ToolConfig(expert=True)))
                runner._setup()
                try:
                    st = runner.state
                    plan, ev = plan_episode(st), Evidence(st)
                    last = plan.trajectories["ugv"][-1]
                    annotations = [s for s in plan.steps["uav"] if s.action == "ANNOTATE_CANDIDATE"]
                    holds = None
                    if plan.finder == "uav":
                        holds = ev.candidate_centre(plan.trajectories["uav"][-1].waypoint_id, annotations[-1].cell or "")[1]
                    out.append(_Planned(st.spec.decision_budget, st.target_xy,
                                        {n: town.uav_grid.nodes[n].position_world_m[:2] for n in town.uav_grid.nodes},
                                        plan, plan_episode(st), ev.verifies(st.roads.parse_anchor_id(last.waypoint_id),
                                                                            last.heading_rad or 0.0), holds))
                finally:
                    runner.teardown()
    return out


@pytest.mark.slow
def test_truncation_at_t_f_and_the_handoff(planned: list[_Planned]) -> None:
    assert {p.plan.finder for p in planned} == {"uav", "ugv"}
    for case in planned:
        plan, steps = case.plan, case.plan.steps
        assert steps["ugv"][-1].action == "CONFIRM" and steps["ugv"][-2].action == "STOP_OBSERVE"
        assert steps["ugv"][-2].sim_time_s == plan.t_arr_s >= plan.t_f_s
        assert case.last_verifies
        # truncated: no move of the UAV arrives after t_f
        assert all(p.t_s <= plan.t_f_s + 1e-9 for p in plan.trajectories["uav"])
        assert plan.decisions <= case.spec_budget
        if plan.finder == "ugv":
            assert plan.t_arr_s == plan.t_f_s
            assert all(p.t_s <= plan.t_f_s + 1e-9 for p in plan.trajectories["ugv"])
            continue
        annotate = [s for s in steps["uav"] if s.action == "ANNOTATE_CANDIDATE"][-1]
        assert annotate.sim_time_s == plan.t_f_s and "please verify" in (annotate.message or "")
        assert case.annotation_holds_target
        assert math.dist(case.node_xy[plan.trajectories["uav"][-1].waypoint_id], case.target_xy) <= 50.0
        # the UGV stops moving at t_f; then its handoff path: GO_TO_CANDIDATE and perhaps a few options
        go = max(k for k, s in enumerate(steps["ugv"]) if s.action == "GO_TO_CANDIDATE")
        assert steps["ugv"][go].sim_time_s >= plan.t_f_s
        assert not [s for s in steps["ugv"][:go] if s.action == "MOVE_TO_ROAD_WAYPOINT" and s.sim_time_s >= plan.t_f_s]
        path = [p for p in plan.trajectories["ugv"] if p.t_s > plan.t_f_s]
        assert path and path[-1].t_s == pytest.approx(plan.t_arr_s)


@pytest.mark.slow
def test_messages_and_determinism(planned: list[_Planned]) -> None:
    for case in planned:
        plan = case.plan
        assert plan.steps == case.again.steps  # same episode, same plan
        assert (plan.steps["uav"][0].message or "").startswith("UAV at (")
        assert (plan.steps["ugv"][0].message or "").startswith("UGV at (")
        assert "Target confirmed" in (plan.steps["ugv"][-1].message or "")
        assert plan.raw["uav"][0].t_s == 0.0 and plan.raw["ugv"][0].t_s == 0.0
