"""Vehicle cues in episodes (issue 22, items 1, 5, 8): attributes in VehicleSpec, the flat look's
refusal, the rich sampler's look-alike kinds and its table of separable pairs, reference views that
show the attributes, today's flat episodes unchanged, and bench/bench_cues.py --quick; the table's
noise and the tolerance of bench/bench_cues.py --check (issue 29, item 9)."""

from __future__ import annotations

import hashlib
import importlib.util
import math
import re
import subprocess
import sys
from pathlib import Path

import msgspec
import numpy as np
import pytest

from agos import Env
from agos.runtime.codec import decode, decode_as, decode_image, encode, from_json, to_json
from agos.runtime.episode_config import CameraConfig, EpisodeConfig
from agos.runtime.schemas import EpisodeSpec, JobGrant, TownRef, VehicleSpec
from agos.world.episodes import sampling
from agos.world.episodes.lookalikes import (
    ATTRIBUTES,
    CUE_CHECK_PCT,
    CUE_GROUND_PCT,
    CUE_GROUND_SD,
    MIN_CUE_PCT,
    PLAIN,
    pairs,
    separable,
)
from agos.world.episodes.sampling import sample_episode
from agos.world.sim import sensors
from agos.world.sim.episode_vehicles import LookMismatch, add_episode_vehicles, check_look
from agos.world.sim.scene import Scene, pb
from agos.world.towns.asset import open_town
from agos.world.towns.catalog import NEAR_COLOURS, VIVID_COLOURS, colour_rgb
from agos.world.towns.look.vehicles import ATTRIBUTE_BODY_TYPES, RICH_BODY_TYPES, ROOF_COLOUR, contrast_colour

ROOT = Path(__file__).resolve().parents[1]
OLD_LINE = (
    '{"type":"episode_spec","v":1,"episode_id":"grid-s7-hard-000-v1","town":{"generator":"grid","seed":7,'
    '"town_id":"grid-s7"},"asset_sha256":"' + "ab" * 32 + '","difficulty":"hard","region_world_m":[0.0,0.0,300.0,'
    '300.0],"target":{"model":"suv","colour":"red","position_world_m":[10.5,20.25,0.0],"yaw_rad":1.570796},'
    '"distractors":[{"model":"suv","colour":"maroon","position_world_m":[60.0,20.25,0.0],"yaw_rad":0.0},'
    '{"model":"van","colour":"red","position_world_m":[120.0,20.25,0.0],"yaw_rad":3.141593}],'
    '"uav_start_waypoint":"U1_1","ugv_start_waypoint":"R7","active_uav_waypoints":["U1_1","U1_2"],'
    '"decision_budget":80,"seed":3}')
"""An episode line as written before vehicles had attributes."""
FLAT_EPISODES_SHA = {"grid-s7": "f8ebf07509183212"}
"""sha256 (16 hex) of sample_episode(grid-s7, easy and hard 0-2, seed 11) in the flat look, asset
hash blanked (the town's asset format sets it): the flat look's draws do not change with the rich
vocabulary. Re-pinned twice since: when procedural sidewalks reached round junction corners and the
buildings beside them moved (c9383c54029e5d58 before), and when parked traffic took the survey's
paints and 60% of the kerbs, targets the survey's shares among vivid paints and the UGV a start beyond
the CONFIRM distance (issue 29; 096ee75e580ecef0 before)."""


@pytest.fixture(scope="module")
def town():
    return open_town("grid-s7")


@pytest.fixture(scope="module")
def rich(town):
    with Scene(town.layout, look="rich") as scene:
        yield scene


@pytest.fixture(scope="module")
def flat(town):
    with Scene(town.layout, look="flat") as scene:
        yield scene


def _spec(target: VehicleSpec, distractors: tuple[VehicleSpec, ...] = ()) -> EpisodeSpec:
    return EpisodeSpec(episode_id="t-hard-000-rich-v1", town=TownRef(generator="grid", seed=7, town_id="grid-s7"),
                       asset_sha256="cd" * 32, difficulty="hard", region_world_m=(0.0, 0.0, 300.0, 300.0),
                       target=target, distractors=list(distractors), uav_start_waypoint="U1_1",
                       ugv_start_waypoint="R7", active_uav_waypoints=["U1_1"], seed=1)


