"""`agos sweep`'s axes without running episodes: every parameter it can set, the derived ones
(burst length at a fixed mean loss, blackout length), the handoff delay read from a ledger, and the
table and plot it writes."""

from __future__ import annotations

import math
from pathlib import Path

import pytest

from agos.deploy.run.sweep import handoff_delay, run_sweep, summarize, with_param
from agos.runtime.codec import to_json
from agos.runtime.episode_config import EpisodeConfig
from agos.runtime.links import IDEAL, CommProfile, load_profile
from agos.runtime.schemas import Candidate, EpisodeRecord, LedgerEntry, LinkStats, Pose
from agos.world.sim.comms import EMPTY_SYNC_BYTES as EMPTY
from agos.world.sim.comms import Channel


def test_plain_fields_and_beacon_period() -> None:
    assert with_param(IDEAL, "loss.p", 0.3).loss.model == "bernoulli"
    assert with_param(IDEAL, "loss.p", 0.3).loss.p == 0.3
    assert with_param(IDEAL, "range.max_range_m", 120).range.max_range_m == 120
    assert with_param(load_profile("narrowband"), "bandwidth.bits_per_s", 250).bandwidth.bits_per_s == 250
    assert with_param(load_profile("narrowband"), "bandwidth.queue_bytes", 1000).bandwidth.queue_bytes == 1000
    assert with_param(IDEAL, "beacon_s", 2.0).beacon_s == 2.0
    assert with_param(IDEAL, "beacon_s", 2.0).name == "ideal[beacon_s=2]"


@pytest.mark.parametrize("param", ["loss.nope", "nope", "name", "blackouts.start_s"])
def test_unknown_parameter_is_refused_by_name(param) -> None:
    with pytest.raises(ValueError, match="not a field"):
        with_param(IDEAL, param, 1.0)


def test_gilbert_elliott_fields_need_a_gilbert_elliott_base() -> None:
    with pytest.raises(ValueError, match="no Gilbert-Elliott"):
        with_param(IDEAL, "loss.p_bad_to_good", 0.1)
    with pytest.raises(ValueError, match="no Gilbert-Elliott"):
        with_param(IDEAL, "loss.burst_len", 10)
    assert with_param(load_profile("bursty"), "loss.loss_bad", 1.0).loss.loss_bad == 1.0


@pytest.mark.parametrize("base", ["bursty", "fading"])
@pytest.mark.parametrize("burst", [1, 5, 40, 200])
def test_burst_length_keeps_the_share_of_the_bad_state(base, burst) -> None:
    before = load_profile(base).loss
    after = with_param(load_profile(base), "loss.burst_len", burst).loss
    assert after.model == "gilbert_elliott"
    assert after.p_bad_to_good == pytest.approx(1 / burst)
    share = before.p_good_to_bad / (before.p_good_to_bad + before.p_bad_to_good)
    assert after.p_good_to_bad / (after.p_good_to_bad + after.p_bad_to_good) == pytest.approx(share)
    assert (after.loss_good, after.loss_bad) == (before.loss_good, before.loss_bad)


def test_burst_length_below_one_or_impossible_is_refused() -> None:
    with pytest.raises(ValueError, match="at least 1"):
        with_param(load_profile("fading"), "loss.burst_len", 0.5)
    mostly_bad = CommProfile(name="x", loss={"model": "gilbert_elliott", "p_good_to_bad": 0.9, "p_bad_to_good": 0.1})
    with pytest.raises(ValueError, match="p_good_to_bad > 1"):
        with_param(mostly_bad, "loss.burst_len", 1)


def test_blackout_duration_sets_every_blackout_from_its_start() -> None:
    base = load_profile("blackout")
    longer = with_param(base, "blackouts.duration_s", 100)
    assert [(b.start_s, b.end_s) for b in longer.blackouts] == [(b.start_s, b.start_s + 100) for b in base.blackouts]
    off = with_param(load_profile("outage"), "blackouts.duration_s", 0)
    assert all(b.start_s == b.end_s for b in off.blackouts)
    with pytest.raises(ValueError, match="no blackouts"):
        with_param(IDEAL, "blackouts.duration_s", 60)


def test_degrading_profiles_are_sweep_points() -> None:
    """Each documented degrading profile is one point of the sweep that shows it (docs/COMMS.md)."""
    outage = load_profile("outage")
    assert with_param(outage, "blackouts.duration_s", 600).blackouts == outage.blackouts
    short = load_profile("short-range")
    assert short.range.max_range_m == 100 and short.range.nlos_loss == 0
    assert with_param(IDEAL, "range.max_range_m", 100).range == short.range


