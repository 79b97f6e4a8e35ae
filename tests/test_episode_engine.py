"""The episode engine in-process, with the real PyBullet scene and scripted decision sources: its
own contract (the shared budget, counted WAITs, the frozen UAV, one record per episode and policy)
on EpisodeRunner itself; what a heuristic episode sends (types, maps) played through agos.Env."""

from __future__ import annotations

import msgspec
import pytest

from agos import Env
from agos.agents.contract import action_for
from agos.agents.inprocess import InProcessAgents
from agos.agents.registry import make_policy
from agos.runtime.episode_config import CameraConfig, EpisodeConfig
from agos.runtime.schemas import Action, EpisodeRecord, EpisodeSpec, Observation, Role, StepEvent
from agos.world.episodes.sampling import generate_episodes
from agos.world.sim.engine import EpisodeRunner, NullSink
from agos.world.sim.scene import Scene
from agos.world.towns.asset import build_town

from support.episodes import SMALL_CAMERAS


@pytest.fixture(scope="module")
def world():
    town = build_town("grid", 7)
    with Scene(town.layout, look="flat") as scene:
        episodes = {e.difficulty + e.episode_id[-6:-3]: e for e in generate_episodes(town, scene, per_difficulty=2, seed=1)}
        yield town, scene, episodes


class Recorder(NullSink):
    def __init__(self) -> None:
        self.steps: list[StepEvent] = []

    def step(self, event: StepEvent) -> None:
        self.steps.append(event)


class Scripted:
    """Answers each role with ``choose(obs)``."""

    def __init__(self, choose) -> None:
        self.choose = choose

    def decide(self, observations: dict[Role, Observation]) -> dict[Role, Action | None]:
        return {role: self.choose(obs) for role, obs in observations.items()}


SMALL = CameraConfig(**SMALL_CAMERAS)


def run(world, key: str, source, sink=None, *, budget: int | None = None, cameras: CameraConfig = SMALL) -> EpisodeRecord:
    """``source`` plays episode ``key``; ``budget`` shortens the decision budget (the paper's 80 by default).
    Small images unless ``cameras`` says otherwise: scripted sources do not look at them."""
    town, scene, episodes = world
    config = EpisodeConfig(look="flat", cameras=cameras, **({} if budget is None else {"decision_budget": budget}))
    return EpisodeRunner(scene, town, episodes[key], run_id="t", worker_id="w", sink=sink, config=config).run(source)


def heuristic() -> InProcessAgents:
    return InProcessAgents({r: make_policy("heuristic", r) for r in ("uav", "ugv")})


def without_wall_time(record: EpisodeRecord) -> EpisodeRecord:
    return msgspec.structs.replace(record, wall_time_s=0.0)


def test_heuristic_confirms_an_easy_target(world) -> None:
    record = run(world, "easy000", heuristic(), cameras=CameraConfig())
    assert record.status == "finished" and record.termination == "confirmed" and record.success
    assert record.ground_observed and record.n_confirm == 1
    # The confirmed candidate is near the target; not always its cell: since parked traffic carries vivid
    # paints too, the UAV may annotate a same-paint car beside the target (before it ever saw the target
    # itself: uav_first_visible_step None) and the UGV confirm the target, as here.
    assert record.candidates[-1].status == "confirmed" and record.candidates[-1].distance_to_polygon_m < 10.0
    assert record.shortest_path_length_m is not None and record.final_distance_m <= 50.0


@pytest.mark.slow
def test_same_episode_and_policy_give_identical_records(world) -> None:
    first = run(world, "mid000", heuristic(), cameras=CameraConfig())
    second = run(world, "mid000", heuristic(), cameras=CameraConfig())
    assert without_wall_time(first) == without_wall_time(second)


def test_budget_is_shared_and_ends_the_episode(world) -> None:
    record = run(world, "easy001", Scripted(lambda obs: action_for(obs, "WAIT")), budget=16)
    assert record.termination == "budget_exhausted" and not record.success
    assert record.decisions_uav + record.decisions_ugv == 16


def test_illegal_and_missing_actions_become_counted_waits(world) -> None:
    def choose(obs: Observation) -> Action | None:
        if obs.role == "uav":
            return action_for(obs, "CONFIRM")  # not a UAV action
        return None if obs.decision_index % 2 else action_for(obs, "MOVE_TO_ROAD_WAYPOINT", waypoint_id="R-1")

    sink = Recorder()
    record = run(world, "easy001", Scripted(choose), sink, budget=16)
    assert record.fallbacks == 16 and record.decisions_uav + record.decisions_ugv == 16
    assert all(step.applied == "WAIT" and step.fallback_reason for step in sink.steps)
    reasons = {step.fallback_reason.split(" ")[0] for step in sink.steps}
    assert reasons == {"CONFIRM", "no", "waypoint"}  # illegal action, missing action, bad waypoint