def _car(model: str = "sedan", colour: str = "blue", xy: tuple[float, float] = (0.0, 0.0), **attrs) -> VehicleSpec:
    return VehicleSpec(model=model, colour=colour, position_world_m=(xy[0], xy[1], 0.0), yaw_rad=0.0, **attrs)


# -- the wire format ---------------------------------------------------------------------------------
def test_vehicle_spec_round_trips_with_and_without_attributes():
    plain, marked = _car(), _car(roof="white", rack=True, stripe="black")
    for v in (plain, marked):
        assert decode_as(encode(v), VehicleSpec) == v
        assert from_json(to_json(v), VehicleSpec) == v
    assert to_json(plain) == b'{"model":"sedan","colour":"blue","position_world_m":[0.0,0.0,0.0],"yaw_rad":0.0}'
    assert b'"roof":"white","rack":true,"stripe":"black"' in to_json(marked)
    assert to_json(_car(rack=False)) == to_json(plain)  # defaults are never written


def test_old_episode_lines_decode_and_encode_to_the_same_bytes():
    spec = from_json(OLD_LINE, EpisodeSpec)
    assert (spec.target.roof, spec.target.rack, spec.target.stripe) == (None, False, None)
    assert to_json(spec).decode() == OLD_LINE
    grant = encode(JobGrant(episode=spec))
    assert encode(decode(grant)) == grant
    with pytest.raises(msgspec.ValidationError):  # still strict: a misspelt attribute is refused
        msgspec.json.decode(OLD_LINE.replace('"yaw_rad":1.570796', '"yaw_rad":1.570796,"rooof":"white"'),
                            type=EpisodeSpec)


# -- the flat look refuses what it cannot draw --------------------------------------------------------
def test_flat_look_refuses_attributes_and_buses_and_the_rich_look_draws_them():
    check_look(_spec(_car(), (_car(colour="navy"),)), "flat")
    for spec in (_spec(_car(rack=True)), _spec(_car(), (_car(stripe="white"),)), _spec(_car(model="bus"))):
        with pytest.raises(LookMismatch, match=r"t-hard-000-rich-v1: its (target|look-alike) needs look = \"rich\""):
            check_look(spec, "flat")
        check_look(spec, "rich")


# -- the rich sampler -----------------------------------------------------------------------------------
def _cue(target: VehicleSpec, d: VehicleSpec) -> str:
    """The one cue a look-alike differs in (fails on none or several)."""
    fields = ("model", "colour", "roof", "rack", "stripe")
    differ = [f for f in fields if getattr(target, f) != getattr(d, f)]
    assert len(differ) == 1, f"{d} differs from {target} in {differ}"
    return {"model": "type", "colour": "paint"}.get(differ[0], "attribute")


def test_rich_lookalikes_differ_in_one_cue_of_every_kind_and_only_in_separable_pairs(town):
    slots = [s for s in town.layout.slots if s.slot_id not in town.layout.occupied_slots and not s.covered]
    kinds: dict[str, int] = {}
    with_attrs, buses, mixed = 0, 0, 0
    for seed in range(150):
        rng = np.random.default_rng(seed)
        order = [slots[int(i)] for i in rng.permutation(len(slots))[:60]]
        got = sampling._rich_vehicles(rng, "hard", order, town.layout)
        assert got is not None
        target, distractors = got
        if target.roof is not None or target.rack or target.stripe is not None:
            with_attrs += 1
            assert target.model in ATTRIBUTE_BODY_TYPES
        buses += target.model == "bus"
        assert target.model in RICH_BODY_TYPES and target.colour in VIVID_COLOURS and 2 <= len(distractors) <= 3
        seen = []
        for d in distractors:
            kind = _cue(target, d)
            seen.append(kind)
            if kind == "type":
                assert separable("type", target.model, d.model, look="rich")
            elif kind == "paint":
                assert d.colour in NEAR_COLOURS[target.colour] and separable("paint", target.colour, d.colour, look="rich")
            else:
                name = next(a for a in ATTRIBUTES if getattr(target, a) != getattr(d, a))
                assert separable("attribute", PLAIN, name, look="rich")
                added = {"roof": ROOF_COLOUR, "rack": True, "stripe": contrast_colour(target.colour)}[name]
                assert {getattr(d, name), getattr(target, name)} <= {None, False, added}
                assert d.model in ATTRIBUTE_BODY_TYPES
            kinds[kind] = kinds.get(kind, 0) + 1
        mixed += len(set(seen)) >= 2  # the kinds take turns
    assert set(kinds) == {"type", "paint", "attribute"}, kinds
    assert mixed > 0.8 * 150
    assert 20 < with_attrs < 70 and buses > 0  # half the cars (4 types of 7) carry one attribute