def _entry(seq: int, sent: float, size: int, delivered: bool = True, sender: str = "uav", kind: str = "sync") -> LedgerEntry:
    return LedgerEntry(seq=seq, kind=kind, sender=sender, receiver="ugv" if sender == "uav" else "uav", sent_s=sent,
                       size_bytes=size, delivered=delivered, arrive_s=sent + 0.5 if delivered else None,
                       delay_s=0.5 if delivered else None, drop_reason=None if delivered else "loss")


def _record(episode: str, ledger: list[LedgerEntry], *, success: bool = True, sim_time_s: float = 100.0) -> str:
    link = LinkStats(profile="x", sent=len(ledger), delivered=sum(e.delivered for e in ledger), dropped={},
                     delivery_rate=sum(e.delivered for e in ledger) / max(1, len(ledger)), mean_delay_s=None,
                     max_delay_s=None, bytes_sent=0, mean_info_age_s={}, candidates_delivered=0, candidates_lost=0)
    rec = EpisodeRecord(
        run_id="r", episode_id=episode, difficulty="easy", status="finished",
        termination="confirmed" if success else "budget_exhausted", success=success, ground_observed=success,
        n_confirm=int(success), ugv_path_length_m=100.0, shortest_path_length_m=50.0, final_distance_m=10.0,
        uav_budget=80, uav_first_visible_step=3, candidates=[], decisions_uav=10, decisions_ugv=5,
        sim_time_s=sim_time_s, wall_time_s=1.0, worker_id="w", town_id="t", asset_sha256="0" * 64, seed=1,
        renderer="pybullet-tiny", link=link, ledger=ledger)
    return to_json(rec).decode()


def test_handoff_delay_from_the_ledger() -> None:
    import json

    def delay(ledger: list[LedgerEntry]) -> float | None:
        return handoff_delay(json.loads(_record("e", ledger)))

    # The UAV's syncs grow when it annotates (at 10 s); lost at 10 and 15, delivered at 20 (+0.5 s latency).
    ledger = [_entry(1, 0.0, EMPTY), _entry(2, 5.0, EMPTY), _entry(3, 6.0, 300, sender="ugv"),
              _entry(4, 10.0, 316, delivered=False), _entry(5, 15.0, 316, delivered=False, kind="beacon"),
              _entry(6, 12.0, 500, kind="message"), _entry(7, 20.0, 318)]
    assert delay(ledger) == pytest.approx(10.5)
    assert delay(ledger[:2]) is None  # no candidate
    assert delay([]) is None
    assert delay(ledger[:5]) == math.inf  # never heard
    assert delay(ledger[3:]) == pytest.approx(10.5)  # annotated at its first decision: every sync carries it


def test_a_sync_without_candidates_has_the_empty_size_and_one_with_a_candidate_is_larger() -> None:
    start = {"uav": Pose(position_world_m=(1.5, -2.25, 80.0), yaw_rad=1.57),
             "ugv": Pose(position_world_m=(9.0, 3.0, 0.0), yaw_rad=0.0)}
    channel = Channel(IDEAL, 0, start)
    channel.sync("uav", 3.25, start["uav"], (80.0, True))
    channel.views["uav"].candidates["C001"] = Candidate(
        candidate_id="C001", cell="B2", polygon_world_m=[(0.0, 0.0), (1.0, 0.0), (1.0, 1.0)], center_world_m=(0.5, 0.5),
        status="pending", created_sim_time_s=3.25, approach_waypoint_id="R12")
    channel.sync("uav", 4.0, start["uav"], (80.0, True), kind="beacon")
    assert [e.size_bytes > EMPTY for e in channel.ledger] == [False, True]
    assert channel.ledger[0].size_bytes == EMPTY


