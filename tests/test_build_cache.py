"""The build cache (world/towns/buildcache.py): a town and a rich city read back from it are the ones
built fresh, byte for byte, down to the rendered pixels; a damaged entry is built again, never
trusted; the key follows the code."""

from __future__ import annotations

import os
import pickle
import shutil

import numpy as np
import pytest

from agos.runtime.episode_config import CameraConfig
from agos.world.sim import sensors
from agos.world.sim.scene import Scene
from agos.world.towns import asset, buildcache
from agos.world.towns.asset import build_town, generate_town
from agos.world.towns.buildcache import code_key, entry_path, read_entry, source_key, write_entry
from agos.world.towns.look import city as city_module
from agos.world.towns.look.city import City, build_city, stored_city
from agos.world.towns.look.textures import texture_file

TOWN_ENTRY = "town-grid-s7.msgpack"


@pytest.fixture(scope="module")
def fresh():
    """grid-s7 as generated here, without any cache."""
    return generate_town("grid", 7)


@pytest.fixture
def cache(tmp_path, monkeypatch):
    root = tmp_path / "assets"
    monkeypatch.setenv("AGOS_ASSET_CACHE", str(root))
    return root


def _not_built(*args, **kwargs):
    raise AssertionError("built although the cache holds it")


def test_a_town_from_the_cache_is_the_town_built_fresh(cache, fresh, monkeypatch):
    first = build_town.__wrapped__("grid", 7)  # builds and stores
    assert read_entry(entry_path(cache, TOWN_ENTRY)) == fresh.document
    monkeypatch.setattr(asset, "generate_town", _not_built)
    again = build_town.__wrapped__("grid", 7)
    for town in (first, again):
        assert town.document == fresh.document and town.sha256 == fresh.sha256
        assert pickle.dumps(town) == pickle.dumps(fresh)  # layout, graphs, grid: every field


def _city_fields(city: City) -> list:
    parts = [(p.material, p.semantic, p.rgb, type(p.rgb), p.specular, p.shadow,
              *[(a.dtype.str, a.shape, a.tobytes()) for a in (p.mesh.vertices, p.mesh.indices, p.mesh.normals, p.mesh.uvs)])
             for p in city.parts]
    return [parts, city.texture_of, city.texture_files, city.dressing, city.triangles, city.vehicle_shade,
            city.vehicle_shadow_rgb, [(p.dtype.str, p.shape, p.tobytes()) for p in city.building_shadows.polygons],
            city.building_shadows.grid]


def test_a_city_from_the_cache_is_the_city_built_fresh(cache, fresh, monkeypatch):
    textures = cache / "textures"
    expected = _city_fields(build_city(fresh.layout, texture_root=textures))
    first = stored_city(fresh.layout, texture_root=textures, cache_root=cache)  # builds and stores
    monkeypatch.setattr(city_module, "build_city", _not_built)
    again = stored_city(fresh.layout, texture_root=textures, cache_root=cache)
    assert _city_fields(first) == expected
    assert _city_fields(again) == expected


@pytest.mark.slow
def test_a_scene_from_the_cache_renders_the_same_pixels(cache, fresh, monkeypatch):
    cam = CameraConfig()
    slot = next(s for s in fresh.layout.slots if not s.plaza)
    x, y = slot.position_world_m
    with Scene(fresh.layout, look="rich") as built:  # builds the city and stores it
        monkeypatch.setattr(city_module, "build_city", _not_built)
        with Scene(fresh.layout, look="rich") as cached:
            for a, b in ((sensors.nadir(s, (x, y), 60.0, cam).render for s in (built, cached)),
                         (sensors.ground_view(s, "front", (x, y), 0.3, cam).render for s in (built, cached))):
                assert a.rgb.tobytes() == b.rgb.tobytes()
                assert a.depth_m.tobytes() == b.depth_m.tobytes() and a.instance.tobytes() == b.instance.tobytes()
                assert len(np.unique(a.instance)) > 3  # a view of the town, not of the sky


@pytest.mark.slow
def test_a_damaged_entry_is_built_again(cache, fresh):
    entry = entry_path(cache, TOWN_ENTRY)
    assert entry is not None
    build_town.__wrapped__("grid", 7)
    sealed = entry.read_bytes()
    flipped = bytearray(sealed)
    flipped[len(sealed) // 2] ^= 1
    for damaged in (bytes(flipped), b"", sealed[:10], sealed[: len(sealed) // 2]):
        entry.write_bytes(damaged)
        assert read_entry(entry) is None
    assert build_town.__wrapped__("grid", 7).document == fresh.document
    assert entry.read_bytes() == sealed  # stored again
    write_entry(entry, b"sealed, but not a town")
    assert build_town.__wrapped__("grid", 7).document == fresh.document
    assert read_entry(entry) == fresh.document
    assert not [p for p in entry.parent.iterdir() if p.name.endswith(".tmp")]

    textures = cache / "textures"
    expected = _city_fields(stored_city(fresh.layout, texture_root=textures, cache_root=cache))
    (city_entry,) = entry.parent.glob("city-*.npz")
    write_entry(city_entry, b"sealed, but not a city")
    assert _city_fields(stored_city(fresh.layout, texture_root=textures, cache_root=cache)) == expected
    assert read_entry(city_entry) != b"sealed, but not a city"
    for path in textures.iterdir():  # textures gone from the cache (as seen by a new process): built again
        path.unlink()
    texture_file.cache_clear()
    again = stored_city(fresh.layout, texture_root=textures, cache_root=cache)
    assert _city_fields(again) == expected
    assert all(path.is_file() for path in again.texture_files.values())


def test_the_key_follows_the_sources_and_old_keys_are_pruned(tmp_path, cache):
    copy = tmp_path / "towns"
    shutil.copytree(buildcache._SOURCES, copy, ignore=shutil.ignore_patterns("__pycache__"))
    assert source_key(copy) == code_key()
    city_py = copy / "look" / "city.py"
    city_py.write_text(city_py.read_text() + "# a comment\n")
    assert source_key(copy) != code_key()

    build = cache / "build"
    for k in range(6):
        (build / f"old{k}").mkdir(parents=True)
        os.utime(build / f"old{k}", (1000 + k, 1000 + k))
    entry = entry_path(cache, "probe")
    assert entry is not None
    write_entry(entry, b"x")
    assert sorted(p.name for p in build.iterdir()) == sorted([entry.parent.name, "old5", "old4", "old3"])
    assert read_entry(entry) == b"x"
