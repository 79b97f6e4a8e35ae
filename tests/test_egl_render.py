"""The EGL renderer draws the scenes TinyRenderer draws (issue 39, item 1).

PyBullet's EGL plugin reads meshes only from files (world/sim/scene.py writes each mesh once as an
OBJ named by its content) and has a 16-bit depth buffer (world/sim/scene.py orders the town's
stacked layers for it). Here, on whatever EGL this machine has (Mesa's llvmpipe on the development
VM and in CI, no GPU), the same scene renders with both renderers with the same objects: instance
and semantic ids agree on at least 99 % of the pixels away from object edges, the median depth
differs by at most 1 %, textures keep their orientation and colours their tint; shading may differ.
Where EGL cannot render at all (no libEGL, no device, no driver), every test here skips and says why.

TinyRenderer's pixels are pinned elsewhere (tests/test_vehicle_meshes.py FLAT_RENDER_SHA,
tests/test_city_look.py); nothing here changes them.
"""

from __future__ import annotations

import re

import cv2
import numpy as np
import pytest

from agos import Env, episode_config
from agos.agents.registry import make_policy
from agos.runtime.episode_config import CameraConfig
from agos.world.episodes.sampling import sample_episode
from agos.world.sim import sensors
from agos.world.sim.scene import LOOKS, Scene, box_mesh, egl_problem, obj_file, obj_text, pb
from agos.world.towns.asset import open_town
from agos.world.towns.look.vehicles import VehicleAttributes

PROBLEM = egl_problem()
needs_egl = pytest.mark.skipif(PROBLEM is not None, reason=f"EGL cannot render here: {PROBLEM}")
CAM = CameraConfig()


@pytest.fixture(autouse=True)
def _own_asset_cache(tmp_path, monkeypatch):
    """Generated textures and meshes go to a cache of this test's own."""
    monkeypatch.setenv("AGOS_ASSET_CACHE", str(tmp_path / "assets"))


# ----- the mesh files (no rendering) ------------------------------------------------------------------
def test_obj_text_and_files_are_named_by_content(tmp_path):
    vertices = np.array([[0.0, 0.0, 0.0], [1.5, 0.0, 0.0], [0.0, 2.0, 0.25]])
    normals = np.array([[0.0, 0.0, 1.0]] * 3)
    uvs = np.array([[0.0, 0.0], [3.0, 0.0], [0.0, 4.0]])
    assert obj_text(vertices, np.array([0, 1, 2])).decode() == "v 0 0 0\nv 1.5 0 0\nv 0 2 0.25\nf 1 2 3\n"
    full = obj_text(vertices, np.array([0, 1, 2]), normals, uvs).decode().splitlines()
    assert full[3:6] == ["vt 0 0", "vt 3 0", "vt 0 4"] and full[6] == "vn 0 0 1" and full[-1] == "f 1/1/1 2/2/2 3/3/3"
    assert obj_text(vertices, np.array([0, 1, 2]), normals).decode().splitlines()[-1] == "f 1//1 2//2 3//3"
    text = obj_text(vertices, np.array([0, 1, 2]), normals, uvs)
    first, again = obj_file(text, tmp_path), obj_file(text, tmp_path)
    assert first == again and first.read_bytes() == text and first.suffix == ".obj"
    assert obj_file(obj_text(vertices * 2, np.array([0, 1, 2])), tmp_path) != first
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted([first.name, obj_file(obj_text(
        vertices * 2, np.array([0, 1, 2])), tmp_path).name])  # no temporary file left behind


def test_box_mesh_faces_point_outwards():
    vertices, indices, normals = box_mesh(np.array([1.0, 2.0, 3.0]))
    tri = indices.reshape(-1, 3)
    face = np.cross(vertices[tri[:, 1]] - vertices[tri[:, 0]], vertices[tri[:, 2]] - vertices[tri[:, 0]])
    assert len(tri) == 12 and np.all(np.einsum("ij,ij->i", face, normals[tri[:, 0]]) > 0)
    assert np.allclose(vertices.min(axis=0), [-1, -2, -3]) and np.allclose(vertices.max(axis=0), [1, 2, 3])


def test_a_missing_egl_is_named_not_fatal(monkeypatch):
    """The plugin ends the process when EGL fails it; the Scene asks EGL first and raises instead."""
    if PROBLEM is None:  # EGL works here: name a device it does not have
        monkeypatch.setenv("EGL_VISIBLE_DEVICES", "99")
    problem = egl_problem()
    assert problem is not None and (PROBLEM is not None or "EGL_VISIBLE_DEVICES=99 names no device" in problem)
    with pytest.raises(RuntimeError, match=re.escape(f"the EGL renderer cannot run here: {problem}")):
        Scene(open_town("grid-s7").layout, look="flat", renderer="egl")


