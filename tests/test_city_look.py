"""The rich look's city (world/towns/look/city.py and the modules it gathers): deterministic textures,
the asset hash covering the dressing, and masks, depth, rays, shadows and the CONFIRM checker
keeping their meaning in a textured town. The flat look's byte-identity is pinned in
tests/test_vehicle_meshes.py::test_default_look_renders_as_before."""

from __future__ import annotations

import dataclasses
import hashlib
import math

import numpy as np
import pytest

from agos.runtime.camera import pixel_to_ground
from agos.runtime.codec import decode_image
from agos.runtime.episode_config import CameraConfig, ConfirmConfig
from agos.world.sim import sensors
from agos.world.sim.confirm import check_confirm
from agos.world.sim.evidence import ground_evidence, nearest_verifying_anchor, target_points
from agos.world.sim.scene import SEM_BUILDING, SEM_MARKING, SEM_ROAD, SEM_SIDEWALK, SEM_VEHICLE, Scene, pb
from agos.world.towns.asset import AssetError, encode_document, open_town, town_document, town_from_document
from agos.world.towns.dressing import DRESSING_VERSION, Facade
from agos.world.towns.look.shadows import clip_convex
from agos.world.towns.look.texmesh import convex_decomposition, signed_area
from agos.world.towns.look.textures import GENERATORS, texture, texture_file

CAM = CameraConfig()


@pytest.fixture(scope="module")
def town():
    return open_town("grid-s7")


@pytest.fixture(scope="module")
def rich(town, tmp_path_factory):
    with pytest.MonkeyPatch.context() as mp:  # generated textures go to a cache of this test's own
        mp.setenv("AGOS_ASSET_CACHE", str(tmp_path_factory.mktemp("assets")))
        with Scene(town.layout, look="rich") as scene:
            yield scene


# ----- textures and the frozen dressing ---------------------------------------------------------------
def test_textures_are_deterministic_and_seeded(tmp_path):
    for name in GENERATORS:
        a, b = texture(name, 7), texture(name, 7)
        assert a.dtype == np.uint8 and a.ndim == 3 and a.shape[2] == 3, name
        assert a.tobytes() == b.tobytes(), name
        assert texture(name, 8).tobytes() != a.tobytes(), name
    first = texture_file.__wrapped__("brick_red", 7, tmp_path)
    again = texture_file.__wrapped__("brick_red", 7, tmp_path)
    other = texture_file.__wrapped__("brick_red", 8, tmp_path)
    assert first == again and first.exists() and other != first  # named by content


def test_asset_hash_covers_the_dressing(town):
    layout, dressing = town.layout, town.layout.dressing
    assert dressing is not None and dressing.version == DRESSING_VERSION
    assert len(dressing.facades) == len(layout.buildings) and dressing.lamps and dressing.street_trees
    again = town_from_document(town.document)
    assert again.layout.dressing == dressing and again.sha256 == town.sha256

    def document_with(**changes) -> bytes:
        changed = dataclasses.replace(layout, dressing=dataclasses.replace(dressing, **changes))
        return encode_document(town_document(changed, town.roads, town.uav_grid))

    def sha_with(**changes) -> str:
        return hashlib.sha256(document_with(**changes)).hexdigest()

    first = dressing.facades[0]
    other_style = "glass_blue" if first.style != "glass_blue" else "brick_red"
    assert sha_with(facades=(Facade(other_style, first.ground), *dressing.facades[1:])) != town.sha256
    assert sha_with(lamps=dressing.lamps[1:]) != town.sha256
    assert sha_with(texture_seed=dressing.texture_seed + 1) != town.sha256
    assert sha_with(version=dressing.version + 1) != town.sha256
    assert sha_with() == town.sha256
    with pytest.raises(AssetError, match="dressing version"):  # this agos cannot draw another version's look
        town_from_document(document_with(version=dressing.version + 1))