def test_summarize_writes_time_and_handoff_columns(tmp_path: Path) -> None:
    ok = [_entry(1, 0.0, EMPTY), _entry(2, 10.0, 316)]
    lost = [_entry(1, 0.0, EMPTY), _entry(2, 10.0, 316, delivered=False)]
    rows = [{"value": 0.0, "seed": 0, "records": [_record("a", ok, sim_time_s=60), _record("b", ok, sim_time_s=80)]},
            {"value": 0.9, "seed": 0, "records": [_record("a", ok, sim_time_s=90),
                                                  _record("b", lost, success=False, sim_time_s=400)]}]
    table = summarize(rows, tmp_path, "loss.p")
    assert [t["T"] for t in table] == [70.0, 245.0]
    assert [t["handoff"] for t in table] == [0.5, 0.5]
    assert [t["handoff_never"] for t in table] == [0, 1]
    assert [t["SR"] for t in table] == [1.0, 0.5]
    md = (tmp_path / "sweep.md").read_text().splitlines()
    assert "time s [95% CI]" in md[0] and "handoff s [95% CI] (never/annotated)" in md[0]
    assert md[3].startswith("| 0.9 | 2 |") and md[3].endswith("| 0.5 [0.5, 0.5] (1/2) |")
    assert (tmp_path / "sweep.png").stat().st_size > 0
    assert "handoff_never" in (tmp_path / "sweep.csv").read_text().splitlines()[0]


def test_a_vlm_policy_without_an_endpoint_fails_before_anything_runs(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="asks a VLM"):
        run_sweep(tmp_path / "missing.jsonl", tmp_path / "out", config=EpisodeConfig(), param="loss.p", values=[0.1],
                  seeds=[0], policies=("agos-agent", "agos-agent"), workers=1)
    with pytest.raises(ValueError, match="not a field"):
        run_sweep(tmp_path / "missing.jsonl", tmp_path / "out", config=EpisodeConfig(), param="loss.q", values=[0.1],
                  seeds=[0], policies=("heuristic", "heuristic"), workers=1)
    assert not (tmp_path / "out").exists()


def test_each_point_has_a_file_of_its_own() -> None:
    """Numbers keep their dots (0.1 and 0.01 are two files), a profile file is named by its stem."""
    from agos.deploy.run.sweep import point_file_name

    names = {point_file_name("corruption.char_error_rate", v, 0) for v in ("0", "0.1", "0.01", "0.001")}
    assert len(names) == 4 and "corruption.char_error_rate=0.01_seed0.jsonl" in names
    assert point_file_name("pose_error", "gnss-5m", 1) == "pose_error=gnss-5m_seed1.jsonl"
    assert point_file_name("pose_error", "my/urban.toml", 0) == "pose_error=urban_seed0.jsonl"
    assert point_file_name("loss.p", "0.25", 0) == "loss.p=0.25_seed0.jsonl"
def test_a_numeric_axis_is_plotted_in_increasing_order(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Values given as 0,0.1,0.01 are drawn left to right, not back and forth."""
    from matplotlib.axes import Axes

    from agos.deploy.run import sweep

    drawn: list[list[float]] = []
    real = Axes.errorbar
    monkeypatch.setattr(Axes, "errorbar", lambda self, x, *a, **k: drawn.append(list(x)) or real(self, x, *a, **k))
    row = {name: 0.5 for name in sweep.METRICS} | {f"{n}_{end}": 0.5 for n in sweep.METRICS for end in ("low", "high")}
    table = [row | {"value": v, "handoff_never_pct": 0.0} for v in ("0", "0.1", "0.01")]
    sweep._plots(table, tmp_path, "corruption.char_error_rate")
    assert drawn and all(x == [0.0, 0.01, 0.1] for x in drawn)
    assert (tmp_path / "sweep.png").exists()



@pytest.mark.parametrize(("values", "scale"), [(("0", "0.001", "0.1"), "symlog"), (("0.001", "0.1"), "log"),
                                               (("0", "0.1", "0.2"), "linear")])
def test_values_over_decades_get_a_log_axis_with_zero_on_it(tmp_path: Path, values: tuple[str, ...],
                                                            scale: str, monkeypatch: pytest.MonkeyPatch) -> None:
    """A rate swept over decades (0, 0.001, 0.1) would crowd at the left of a linear axis."""
    import matplotlib.pyplot as plt

    from agos.deploy.run import sweep

    closed: list = []
    monkeypatch.setattr(plt, "close", closed.append)  # keep the figure to look at its axes
    row = {name: 0.5 for name in sweep.METRICS} | {f"{n}_{end}": 0.5 for n in sweep.METRICS for end in ("low", "high")}
    sweep._plots([row | {"value": v, "handoff_never_pct": 0.0} for v in values], tmp_path, "corruption.char_error_rate")
    (figure,) = closed
    assert {ax.get_xscale() for ax in figure.axes} == {scale}