# ----- rendering through EGL ----------------------------------------------------------------------------
def _interior(ids: np.ndarray) -> np.ndarray:
    """Pixels whose 3x3 neighbourhood holds one id only (each id's region eroded by one pixel)."""
    padded = np.pad(ids, 1, mode="edge")
    h, w = ids.shape
    same = np.ones(ids.shape, bool)
    for dy in range(3):
        for dx in range(3):
            same &= padded[dy:dy + h, dx:dx + w] == ids
    return same


def _agreement(tiny, egl, sem_tiny, sem_egl) -> tuple[float, float, float, float]:
    """Instance and semantic agreement away from edges, and there the median relative depth difference
    and the median RGB difference (0-255, the largest of the three channels'). Shading differs by a few
    levels; a texture on the wrong body (the plugin's changeShapeTexture, see Scene._textured_body)
    makes the median 26-54 in these views, against 6-9."""
    inner = _interior(tiny.instance) & _interior(egl.instance)
    hit = inner & (tiny.instance >= 0) & (egl.instance >= 0)
    depth = np.abs(egl.depth_m[hit] - tiny.depth_m[hit]) / tiny.depth_m[hit]
    rgb = np.abs(egl.rgb[hit].astype(int) - tiny.rgb[hit].astype(int)).max(axis=1)
    return (float(np.mean(tiny.instance[inner] == egl.instance[inner])),
            float(np.mean(sem_tiny[inner] == sem_egl[inner])), float(np.median(depth)) if hit.any() else 0.0,
            float(np.median(rgb)) if hit.any() else 0.0)


