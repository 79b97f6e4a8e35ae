"""The paper's agent inputs that the world sends and the VLM prompts show: the UAV's top view of its
teammate (both methods) and the UGV's remaining confirmation budget (docs/AGENTS.md). Unit tier: the
prompts are built in-process, no request is sent."""

from __future__ import annotations

import msgspec
import numpy as np
import pytest

from agos.agents.vlm import agos_prompts, baseline_prompts, protocol
from agos.agents.vlm.agent import MAX_IMAGES
from agos.agents.vlm.request import Memory
from agos.runtime.codec import decode_image
from agos.runtime.episode_config import CameraConfig
from agos.runtime.schemas import Observation
from agos.world.sim import rules
from agos.world.sim.scene import Scene
from agos.world.sim.teammate import TEAMMATE_TOP, UGV_MODEL, teammate_top_view
from agos.world.towns.asset import open_town
from agos.world.towns.catalog import body_type

UAV_BUILDERS = {"agos-agent": agos_prompts.uav_prompt, "baseline": baseline_prompts.uav_prompt}
UGV_BUILDERS = {"agos-agent": agos_prompts.ugv_prompt, "baseline": baseline_prompts.ugv_prompt}


def _first(observations: list[Observation], role: str, mode: str | None = None) -> Observation:
    return next(o for o in observations if o.role == role and (mode is None or o.mode == mode))


def test_every_uav_observation_carries_the_teammate_view_and_no_ugv_one_does(observations) -> None:
    uav = [o for o in observations if o.role == "uav"]
    ugv = [o for o in observations if o.role == "ugv"]
    assert uav and ugv
    first = uav[0].teammate_reference
    assert first is not None and first.name == TEAMMATE_TOP and first.metres_per_px
    assert all(o.teammate_reference == first for o in uav)  # rendered once, at the episode's start
    assert all(o.teammate_reference is None for o in ugv)


@pytest.mark.parametrize("method", sorted(UAV_BUILDERS))
def test_the_uav_request_shows_the_teammate_view_labelled(observations, method: str) -> None:
    obs = _first(observations, "uav")
    assert obs.teammate_reference is not None
    prompt = UAV_BUILDERS[method](obs, Memory())
    req = protocol.split_request(prompt.messages())
    assert req.unlabelled == 0
    assert req.images[protocol.TEAMMATE_REFERENCE] == obs.teammate_reference.data
    assert not protocol.TEAMMATE_REFERENCE.startswith(protocol.REFERENCE_PREFIX)  # never read as the target
    assert req.state is not None and req.state["teammate_m_per_px"] == obs.teammate_reference.metres_per_px
    assert "teammate, the UGV, seen from straight above" in req.text
    assert len(req.images) == MAX_IMAGES[("uav", "all")]  # the preflight asks for as many as are sent
    view_only = protocol.split_request(UAV_BUILDERS[method](obs, Memory(), images="view_only").messages())
    assert protocol.TEAMMATE_REFERENCE not in view_only.images
    assert len(view_only.images) <= MAX_IMAGES[("uav", "view_only")]


@pytest.mark.parametrize("method", sorted(UGV_BUILDERS))
def test_the_ugv_request_has_no_teammate_view(observations, method: str) -> None:
    req = protocol.split_request(UGV_BUILDERS[method](_first(observations, "ugv"), Memory()).messages())
    assert protocol.TEAMMATE_REFERENCE not in req.images


def test_the_teammate_view_is_the_ugv_alone_from_above() -> None:
    town = open_town("grid-s7")
    with Scene(town.layout, look="flat") as scene:
        frame = teammate_top_view(scene, CameraConfig())
        assert teammate_top_view(scene, CameraConfig()) is frame  # one render per scene and size
        small = teammate_top_view(scene, CameraConfig(reference_px=96))
    rgba = decode_image(frame.data)
    assert rgba.shape == (160, 160, 4) and decode_image(small.data).shape == (96, 96, 4)
    alpha = rgba[:, :, 3] > 0
    assert not alpha[0].any() and not alpha[-1].any() and not alpha[:, 0].any()  # background removed
    body = body_type(UGV_MODEL)
    mpp = frame.metres_per_px
    assert mpp is not None
    assert alpha.sum() * mpp**2 == pytest.approx(body.length_m * body.width_m, rel=0.15)  # its footprint
    rows, cols = np.nonzero(alpha)
    assert (rows.max() - rows.min()) > 2 * (cols.max() - cols.min())  # nose up: long along the image's height
    with Scene(town.layout, look="flat") as again:  # the same picture from a fresh scene
        assert teammate_top_view(again, CameraConfig()).data == frame.data


def test_the_world_sends_the_confirmation_budget(observations) -> None:
    assert {(o.coordination.confirmations_used, o.coordination.max_confirmations) for o in observations} == {
        (0, rules.MAX_CONFIRMATIONS)} == {(0, 1)}  # a CONFIRM ends the episode, so no observation follows one


@pytest.mark.parametrize("method", sorted(UGV_BUILDERS))
@pytest.mark.parametrize("mode", ["driving", "stop_6view"])
def test_the_ugv_prompt_states_the_remaining_confirmation_budget(observations, method: str, mode: str) -> None:
    obs = _first(observations, "ugv", mode)
    req = protocol.split_request(UGV_BUILDERS[method](obs, Memory()).messages())
    assert req.state is not None and req.state["confirmations"] == {"used": 0, "max": 1, "left": 1}
    assert "Confirmations left: 1 of 1" in req.text
    # the numbers are the world's, not the prompt's: another coordination state, other numbers
    other = msgspec.structs.replace(obs, coordination=msgspec.structs.replace(
        obs.coordination, confirmations_used=1, max_confirmations=3))
    req = protocol.split_request(UGV_BUILDERS[method](other, Memory()).messages())
    assert req.state is not None and req.state["confirmations"] == {"used": 1, "max": 3, "left": 2}
    assert "Confirmations left: 2 of 3" in req.text
