"""The link to the model (runtime/model_link.py, world/sim/model_link.py, docs/COMMS.md): the exchange's
arithmetic (bytes over bandwidth plus latency, retries after a timeout, a failed decision), seeded
streams, the one-line refusals of bad placements, the configuration hash at the default, the exact
request and reply sizes the client reports (also from the replay cache), the image-size lever, and
episodes over the stand-in VLM: bytes and link time in the records, a satellite's decisions later in
simulated time than onboard ones, identical records on two runs and from a replay."""

from __future__ import annotations

import asyncio
import json
from pathlib import Path

import httpx
import msgspec
import numpy as np
import pytest

from agos import Env, episode_config
from agos.agents.registry import make_policy
from agos.agents.vlm.cache import ReplyCache
from agos.agents.vlm.client import VlmClient
from agos.agents.vlm.images import as_sent, sized
from agos.agents.vlm.standin.server import DEFAULT_MODELS, StandinServer
from agos.deploy.run.card_writer import model_link_card, sampling
from agos.runtime.codec import decode_image, encode_jpeg, encode_png
from agos.runtime.episode_config import EpisodeConfig, config_hash, with_model_link
from agos.runtime.model_link import (
    ModelLinkError,
    ModelLinkProfile,
    load_model_link,
    model_link_for,
)
from agos.runtime.schemas import CameraIntrinsics, EpisodeRecord, ImageFrame
from agos.runtime.settings import VlmOptions
from agos.world.episodes.sampling import sample_episode
from agos.world.sim.scene import Scene
from agos.world.towns.asset import open_town

from support.episodes import SMALL_CAMERAS

VOLATILE = ("run_id", "worker_id", "wall_time_s", "provenance")


def profile(**sections) -> ModelLinkProfile:
    """1 Mbit/s up, 8 Mbit/s down, 100 ms each way, no jitter; retry after 2 s, 3 attempts; ``sections``
    replace parts of it (``up={...}``)."""
    data = {"name": "test", "up": {"latency": {"mean_s": 0.1}, "bandwidth": {"bits_per_s": 1e6}},
            "down": {"latency": {"mean_s": 0.1}, "bandwidth": {"bits_per_s": 8e6}},
            "retry": {"timeout_s": 2.0, "max_attempts": 3}}
    for side, value in sections.items():
        data[side] = {**data.get(side, {}), **value} if isinstance(value, dict) else value
    return ModelLinkProfile.model_validate(data)


def link(p: ModelLinkProfile, seed: int = 0):
    made = model_link_for(p, seed)
    assert made is not None
    return made


# ----- the arithmetic -------------------------------------------------------------------------------------
def test_the_link_time_is_bytes_over_bandwidth_plus_latency_each_way() -> None:
    trip = link(profile()).exchange("ugv", 10.0, 125_000, 1_000)  # 1 s up + 0.1 s; 1 ms down + 0.1 s
    assert trip.failed is None and trip.attempts == 1
    assert trip.link_s == pytest.approx(1.0 + 0.1 + 0.001 + 0.1)
    assert (trip.bytes_up, trip.bytes_down) == (125_000, 1_000)


def test_a_lost_request_is_sent_again_after_the_timeout() -> None:
    # The uplink is out until 5 s: attempts at 0, 0 + 1 s sending + 2 s timeout = 3, and 6 (through).
    trip = link(profile(up={"blackouts": [{"start_s": 0.0, "end_s": 5.0}]})).exchange("uav", 0.0, 125_000, 1_000)
    assert trip.failed is None and trip.attempts == 3
    assert trip.link_s == pytest.approx(6.0 + 1.0 + 0.1 + 0.001 + 0.1)


def test_a_lost_reply_costs_a_timeout_and_the_whole_exchange_again() -> None:
    trip = link(profile(down={"blackouts": [{"start_s": 0.0, "end_s": 2.0}]})).exchange("uav", 0.0, 125_000, 1_000)
    assert trip.failed is None and trip.attempts == 2  # the first reply leaves at 1.1 s, in the blackout
    assert trip.link_s == pytest.approx(3.0 + 1.0 + 0.1 + 0.001 + 0.1)


def test_every_attempt_lost_fails_the_decision_after_the_last_timeout() -> None:
    ml = link(profile(up={"blackouts": [{"start_s": 0.0, "end_s": 100.0}]}))
    trip = ml.exchange("ugv", 0.0, 125_000, 1_000)
    assert trip.failed == "request lost (blackout)" and trip.attempts == 3
    assert trip.link_s == pytest.approx(3 * (1.0 + 2.0))
    late = link(profile(down={"latency": {"mean_s": 5.0}})).exchange("ugv", 0.0, 125_000, 1_000)
    assert late.failed == "reply too late (timeout)"  # 5.1 s to the reply's first byte > 2 s timeout
    stats = ml.stats()
    assert (stats.decisions, stats.failed, stats.bytes_up, stats.bytes_down) == (1, 1, 125_000, 1_000)
    assert stats.link_time_s == stats.max_link_time_s == 9.0