def test_the_table_holds_every_rich_pair_and_the_sampler_uses_only_those_at_the_floor():
    measured = {key for key in CUE_GROUND_PCT}
    every = {(kind, a, b) for kind, kind_pairs in pairs("rich").items() for a, b in kind_pairs}
    assert measured == every, "re-run bench/bench_cues.py and paste its table"
    for (kind, a, b), pct in CUE_GROUND_PCT.items():
        assert separable(kind, a, b, look="rich") == (pct >= MIN_CUE_PCT)
        assert separable(kind, b, a, look="rich") == (pct >= MIN_CUE_PCT)
        assert separable(kind, a, b, look="flat")  # the flat look keeps every pair


def test_the_table_carries_its_noise_and_the_checks_reference():
    every = {(kind, a, b) for kind, kind_pairs in pairs("rich").items() for a, b in kind_pairs}
    assert set(CUE_GROUND_SD) == every and set(CUE_CHECK_PCT) == every, "paste all three tables of --repeats"
    for key, pct in CUE_GROUND_PCT.items():
        mean, spread = CUE_CHECK_PCT[key]
        assert 0.0 <= CUE_GROUND_SD[key] < 10.0 and 0.0 <= spread < 15.0
        assert mean <= pct + 3 * max(spread, 1.0), key  # fewer crops train a weaker classifier, never a better one


def _bench(name: str):
    """A bench script as a module (registered first: its dataclasses look their module up)."""
    if name not in sys.modules:
        bench_dir = ROOT / "bench"
        if str(bench_dir) not in sys.path:
            sys.path.insert(0, str(bench_dir))  # its sibling modules (figures), as when run as a script
        spec = importlib.util.spec_from_file_location(name, bench_dir / f"{name}.py")
        assert spec is not None and spec.loader is not None
        sys.modules[name] = module = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(module)
    return sys.modules[name]


def test_the_cue_check_fails_a_pair_only_beyond_its_noise_and_gates_make_bench():
    bench = _bench("bench_cues")
    z_max, floor = bench.CHECK_Z, bench.CHECK_MIN_SD
    assert bench.judge(90.0, (90.0, 2.0)) == (0.0, False)
    assert not bench.judge(90.0 - 0.99 * z_max * 2.0, (90.0, 2.0))[1]
    z, out = bench.judge(90.0 - 1.01 * z_max * 2.0, (90.0, 2.0))
    assert out and z < -z_max
    assert bench.judge(90.0 + 1.01 * z_max * 2.0, (90.0, 2.0))[1]  # a pair that got easier is out too
    assert not bench.judge(100.0 - 0.99 * z_max * floor, (100.0, 0.0))[1]  # an sd of 0 is taken as the floor
    assert bench.judge(100.0 - 1.01 * z_max * floor, (100.0, 0.0))[1]
    for reference in CUE_CHECK_PCT.values():
        assert not bench.judge(reference[0], reference)[1]
    cues = {b.name: b for b in _bench("run_all").benches()}["cues"]
    assert cues.script == "bench_cues.py" and cues.args == ["--check"] and cues.gate