def test_the_same_asset_renders_the_same_city(rich, town):
    x, y, _ = _road_point(town)
    with Scene(town_from_document(town.document).layout, look="rich") as again:
        shots = [sensors.nadir(s, (x, y), 80.0, CAM).render for s in (rich, again)]
        views = [sensors.ground_view(s, "front", (x, y), 0.3, CAM).render for s in (rich, again)]
        for a, b in (shots, views):
            assert a.rgb.tobytes() == b.rgb.tobytes() and a.depth_m.tobytes() == b.depth_m.tobytes()


def test_geometry_helpers():
    square = np.array([[0.0, 0.0], [2.0, 0.0], [2.0, 2.0], [0.0, 2.0]])
    part = np.asarray(clip_convex([(1.0, 1.0), (3.0, 1.0), (3.0, 3.0), (1.0, 3.0)], square))
    assert abs(signed_area(part) - 1.0) < 1e-9
    ell = np.array([[0, 0], [4, 0], [4, 1], [1, 1], [1, 4], [0, 4]], float)
    pieces = convex_decomposition(ell)
    assert abs(sum(signed_area(p) for p in pieces) - 7.0) < 1e-9 and len(pieces) == 2


# ----- channels keep their meaning --------------------------------------------------------------------
def _road_point(town) -> tuple[float, float, float]:
    slot = next(s for s in town.layout.slots if not s.plaza and s.slot_id not in town.layout.occupied_slots)
    return (*slot.position_world_m, slot.yaw_rad)


def test_vehicle_pixels_carry_its_id_and_shadows_are_road(rich, town):
    x, y, yaw = _road_point(town)
    before = pb.getNumBodies(physicsClientId=rich.client)
    shadow_uid = rich._shadow_proxy  # every vehicle's drawn shadow shows this id, of class road

    def shadow_px() -> int:  # parked cars nearby may cast some already
        return int(np.count_nonzero(sensors.nadir(rich, (x, y), 30.0, CAM).render.instance == shadow_uid))

    parked_shadow_px = shadow_px()
    uid = rich.add_vehicle("suv", "red", (x, y, 0.0), yaw)
    try:
        shot = sensors.nadir(rich, (x, y), 30.0, CAM)
        inst = shot.render.instance
        sem = rich.semantic(inst)
        assert np.count_nonzero(inst == uid) > 500
        assert np.all(sem[inst == uid] == SEM_VEHICLE)
        assert np.count_nonzero(inst == shadow_uid) > parked_shadow_px + 50  # the drawn shadow is seen ...
        assert np.all(sem[inst == shadow_uid] == SEM_ROAD)  # ... as road, not as a vehicle
        vehicle_ids = {u for u, c in rich._semantic.items() if c == SEM_VEHICLE}
        assert np.all(np.isin(inst[sem == SEM_MARKING], list(vehicle_ids), invert=True))
        assert {SEM_ROAD, SEM_MARKING, SEM_SIDEWALK} <= set(np.unique(sem).tolist())
        # E2A: the vehicle's pixel centroid projects onto the ground at the vehicle
        v, u = np.argwhere(inst == uid).mean(axis=0)
        gx, gy = pixel_to_ground(float(u), float(v), shot.world_from_camera, shot.intrinsics)
        assert math.dist((gx, gy), (x, y)) < 1.0
    finally:
        rich.remove(uid)
    assert pb.getNumBodies(physicsClientId=rich.client) == before
    assert shadow_px() == parked_shadow_px  # gone with it


def test_depth_is_metric_on_road_and_roof(rich, town):
    x, y, _ = _road_point(town)
    shot = sensors.nadir(rich, (x, y), 80.0, CAM)
    c = CAM.nadir_px // 2
    assert rich.semantic(shot.render.instance)[c, c] == SEM_ROAD
    assert abs(float(shot.render.depth_m[c, c]) - (80.013 - 0.02)) < 0.03
    b = max(town.layout.buildings, key=lambda b: b.size_m[0] * b.size_m[1])
    roof = sensors.nadir(rich, b.center_world_m, 80.0, CAM)
    assert rich.semantic(roof.render.instance)[c, c] == SEM_BUILDING
    assert abs(float(roof.render.depth_m[c, c]) - (80.013 - b.size_m[2])) < 0.05