def test_a_reask_pays_the_latency_again_and_shares_the_bytes() -> None:
    once = link(profile()).exchange("ugv", 0.0, 250_000, 2_000)
    twice = link(profile()).exchange("ugv", 0.0, 250_000, 2_000, exchanges=2)
    assert twice.link_s == pytest.approx(once.link_s + 0.2) and twice.attempts == 2


def test_the_same_seed_gives_the_same_times_and_each_role_its_own_stream() -> None:
    lte = load_model_link("lte")

    def times(seed: int, role: str = "uav") -> list[float]:
        ml = link(lte, seed)
        return [ml.exchange(role, 5.0 * k, 200_000, 500).link_s for k in range(30)]

    assert times(3) == times(3)
    assert times(3) != times(4)
    assert times(3, "uav") != times(3, "ugv")


def test_the_shipped_placements_load_and_onboard_is_no_link() -> None:
    onboard = load_model_link("onboard")
    assert onboard.onboard and model_link_for(onboard, 0) is None
    for name in ("edge", "lte", "satellite"):
        p = load_model_link(name)
        assert p.description and p.up.bandwidth.bits_per_s and p.down.bandwidth.bits_per_s
    assert load_model_link("satellite").retry.timeout_s == 3.0


# ----- refusals -------------------------------------------------------------------------------------------
@pytest.mark.parametrize(("text", "says"), [
    ('[up.latency]\nmean_s = 0.1\n[down.bandwidth]\nbits_per_s = 1e6\n',
     "up.bandwidth.bits_per_s: a model link needs a bandwidth (use onboard for none)"),
    ('[up.bandwidth]\nbits_per_s = 1e6\n[down.latency]\nmean_s = 0.1\n',
     "down.bandwidth.bits_per_s: a model link needs a bandwidth (use onboard for none)"),
    ('[up.latency]\njitter_s = -1\n', "up.latency.jitter_s: Input should be greater than or equal to 0"),
    ('[up.range]\nmax_range_m = 10\n', "up.range: Extra inputs are not permitted"),
    ('onboard = true\n[up.bandwidth]\nbits_per_s = 1e6\n', "up: an onboard model has no link (leave out up, down and retry)"),
    ('[retry]\nmax_attempts = 0\n', "retry.max_attempts: Input should be greater than or equal to 1"),
])
def test_a_bad_placement_is_one_line_naming_the_file_and_the_field(tmp_path: Path, text: str, says: str) -> None:
    bad = tmp_path / "x.toml"
    bad.write_text(text)
    with pytest.raises(ModelLinkError) as caught:
        load_model_link(bad)
    assert str(caught.value) == f"{bad}: {says}"


def test_an_unknown_placement_lists_the_known_ones() -> None:
    with pytest.raises(ModelLinkError, match=r"^model link moon: no such file .*known placements: edge, lte, onboard, satellite$"):
        load_model_link("moon")


@pytest.mark.parametrize("command", ["eval", "sweep"])
def test_the_commands_refuse_a_bad_placement_in_one_line(tmp_path: Path, agos, command: str) -> None:
    bad = tmp_path / "x.toml"
    bad.write_text("[up.latency]\nmean_s = 0.1\n")
    where = ["--run-dir", tmp_path / "run"] if command == "eval" else ["--split", tmp_path / "none.jsonl", "--out", tmp_path / "o"]
    out = agos(command, "--model-link", bad, *where)
    assert out.returncode == 2, out
    assert out.stderr.strip() == f"{command} error: {bad}: up.bandwidth.bits_per_s: a model link needs a bandwidth " \
                                 "(use onboard for none)"
    assert not (tmp_path / "run").exists()


# ----- the configuration ----------------------------------------------------------------------------------
def test_the_default_and_onboard_keep_the_configuration_hash() -> None:
    default = EpisodeConfig()
    stored = default.model_dump(mode="json")
    assert stored["model_link"] is None
    del stored["model_link"]  # as configurations were stored before the field existed
    assert config_hash(stored) == default.config_hash()
    assert with_model_link(default, "onboard") == default
    assert EpisodeConfig(model_link=load_model_link("onboard")).model_link is None
    assert episode_config(model_link="onboard") == EpisodeConfig()
    lte = with_model_link(default, "lte")
    assert lte.model_link is not None and lte.model_link.name == "lte" and lte.config_hash() != default.config_hash()
    assert EpisodeConfig.model_validate(lte.model_dump(mode="json")) == lte  # stored and read back