def _shots(scene: Scene, town) -> list[sensors.Shot]:
    anchors = town.roads.anchor_array()[0]
    a, b = (tuple(float(v) for v in town.roads.positions_world_m[int(k)][:2]) for k in (anchors[0], anchors[len(anchors) // 2]))
    return [sensors.nadir(scene, a, 80.0, CAM), sensors.nadir(scene, b, 40.0, CAM),
            *sensors.six_views(scene, a, 0.3, CAM)]


@needs_egl
@pytest.mark.slow
@pytest.mark.parametrize("look", LOOKS)
def test_egl_renders_the_objects_tinyrenderer_renders(look):
    """grid-s7 with its parked traffic and one vehicle more: two UAV views, the UGV's six, and the
    vehicle's reference views in the studio, through TinyRenderer and through EGL."""
    town = open_town("grid-s7")
    anchor = town.roads.positions_world_m[int(town.roads.anchor_array()[0][0])]
    where = (anchor[0] + 6.0, anchor[1], 0.0)
    extra = dict(attributes=VehicleAttributes(roof="white", stripe="black")) if look == "rich" else {}
    renders, references, shown = {}, {}, {}
    for renderer in ("tiny", "egl"):
        with Scene(town.layout, look=look, renderer=renderer) as scene:
            assert scene.renderer_name() == f"pybullet-{renderer}"
            uid = scene.add_vehicle("suv", "red", where, 0.4, **extra)
            renders[renderer] = [(s.name, s.render, scene.semantic(s.render.instance)) for s in _shots(scene, town)]
            shown[renderer] = [np.count_nonzero(r.instance == uid) for _, r, _ in renders[renderer]]
            references[renderer] = [cv2.imdecode(np.frombuffer(f.data, np.uint8), cv2.IMREAD_UNCHANGED)[:, :, 3] > 0
                                    for f in sensors.reference_views(scene, uid, where, 0.4, CAM)]
    figures = []
    for (name, tiny, sem_tiny), (_, egl, sem_egl) in zip(renders["tiny"], renders["egl"], strict=True):
        instance, semantic, depth, rgb = _agreement(tiny, egl, sem_tiny, sem_egl)
        figures.append(f"{look} {name}: instance {instance:.4f} semantic {semantic:.4f} depth {depth:.3%} rgb {rgb:.0f}")
        assert instance >= 0.99 and semantic >= 0.99 and depth <= 0.01, figures[-1]
        # colours: the textures (rich); the flat look's plain faces turned from the sun come out up to
        # 22 levels lighter through EGL's shader, which the median catches where such a face fills a view
        assert rgb <= 16 or look == "flat", figures[-1]
    print("\n".join(figures))
    # the vehicle added shows in the same views, about as large
    assert [p > 0 for p in shown["tiny"]] == [p > 0 for p in shown["egl"]] and sum(shown["tiny"]) > 0
    assert abs(sum(shown["egl"]) - sum(shown["tiny"])) <= 0.1 * sum(shown["tiny"]), shown
    for tiny_mask, egl_mask in zip(references["tiny"], references["egl"], strict=True):  # the studio's views
        inner = _interior(tiny_mask) & _interior(egl_mask)
        assert tiny_mask.any() and np.mean(tiny_mask[inner] == egl_mask[inner]) >= 0.99


@needs_egl
def test_egl_keeps_texture_orientation_and_tint(tmp_path):
    """A quad whose texture is white in its top rows and blue in its bottom ones, tinted by rgbaColor
    (green halved) and seen from above: magenta where v = 1 (north), blue where v = 0, from arrays (TinyRenderer) as from the
    OBJ file (EGL). In a bare client: the plugin gives a texture to the right body only while every
    shape so far has one instance (world/sim/scene.py, Scene._textured_body)."""
    import importlib.util

    texture = np.zeros((8, 8, 3), np.uint8)  # rows of 24 bytes (GL reads rows 4-byte aligned)
    texture[:4] = (255, 255, 255)  # the top rows (v = 1) white
    texture[4:] = (255, 0, 0)  # the bottom rows (v = 0) blue
    path = tmp_path / "two_rows.png"
    cv2.imwrite(str(path), texture)
    vertices = np.array([[-5.0, -5.0, 0.0], [5.0, -5.0, 0.0], [5.0, 5.0, 0.0], [-5.0, 5.0, 0.0]])
    indices, normals = np.array([0, 1, 2, 0, 2, 3]), np.array([[0.0, 0.0, 1.0]] * 4)
    uvs = np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]])
    style = dict(rgbaColor=[1.0, 0.5, 1.0, 1.0], specularColor=[0.0] * 3)
    for renderer in ("tiny", "egl"):
        client = pb.connect(pb.DIRECT)
        try:
            if renderer == "egl":
                plugin = importlib.util.find_spec("eglRenderer")
                assert plugin is not None and plugin.origin is not None
                assert pb.loadPlugin(plugin.origin, "_eglRendererPlugin", physicsClientId=client) >= 0
                obj = obj_file(obj_text(vertices, indices, normals, uvs), tmp_path / "meshes")
                shape = pb.createVisualShape(pb.GEOM_MESH, fileName=str(obj), meshScale=[1.0] * 3, **style,
                                             physicsClientId=client)
            else:
                shape = pb.createVisualShape(pb.GEOM_MESH, vertices=vertices.tolist(), indices=indices.tolist(),
                                             normals=normals.tolist(), uvs=uvs.tolist(), **style, physicsClientId=client)
            uid = pb.createMultiBody(baseMass=0, baseVisualShapeIndex=shape, physicsClientId=client)
            pb.changeVisualShape(uid, -1, textureUniqueId=pb.loadTexture(str(path), physicsClientId=client),
                                 physicsClientId=client)
            view = pb.computeViewMatrix([0.0, 0.0, 20.0], [0.0, 0.0, 0.0], [0.0, 1.0, 0.0])
            _, _, rgba, _, seg = pb.getCameraImage(
                64, 64, view, pb.computeProjectionMatrixFOV(40.0, 1.0, 0.3, 100.0), shadow=0, lightDirection=[0.2, 0.1, 1.0],
                lightAmbientCoeff=0.6, lightDiffuseCoeff=0.4, lightSpecularCoeff=0.0, physicsClientId=client,
                renderer=pb.ER_BULLET_HARDWARE_OPENGL if renderer == "egl" else pb.ER_TINY_RENDERER)
        finally:
            pb.disconnect(physicsClientId=client)
        rgb = np.asarray(rgba, np.uint8).reshape(64, 64, 4)[:, :, :3].astype(float)
        mine = (np.asarray(seg).reshape(64, 64) & ((1 << 24) - 1)) == uid
        rows = np.nonzero(mine.any(axis=1))[0]
        assert len(rows) > 20, renderer
        top = rgb[rows[2:len(rows) // 3]][mine[rows[2:len(rows) // 3]]].mean(axis=0)
        bottom = rgb[rows[-len(rows) // 3:-2]][mine[rows[-len(rows) // 3:-2]]].mean(axis=0)
        assert top[0] > 200 and abs(top[2] - top[0]) < 10 and 0.4 < top[1] / top[0] < 0.6, (renderer, top)
        assert bottom[2] > 2 * max(bottom[0], bottom[1]), (renderer, bottom)  # blue


@needs_egl
@pytest.mark.slow
def test_the_oracle_succeeds_with_egl():
    """A rich episode played by the oracle with EGL succeeds as with TinyRenderer (its visibility and
    CONFIRM checks read instance pixels), and the record names the renderer."""
    town = open_town("grid-s7")
    with Scene(town.layout, look="rich") as scene:
        spec = sample_episode(town, scene, "mid", 0, seed=5, stream=1)
    config = episode_config(policies="oracle", renderer="egl")
    with Env(spec, config, town=town) as env:
        record = env.play({r: make_policy("oracle", r) for r in ("uav", "ugv")})
    assert record.renderer == "pybullet-egl" and record.status == "finished" and record.success, record.termination