def test_rays_hit_buildings_not_decorations(rich, town):
    b = max(town.layout.buildings, key=lambda b: b.size_m[0])
    cx, cy = b.center_world_m
    a, z = np.array([cx - b.size_m[0], cy, 1.7]), np.array([cx + b.size_m[0], cy, 1.7])
    assert not rich.clear_line(a, z)
    lamp = rich._city.dressing.lamps[0]
    tree = rich._city.dressing.street_trees[0]
    for px, py in (lamp.position_world_m, tree.position_world_m):  # through a lamp post, a street tree
        assert rich.clear_line(np.array([px - 3.0, py, 2.0]), np.array([px + 3.0, py, 2.0]))


def test_vehicles_in_building_shadow_are_darker_and_the_studio_lights_them(rich, town):
    city = rich._city
    slots = [s for s in town.layout.slots if not s.plaza and s.slot_id not in town.layout.occupied_slots]
    shaded = next(s for s in slots if city.in_building_shadow(s.position_world_m))
    sunny = next(s for s in slots if not city.in_building_shadow(s.position_world_m))
    means = {}
    for name, slot in (("shaded", shaded), ("sunny", sunny)):
        x, y = slot.position_world_m
        uid = rich.add_vehicle("sedan", "white", (x, y, 0.0), slot.yaw_rad)
        shot = sensors.nadir(rich, (x, y), 30.0, CAM)
        means[name] = float(shot.render.rgb[shot.render.instance == uid].mean())
        refs = sensors.reference_views(rich, uid, (x, y, 0.0), slot.yaw_rad, CAM)
        rgba = decode_image(refs[0].data)
        means[name + "_ref"] = float(rgba[rgba[:, :, 3] > 0, :3].mean())
        assert rich._extras[uid].shaded == (name == "shaded")  # back from the studio, shaded again
        rich.remove(uid)
    assert means["shaded"] < 0.8 * means["sunny"]
    assert abs(means["shaded_ref"] - means["sunny_ref"]) < 1.0  # in the studio both stand in the sun


def test_confirm_checker_accepts_in_the_rich_town(rich, town):
    from agos.world.episodes.sampling import sample_episode

    with Scene(town.layout, look="flat") as flat:
        spec = sample_episode(town, flat, "easy", 0, seed=3)
    t = spec.target
    uid = rich.add_vehicle(t.model, t.colour, t.position_world_m, t.yaw_rad)
    try:
        ids, xy = town.roads.anchor_array()
        start = int(ids[np.argmin(np.hypot(xy[:, 0] - t.position_world_m[0], xy[:, 1] - t.position_world_m[1]))])
        found = nearest_verifying_anchor(rich, town, start, town.roads.heading_at(start), uid, t.position_world_m,
                                         t.yaw_rad, ConfirmConfig(), CAM)
        assert found is not None  # an anchor where the checker, fed rich renders, accepts
        node, _ = found
        evidence = ground_evidence(rich, town, node, uid, target_points(t.position_world_m, t.yaw_rad),
                                   t.position_world_m[:2], CAM)
        assert evidence.max_target_pixels > 0 and evidence.line_of_sight
        # a checker fed the same renders but the target's shadow would refuse: shadows are not the target
        shadow = rich._shadow_proxy
        shot = sensors.nadir(rich, t.position_world_m[:2], 40.0, CAM)
        assert sensors.target_pixels(shot, shadow) > 0 and sensors.target_pixels(shot, uid) > 0
        assert check_confirm(dataclasses.replace(evidence, max_target_pixels=0), ConfirmConfig())
    finally:
        rich.remove(uid)