def test_the_run_card_shows_the_placement_and_the_image_settings() -> None:
    assert model_link_card(None) == {"placement": "onboard"}
    card = model_link_card(load_model_link("satellite"))
    assert card["placement"] == "satellite" and "GEO" in card["description"] and card["profile"]["retry"]["timeout_s"] == 3.0
    s = sampling(VlmOptions(image_max_px=128, jpeg_quality=60))
    assert (s["image_max_px"], s["jpeg_quality"]) == (128, 60)


# ----- the client's sizes ---------------------------------------------------------------------------------
REPLY = b'{"choices": [{"message": {"content": "{\\"action\\": \\"WAIT\\"}"}, "finish_reason": "stop"}]}  \n'


def test_the_client_reports_the_exact_request_and_reply_sizes_also_from_the_cache(tmp_path: Path) -> None:
    posted: list[bytes] = []

    def endpoint(request: httpx.Request) -> httpx.Response:
        posted.append(request.read())
        return httpx.Response(200, content=REPLY, headers={"content-type": "application/json"})

    messages = [{"role": "user", "content": [{"type": "text", "text": "où est la voiture ?"}]}]

    async def ask(cache: ReplyCache | None, transport: httpx.MockTransport) -> tuple:
        client = VlmClient("http://x/v1", "m", transport=transport, cache=cache, max_retries=0)
        try:
            reply = await client.complete(messages)
        finally:
            await client.close()
        return reply.request_bytes, reply.reply_bytes

    live = asyncio.run(ask(None, httpx.MockTransport(endpoint)))
    assert live == (len(posted[0]), len(REPLY)) and json.loads(posted[0])["messages"] == messages
    recorded = asyncio.run(ask(ReplyCache(tmp_path, "record"), httpx.MockTransport(endpoint)))
    replayed = asyncio.run(ask(ReplyCache(tmp_path, "replay"), httpx.MockTransport(lambda r: httpx.Response(500))))
    assert recorded == replayed == live and len(posted) == 2


# ----- the lever: image size and encoding -----------------------------------------------------------------
def frame(kind: str = "rgb", encoding: str = "jpeg", side: int = 256) -> ImageFrame:
    rng = np.random.default_rng(0)
    image = rng.integers(0, 255, (side, side, 3), dtype=np.uint8)
    data = encode_jpeg(image) if encoding == "jpeg" else encode_png(image)
    return ImageFrame(name="front", kind=kind, encoding=encoding, data=data, metres_per_px=0.05,  # type: ignore[arg-type]
                      intrinsics=CameraIntrinsics(width_px=side, height_px=side, fx_px=200.0, fy_px=200.0,
                                                  cx_px=side / 2, cy_px=side / 2))


def test_images_are_shrunk_with_their_camera_numbers_and_reencoded_as_asked() -> None:
    original = frame()
    small = sized(original, 128, None)
    assert decode_image(small.data).shape[:2] == (128, 128) and small.encoding == "jpeg"
    assert small.intrinsics == CameraIntrinsics(width_px=128, height_px=128, fx_px=100.0, fy_px=100.0, cx_px=64.0, cy_px=64.0)
    assert small.metres_per_px == pytest.approx(0.1) and len(small.data) < len(original.data)
    png = frame(encoding="png")
    as_jpeg = sized(png, None, 50)
    assert as_jpeg.encoding == "jpeg" and as_jpeg.intrinsics == png.intrinsics and len(as_jpeg.data) < len(png.data)
    rgba = np.zeros((160, 160, 4), np.uint8)
    rgba[40:120, 60:100] = (20, 71, 224, 255)  # a reference view: the car, the background transparent
    ref = ImageFrame(name="ref_top", kind="rgb", encoding="png", data=encode_png(rgba), metres_per_px=0.0655)
    kept = sized(ref, 80, 50)
    assert kept.encoding == "png" and decode_image(kept.data).shape == (80, 80, 4)  # JPEG has no transparency
    assert sized(original, 512, None) is original  # already small enough, no quality asked: as rendered
    depth = frame(kind="depth", encoding="png")
    assert sized(depth, 64, 50) is depth  # never sent to a model


# ----- episodes over the stand-in VLM ---------------------------------------------------------------------
@pytest.fixture(scope="module")
def world():
    town = open_town("grid-s7")
    with Scene(town.layout, look="flat") as scene:
        yield town, scene, sample_episode(town, scene, "easy", 0, seed=2, stream=0)