def test_confirm_without_stop_observe_is_a_false_confirm(world) -> None:
    record = run(world, "easy000", Scripted(lambda obs: action_for(obs, "CONFIRM" if obs.role == "ugv" else "WAIT")))
    assert record.termination == "false_confirm" and not record.success and record.n_confirm == 1
    assert "no fresh STOP_OBSERVE" in (record.confirm_rejection or "") and record.error is None


def test_reject_unfreezes_the_uav_and_records_the_candidate(world) -> None:
    state = {"annotated": False}

    def choose(obs: Observation) -> Action:
        if obs.role == "uav":
            if not state["annotated"]:
                state["annotated"] = True
                return action_for(obs, "ANNOTATE_CANDIDATE", cell="A1")
            return action_for(obs, "NO_RELIABLE_CANDIDATE")
        active = [c for c in obs.coordination.candidates if c.status in ("pending", "arrived")]
        if active:
            return action_for(obs, "REJECT", candidate_id=active[0].candidate_id)
        return action_for(obs, "WAIT")

    sink = Recorder()
    record = run(world, "mid001", Scripted(choose), sink, budget=24)
    assert [c.status for c in record.candidates] == ["rejected"]
    annotate = next(s for s in sink.steps if s.applied == "ANNOTATE_CANDIDATE")
    reject = next(s for s in sink.steps if s.applied == "REJECT")
    uav_after = [s for s in sink.steps if s.role == "uav" and s.episode_step > annotate.episode_step]
    # frozen: no UAV decision between the annotation and the rejection
    assert uav_after and all(s.episode_step > reject.episode_step for s in uav_after)


def test_asset_hash_mismatch_is_refused(world) -> None:
    from agos.world.towns.asset import AssetMismatch, town_for

    spec: EpisodeSpec = world[2]["easy000"]
    with pytest.raises(AssetMismatch, match="grid-s7"):
        town_for(spec.town.generator, spec.town.seed, "0" * 64)


class Everything(NullSink):
    """Keeps every message the runner reports."""

    def __init__(self) -> None:
        self.messages: list = []

    def step(self, event: StepEvent) -> None:
        self.messages.append(event)

    def coordination(self, truth, views) -> None:
        self.messages += [truth, *views.values()]

    def message(self, message) -> None:
        self.messages.append(message)


def test_every_message_is_written_with_its_declared_types(world) -> None:
    """Structs are not converted when built, so the world must build them with the declared types
    (a float, not an int or a numpy scalar, in a ``float`` field): then what it sends is exactly what
    the receiver's struct writes again, and payload sizes (the link ledger's ``size_bytes``) do not
    depend on how a value was computed."""
    from agos.runtime.codec import decode, encode
    from agos.runtime.links import load_profile


    town, scene, episodes = world
    sink, seen = Everything(), []
    with Env(episodes["mid000"], EpisodeConfig(look="flat", comm=load_profile("lossy")), run_id="t", worker_id="w",
             scene=scene, town=town, sink=sink) as env:
        record = env.play({r: make_policy("heuristic", r) for r in ("uav", "ugv")}, seen=seen)
    assert record.ledger and sink.messages and seen
    for message in [*seen, *sink.messages, record]:
        payload = encode(message)
        assert encode(decode(payload)) == payload, type(message).__name__


@pytest.mark.slow
def test_the_map_shows_the_teammate_where_the_link_reported_it(world) -> None:
    """M carries no more than the link: each role's map has its own marker where it is and its
    teammate's at the pose in that role's coordination view (none before the first report)."""
    from agos.runtime.codec import decode_image
    from agos.runtime.links import load_profile
    from agos.world.towns.topdown import region_map

    town, scene, episodes = world
    config = EpisodeConfig(look="flat", comm=load_profile("outage"))  # nothing gets through after 20 s
    asked: list[Observation] = []
    with Env(episodes["mid000"], config, run_id="t", worker_id="w", scene=scene, town=town) as env:
        env.play({r: make_policy("heuristic", r) for r in ("uav", "ugv")}, seen=asked)  # a long one
    seen = [(obs, next(f.data for f in obs.images if f.kind == "map")) for obs in asked]
    late = [(obs, png) for obs, png in seen if obs.sim_time_s > 60.0]
    assert len(late) > 5
    for obs, png in seen[:6] + late[:6]:
        image = decode_image(png)
        mate = obs.coordination.poses.get("ugv" if obs.role == "uav" else "uav")
        mate_xy = None if mate is None else mate.position_world_m[:2]
        own_xy = obs.pose.position_world_m[:2]
        uav_xy, ugv_xy = (own_xy, mate_xy) if obs.role == "uav" else (mate_xy, own_xy)
        ugv_yaw = (obs.pose.yaw_rad if obs.role == "ugv" else (0.0 if mate is None else mate.yaw_rad))
        expected, _ = region_map(town.layout, obs.region_world_m, size_px=image.shape[1], uav_xy=uav_xy,
                                 ugv_xy=ugv_xy, ugv_yaw_rad=ugv_yaw)
        assert (expected == image).all(), (obs.role, obs.decision_index)