def test_a_bus_parks_only_where_its_neighbours_are_free(town):
    long_ok = sampling.long_slots(town.layout)
    taken = {s.slot_id: s for s in town.layout.slots if s.slot_id in town.layout.occupied_slots}
    assert 0 < len(long_ok) < len(town.layout.slots)
    for slot in town.layout.slots:
        near = any(t.lane_id == slot.lane_id and math.dist(t.position_world_m, slot.position_world_m) < 9.5
                   for t in taken.values())
        assert (slot.slot_id in long_ok) == (not near)


def test_rich_episodes_are_sampled_solvable_and_named_rich(town, rich):
    ep = sample_episode(town, rich, "hard", 0, seed=4, stream=2)
    assert ep.episode_id == "grid-s7-hard-000-rich-v1"
    assert 2 <= len(ep.distractors) <= 3
    assert to_json(sample_episode(town, rich, "hard", 0, seed=4, stream=2)) == to_json(ep)
    with pytest.raises(LookMismatch):
        check_look(msgspec.structs.replace(ep, target=_car(stripe="white")), "flat")


def test_flat_look_gives_todays_episodes(town, flat):
    h = hashlib.sha256()
    for difficulty, stream in (("easy", 0), ("hard", 2)):
        for i in range(3):
            ep = sample_episode(town, flat, difficulty, i, seed=11, stream=stream)
            assert "rich" not in ep.episode_id
            h.update(to_json(msgspec.structs.replace(ep, asset_sha256="", v=1)))  # the episodes, whatever the wire version
    assert h.hexdigest()[:16] == FLAT_EPISODES_SHA["grid-s7"]


def test_a_flat_world_refuses_a_rich_episode_before_adding_anything(town, flat):
    ep = sample_episode(town, flat, "easy", 0, seed=11, stream=0)
    rich_ep = msgspec.structs.replace(ep, target=msgspec.structs.replace(ep.target, model="sedan", rack=True))
    bodies = pb.getNumBodies(physicsClientId=flat.client)
    with Env(rich_ep, EpisodeConfig(look="flat"), run_id="r", worker_id="w", scene=flat, town=town) as env, \
            pytest.raises(LookMismatch, match="its target needs look"):
        env.reset()
    assert pb.getNumBodies(physicsClientId=flat.client) == bodies


# -- what agents are shown ------------------------------------------------------------------------------
def test_reference_views_show_the_attributes(rich):
    cam = CameraConfig()
    roof_rgb = np.array(colour_rgb("white")) * 255
    counts = {}
    for name, target in (("plain", _car()), ("roof", _car(roof="white")), ("rack", _car(rack=True))):
        uid, = add_episode_vehicles(rich, _spec(target))
        try:
            frames = {f.name: decode_image(f.data) for f in sensors.reference_views(
                rich, uid, target.position_world_m, target.yaw_rad, cam)}
        finally:
            rich.remove(uid)
        top = frames["ref_top"]
        near_roof = (np.abs(top[:, :, :3].astype(float) - roof_rgb * 0.85).max(axis=2) < 60) & (top[:, :, 3] > 0)
        side = frames["ref_side"][:, :, 3] > 0
        counts[name] = (int(np.count_nonzero(near_roof)), int(np.flatnonzero(side.any(axis=1))[0]))
    assert counts["roof"][0] > 150 and counts["plain"][0] < 10, counts  # roof-coloured pixels from above
    assert counts["rack"][1] < counts["plain"][1] - 3, counts  # the cargo box raises the side silhouette


@pytest.mark.e2e  # the bench script as a user runs it, so it cannot rot
def test_bench_cues_quick_runs():
    out = subprocess.run([sys.executable, "bench/bench_cues.py", "--quick"], cwd=ROOT, capture_output=True,
                         text=True, timeout=120)
    assert out.returncode == 0, out.stderr[-2000:]
    lines = re.findall(r"^cue (flat|rich) (ground|air) (\S+) vs (\S+): (\d+\.\d)%$", out.stdout, re.M)
    assert {(look, view) for look, view, *_ in lines} == {(lk, v) for lk in ("flat", "rich") for v in ("ground", "air")}
    assert {(a, b) for *_, a, b, _ in lines} == {("sedan", "suv"), ("maroon", "red"), (PLAIN, "roof")}
    assert "CUE_GROUND_PCT" in out.stdout