@pytest.fixture(scope="module")
def standin():
    with StandinServer() as server:
        yield VlmOptions(base_url=server.url, model=DEFAULT_MODELS[0])


def play(world, vlm: VlmOptions, policy: str = "agos-agent", **config) -> EpisodeRecord:
    town, scene, spec = world
    cfg = episode_config(policies=policy, look="flat", decision_budget=8, **config)
    with Env(spec, cfg, illegal="wait", scene=scene, town=town) as env:
        return env.play({r: make_policy(policy, r, vlm=vlm if policy == "agos-agent" else None) for r in ("uav", "ugv")})


def same(record: EpisodeRecord, *, wall: bool = False) -> dict:
    """The record less what differs between two plays (and, unless ``wall``, the traces' wall-clock latency)."""
    out = {k: v for k, v in msgspec.to_builtins(record).items() if k not in VOLATILE}
    if not wall:
        out["decision_traces"] = [{k: v for k, v in t.items() if k != "latency_s"} for t in out["decision_traces"]]
        out.pop("agent_stats", None)
    return out


@pytest.mark.loopback  # the stand-in VLM listens on 127.0.0.1
def test_a_satellite_link_delays_every_decision_and_the_records_carry_it(world, standin: VlmOptions) -> None:
    onboard = play(world, standin)
    sat = play(world, standin, model_link="satellite")
    assert onboard.model_link is None and all(s.model_link_s is None for s in onboard.step_log)
    assert onboard.step_log[0].sim_time_s == 0.0
    stats = sat.model_link
    assert stats is not None and stats.profile == "satellite" and stats.decisions == len(sat.step_log) >= 4
    for step, trace in zip(sat.step_log, sat.decision_traces, strict=True):
        assert step.model_bytes_up == trace.request_bytes > 10_000  # images
        assert step.model_bytes_down == trace.reply_bytes > 100
        assert step.model_link_s is not None and step.model_link_s > 0.6  # two 300 ms hops at least
    assert stats.bytes_up == sum(t.request_bytes for t in sat.decision_traces)
    assert stats.link_time_s == pytest.approx(sum(s.model_link_s or 0 for s in sat.step_log), abs=1e-3)
    first = {s.role: s.sim_time_s for s in reversed(sat.step_log)}
    assert min(first.values()) > 0.6  # the first decisions took effect after the link, not at 0
    assert sat.sim_time_s > onboard.sim_time_s
    assert same(play(world, standin, model_link="satellite")) == same(sat)  # the same seed, the same record


def test_scripted_policies_pay_nothing_and_the_robot_link_is_untouched(world) -> None:
    # what the heuristic sees does not matter here: small images
    onboard = play(world, VlmOptions(), policy="heuristic", comm="lossy", cameras=SMALL_CAMERAS)
    sat = play(world, VlmOptions(), policy="heuristic", comm="lossy", model_link="satellite", cameras=SMALL_CAMERAS)
    assert sat.model_link is not None and sat.model_link.decisions == 0
    assert sat.step_log == onboard.step_log and sat.ledger == onboard.ledger and sat.sim_time_s == onboard.sim_time_s


@pytest.mark.loopback  # the stand-in VLM listens on 127.0.0.1
def test_a_replayed_run_with_a_model_link_gives_the_recorded_records(world, standin: VlmOptions, tmp_path: Path) -> None:
    recorded = play(world, standin.model_copy(update={"cache_dir": tmp_path, "cache_mode": "record"}), model_link="lte")
    replayed = play(world, VlmOptions(model=standin.model, cache_dir=tmp_path, cache_mode="replay"), model_link="lte")
    assert same(replayed, wall=True) == same(recorded, wall=True)
    assert recorded.model_link is not None and recorded.model_link.bytes_up > 0


@pytest.mark.loopback  # the stand-in VLM listens on 127.0.0.1
def test_smaller_images_make_lighter_requests(world, standin: VlmOptions) -> None:
    full = play(world, standin, model_link="lte")
    small = play(world, standin.model_copy(update={"image_max_px": 64, "jpeg_quality": 50}), model_link="lte")
    assert full.model_link is not None and small.model_link is not None
    assert small.model_link.bytes_up / small.model_link.decisions < 0.5 * full.model_link.bytes_up / full.model_link.decisions


def test_as_sent_leaves_an_observation_alone_by_default(observations) -> None:
    obs = observations[0]
    assert as_sent(obs, None, None) is obs
    shrunk = as_sent(obs, 64, None)
    assert all(max(decode_image(f.data).shape[:2]) <= 64 for f in shrunk.images if f.kind in ("rgb", "rgb_grid", "map"))
    assert all(max(decode_image(f.data).shape[:2]) <= 64 for f in shrunk.references)
