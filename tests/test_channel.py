"""The in-episode channel of agos.world.sim.comms: role views, sync/beacon/message delivery, ledger, stats.

Unit tests use hand-made candidates and poses; the last test runs a whole lossy episode in-process.
"""

from __future__ import annotations

import math

import msgpack
import msgspec
import pytest

from agos.runtime.episode_config import EpisodeConfig
from agos.runtime.links import IDEAL, Blackout, CommProfile, Delivery, LatencySpec, LossSpec, RangeSpec, load_profile
from agos.runtime.schemas import Candidate, MessageRecord, Pose
from agos.world.sim.comms import MESSAGE_OVERHEAD_BYTES, STATUS_RANK, Arrival, Channel, RoleView

NEAR = (10.0, True)  # (distance_m, line_of_sight) of the two roles


def pose(x: float, y: float = 0.0, yaw: float = 0.0) -> Pose:
    return Pose(position_world_m=(x, y, 0.0), yaw_rad=yaw)


def cand(cid: str = "C001", status: str = "pending", t: float = 0.0) -> Candidate:
    return Candidate(candidate_id=cid, cell="B2", polygon_world_m=[(0.0, 0.0), (10.0, 0.0), (10.0, 10.0), (0.0, 10.0)],
                     center_world_m=(5.0, 5.0), status=status, created_sim_time_s=t)


START = {"uav": pose(0.0, 0.0), "ugv": pose(100.0, 50.0, 1.0)}


def channel(profile: CommProfile = IDEAL, seed: int = 1) -> Channel:
    return Channel(profile, seed, dict(START))


class ScriptedLink:
    """Stands in for a Link: hands out the given deliveries in order (delays relative to the send time)."""

    def __init__(self, *fates: float | str) -> None:
        self.fates = list(fates)
        self.sent: list[tuple[float, int]] = []

    def transmit(self, t_send: float, size_bytes: int, *, distance_m: float = 0.0, line_of_sight: bool = True) -> Delivery:
        self.sent.append((t_send, size_bytes))
        fate = self.fates.pop(0)
        if isinstance(fate, str):
            return Delivery(False, None, fate)
        return Delivery(True, t_send + fate)


# ----- initial state and beacons ---------------------------------------------------------------------
def test_initial_views_know_the_teammate_start():
    ch = channel()
    assert ch.views["uav"].teammate_pose == START["ugv"]
    assert ch.views["ugv"].teammate_pose == START["uav"]
    assert ch.views["uav"].teammate_info_s == 0.0 and ch.views["ugv"].teammate_info_s == 0.0
    assert ch.views["uav"].candidates == {} and ch.views["uav"].messages == []
    assert ch.ledger == []
    assert ch.next_arrival_s() == math.inf
    assert ch.deliver_until(1e9) == []


def test_ideal_sync_arrives_at_send_time_and_no_beacons():
    ch = channel(IDEAL)
    assert ch.next_beacon_s() == math.inf
    assert set(ch.next_beacon.values()) == {math.inf}
    ch.views["uav"].candidates["C001"] = cand()
    new_pose = pose(3.0, 4.0)
    ch.sync("uav", 12.5, new_pose, NEAR)
    assert ch.next_arrival_s() == 12.5
    (entry,) = ch.ledger
    assert entry.delivered and entry.arrive_s == 12.5 and entry.delay_s == 0.0 and entry.drop_reason is None
    assert ch.deliver_until(12.4) == []
    arrivals = ch.deliver_until(12.5)
    assert arrivals == [Arrival("ugv", "sync", True)]
    view = ch.views["ugv"]
    assert view.candidates["C001"].status == "pending"
    assert view.teammate_pose == new_pose and view.teammate_info_s == 12.5
    assert ch.next_arrival_s() == math.inf
    # the sender's own view is untouched
    assert ch.views["uav"].teammate_info_s == 0.0


@pytest.mark.parametrize("name", ["lossy", "bursty", "narrowband", "long-range", "blackout"])
def test_degraded_profiles_schedule_beacons(name):
    prof = load_profile(name)
    ch = channel(prof)
    assert ch.next_beacon == {"uav": prof.beacon_s, "ugv": prof.beacon_s}
    assert ch.next_beacon_s() == prof.beacon_s


def test_custom_beacon_period():
    prof = CommProfile(name="x", loss=LossSpec(model="bernoulli", p=0.1), beacon_s=2.5)
    ch = channel(prof)
    assert ch.next_beacon_s() == 2.5
    ch.next_beacon["uav"] += prof.beacon_s  # what the episode runner does after beaconing
    assert ch.next_beacon_s() == 2.5
    ch.next_beacon["ugv"] += prof.beacon_s
    assert ch.next_beacon_s() == 5.0


def test_beacon_kind_travels_like_a_sync():
    ch = channel(CommProfile(name="x", latency=LatencySpec(mean_s=0.5)))
    ch.views["ugv"].candidates["C001"] = cand(status="arrived")
    ch.sync("ugv", 5.0, pose(1.0), NEAR, kind="beacon")
    assert ch.ledger[0].kind == "beacon" and ch.ledger[0].sender == "ugv" and ch.ledger[0].receiver == "uav"
    assert ch.deliver_until(5.49) == []
    assert ch.deliver_until(5.5) == [Arrival("uav", "beacon", True)]
    assert ch.views["uav"].candidates["C001"].status == "arrived"
    assert ch.views["uav"].teammate_info_s == 5.0


# ----- RoleView.merge ------------------------------------------------------------------------------
def test_status_rank_order():
    assert STATUS_RANK["pending"] < STATUS_RANK["arrived"] < STATUS_RANK["rejected"]
    assert STATUS_RANK["confirmed"] == STATUS_RANK["false_confirm"] == STATUS_RANK["rejected"]


def test_merge_keeps_most_advanced_status():
    view = RoleView()
    assert view.merge([cand("C001", "pending")]) is True
    assert view.merge([cand("C001", "pending")]) is False  # nothing new
    assert view.merge([cand("C001", "arrived")]) is True
    assert view.candidates["C001"].status == "arrived"
    assert view.merge([cand("C001", "pending")]) is False  # older knowledge is ignored
    assert view.candidates["C001"].status == "arrived"
    assert view.merge([cand("C001", "rejected")]) is True
    assert view.merge([cand("C001", "arrived"), cand("C001", "pending")]) is False
    assert view.candidates["C001"].status == "rejected"
    assert view.merge([cand("C001", "confirmed")]) is False  # same rank: first one stays
    assert view.candidates["C001"].status == "rejected"


def test_merge_adds_new_candidates_and_copies():
    view = RoleView()
    view.merge([cand("C001", "rejected")])
    incoming = cand("C002", "pending")
    assert view.merge([cand("C001", "pending"), incoming]) is True
    assert sorted(view.candidates) == ["C001", "C002"]
    assert view.candidates["C001"].status == "rejected"
    incoming.status = "arrived"  # the view holds its own copy
    assert view.candidates["C002"].status == "pending"


def test_active_candidate_is_first_unresolved():
    view = RoleView()
    assert view.active_candidate() is None
    view.merge([cand("C002", "pending"), cand("C001", "rejected"), cand("C003", "arrived")])
    assert view.active_candidate().candidate_id == "C002"


# ----- sync delivery -------------------------------------------------------------------------------
def test_sync_snapshot_is_taken_at_send_time():
    ch = channel(CommProfile(name="x", latency=LatencySpec(mean_s=1.0)))
    ch.views["uav"].candidates["C001"] = cand(status="pending")
    ch.sync("uav", 2.0, pose(1.0), NEAR)
    ch.views["uav"].candidates["C001"].status = "rejected"  # changes after sending do not travel
    ch.deliver_until(3.0)
    assert ch.views["ugv"].candidates["C001"].status == "pending"


def test_older_sync_does_not_overwrite_teammate_pose():
    ch = channel()
    ch.links[("uav", "ugv")] = ScriptedLink(3.0, 1.0)  # the second sync overtakes the first
    ch.views["uav"].candidates["C001"] = cand(status="pending")
    ch.sync("uav", 10.0, pose(1.0), NEAR)  # arrives at 13
    ch.views["uav"].candidates["C001"].status = "arrived"
    ch.sync("uav", 11.0, pose(2.0), NEAR)  # arrives at 12
    assert ch.next_arrival_s() == 12.0
    assert ch.deliver_until(12.0) == [Arrival("ugv", "sync", True)]
    view = ch.views["ugv"]
    assert view.teammate_pose == pose(2.0) and view.teammate_info_s == 11.0
    assert view.candidates["C001"].status == "arrived"
    # the stale sync arrives later: neither the pose nor the candidate goes back
    assert ch.deliver_until(13.0) == [Arrival("ugv", "sync", False)]
    assert view.teammate_pose == pose(2.0) and view.teammate_info_s == 11.0
    assert view.candidates["C001"].status == "arrived"


def test_newer_sync_updates_teammate_pose():
    ch = channel()
    ch.links[("ugv", "uav")] = ScriptedLink(0.5, 0.5)
    ch.sync("ugv", 1.0, pose(7.0), NEAR)
    ch.sync("ugv", 2.0, pose(8.0), NEAR)
    ch.deliver_until(1.5)
    assert ch.views["uav"].teammate_pose == pose(7.0) and ch.views["uav"].teammate_info_s == 1.0
    ch.deliver_until(2.5)
    assert ch.views["uav"].teammate_pose == pose(8.0) and ch.views["uav"].teammate_info_s == 2.0


def test_deliveries_come_in_arrival_order():
    ch = channel()
    ch.links[("uav", "ugv")] = ScriptedLink(2.0, 0.5, 1.0)
    ch.message("uav", 0.0, "first", NEAR)   # arrives 2.0
    ch.message("uav", 0.0, "second", NEAR)  # arrives 0.5
    ch.message("uav", 0.0, "third", NEAR)   # arrives 1.0
    arrivals = ch.deliver_until(5.0)
    assert [a.message.text for a in arrivals] == ["second", "third", "first"]
    assert [m.delivered_sim_time_s for m in ch.views["ugv"].messages] == [0.5, 1.0, 2.0]


def test_dropped_sync_changes_nothing():
    ch = channel()
    ch.links[("uav", "ugv")] = ScriptedLink("loss")
    ch.views["uav"].candidates["C001"] = cand()
    ch.sync("uav", 4.0, pose(9.0), NEAR)
    assert ch.next_arrival_s() == math.inf
    assert ch.deliver_until(100.0) == []
    assert ch.views["ugv"].candidates == {} and ch.views["ugv"].teammate_info_s == 0.0
    assert ch.ledger[0].drop_reason == "loss" and ch.ledger[0].arrive_s is None and ch.ledger[0].delay_s is None


# ----- messages ----------------------------------------------------------------------------------
def test_message_appended_with_delivered_time():
    ch = channel()
    ch.links[("uav", "ugv")] = ScriptedLink(0.75)
    ch.message("uav", 3.0, "target is red", NEAR)
    (entry,) = ch.ledger
    assert entry.kind == "message" and entry.size_bytes == len(b"target is red") + MESSAGE_OVERHEAD_BYTES
    (arrival,) = ch.deliver_until(4.0)
    expected = MessageRecord(sender="uav", receiver="ugv", text="target is red", sent_sim_time_s=3.0,
                             delivered_sim_time_s=3.75)
    assert arrival == Arrival("ugv", "message", True, expected)
    assert ch.views["ugv"].messages == [expected]
    assert ch.views["uav"].messages == []
    # messages carry no knowledge: pose and candidates stay
    assert ch.views["ugv"].teammate_info_s == 0.0 and ch.views["ugv"].candidates == {}


def test_messages_accumulate_on_ideal_link():
    ch = channel()
    ch.message("ugv", 1.0, "a", NEAR)
    ch.message("ugv", 2.0, "b", NEAR)
    ch.deliver_until(2.0)
    assert [(m.text, m.sent_sim_time_s, m.delivered_sim_time_s) for m in ch.views["uav"].messages] == [
        ("a", 1.0, 1.0), ("b", 2.0, 2.0)]


# ----- ledger and stats ------------------------------------------------------------------------------
def busy_channel(seed: int = 3) -> Channel:
    prof = CommProfile(name="mixed", latency=LatencySpec(mean_s=0.2, jitter_s=0.05), loss=LossSpec(model="bernoulli", p=0.3),
                       range=RangeSpec(max_range_m=200.0, nlos_loss=0.5), blackouts=[Blackout(start_s=20.0, end_s=30.0)])
    ch = channel(prof, seed)
    for i in range(200):
        t = i * 0.25
        sender = "uav" if i % 2 else "ugv"
        geometry = (250.0 if i % 11 == 0 else 50.0, i % 5 != 0)
        if i % 7 == 0:
            ch.message(sender, t, f"note {i}", geometry)
        else:
            if i % 3 == 0:
                ch.views[sender].candidates[f"C{i:03d}"] = cand(f"C{i:03d}", t=t)
            ch.sync(sender, t, pose(float(i)), geometry, kind="beacon" if i % 4 == 0 else "sync")
        ch.deliver_until(t)
    return ch


def test_ledger_records_every_transmission():
    ch = busy_channel()
    assert len(ch.ledger) == 200
    assert [e.seq for e in ch.ledger] == list(range(1, 201))
    assert {e.kind for e in ch.ledger} == {"sync", "beacon", "message"}
    assert all(e.size_bytes > 0 for e in ch.ledger)
    assert {e.drop_reason for e in ch.ledger if not e.delivered} == {"blackout", "out_of_range", "nlos", "loss"}
    for e in ch.ledger:
        assert e.receiver != e.sender
        if e.delivered:
            assert e.drop_reason is None and e.arrive_s >= e.sent_s
            assert e.delay_s == pytest.approx(e.arrive_s - e.sent_s, abs=2e-4)
        else:
            assert e.arrive_s is None and e.delay_s is None
        if 20.0 <= e.sent_s < 30.0:
            assert e.drop_reason == "blackout"


def test_sync_size_is_the_packed_payload():
    ch = channel()
    ch.views["uav"].candidates["C001"] = cand()
    p = pose(1.0, 2.0)
    ch.sync("uav", 1.5, p, NEAR)
    c = ch.views["uav"].candidates["C001"]
    expected = len(msgpack.packb({"candidates": [msgspec.to_builtins(c)], "pose": msgspec.to_builtins(p), "t": 1.5}))
    assert ch.ledger[0].size_bytes == expected
    ch.views["uav"].candidates["C002"] = cand("C002")
    ch.sync("uav", 2.0, p, NEAR)
    assert ch.ledger[1].size_bytes > ch.ledger[0].size_bytes  # more knowledge, bigger sync


def test_stats_count_by_reason():
    ch = busy_channel()
    ch.deliver_until(1e9)
    truth = [cand(f"C{i:03d}") for i in range(0, 200, 3) if i % 7]
    stats = ch.stats(truth)
    delivered = [e for e in ch.ledger if e.delivered]
    assert stats.profile == "mixed"
    assert stats.sent == len(ch.ledger) == 200
    assert stats.delivered == len(delivered)
    expected: dict[str, int] = {}
    for e in ch.ledger:
        if not e.delivered:
            expected[e.drop_reason] = expected.get(e.drop_reason, 0) + 1
    assert stats.dropped == expected
    assert stats.delivered + sum(stats.dropped.values()) == stats.sent
    assert stats.delivery_rate == pytest.approx(stats.delivered / stats.sent, abs=1e-4)
    assert stats.bytes_sent == sum(e.size_bytes for e in ch.ledger)
    delays = [e.delay_s for e in delivered]
    assert stats.mean_delay_s == pytest.approx(sum(delays) / len(delays), abs=1e-4)
    assert stats.max_delay_s == max(delays)
    known = set(ch.views["ugv"].candidates)
    assert stats.candidates_delivered == sum(c.candidate_id in known for c in truth)
    assert stats.candidates_lost == sum(c.candidate_id not in known for c in truth)
    assert stats.candidates_delivered + stats.candidates_lost == len(truth)


def test_stats_candidates_lost():
    ch = channel()
    ch.links[("uav", "ugv")] = ScriptedLink(0.1, "loss")
    ch.views["uav"].candidates["C001"] = cand("C001")
    ch.sync("uav", 1.0, pose(0.0), NEAR)  # carries C001
    ch.views["uav"].candidates["C002"] = cand("C002")
    ch.sync("uav", 2.0, pose(0.0), NEAR)  # carries C001 and C002: lost
    ch.deliver_until(10.0)
    stats = ch.stats([cand("C001"), cand("C002")])
    assert stats.candidates_delivered == 1 and stats.candidates_lost == 1
    assert stats.sent == 2 and stats.delivered == 1 and stats.dropped == {"loss": 1}
    assert stats.delivery_rate == 0.5


def test_stats_of_an_empty_channel():
    stats = channel().stats([])
    assert stats.sent == 0 and stats.delivered == 0 and stats.dropped == {}
    assert stats.delivery_rate is None and stats.mean_delay_s is None and stats.max_delay_s is None
    assert stats.bytes_sent == 0 and stats.candidates_lost == 0
    assert stats.mean_info_age_s == {"uav": None, "ugv": None}


# ----- information age ------------------------------------------------------------------------------
def test_info_age_and_its_mean_in_stats():
    ch = channel()
    assert ch.info_age("ugv", 7.25) == 7.25  # since the initial exchange at t = 0
    ch.links[("uav", "ugv")] = ScriptedLink(0.5)
    ch.sync("uav", 10.0, pose(1.0), NEAR)
    assert ch.info_age("ugv", 10.2) == 10.2  # not arrived yet
    ch.deliver_until(10.5)
    assert ch.info_age("ugv", 12.0) == 2.0
    assert ch.info_age("ugv", 13.5) == 3.5
    assert ch.info_age("uav", 4.0) == 4.0
    stats = ch.stats([])
    assert stats.mean_info_age_s["ugv"] == pytest.approx((7.25 + 10.2 + 2.0 + 3.5) / 4, abs=1e-3)
    assert stats.mean_info_age_s["uav"] == 4.0


def test_info_age_unknown_is_none_and_not_averaged():
    ch = channel()
    ch.views["uav"].teammate_info_s = None
    assert ch.info_age("uav", 5.0) is None
    assert ch.stats([]).mean_info_age_s == {"uav": None, "ugv": None}


# ----- determinism and geometry -----------------------------------------------------------------------
@pytest.mark.parametrize("name", ["lossy", "bursty", "long-range"])
def test_channel_same_seed_same_ledger(name):
    def run(seed: int) -> list:
        ch = channel(load_profile(name), seed)
        for i in range(300):
            ch.sync("uav" if i % 2 else "ugv", i * 0.5, pose(float(i)), (float(i % 300), i % 4 != 0))
        return list(ch.ledger)

    assert run(5) == run(5)
    assert run(5) != run(6)


def test_geometry_reaches_the_link():
    ch = channel(load_profile("long-range"))
    ch.sync("uav", 1.0, pose(0.0), (300.0, True))
    ch.sync("ugv", 1.0, pose(0.0), (300.0, True))
    assert [e.drop_reason for e in ch.ledger] == ["out_of_range", "out_of_range"]
    ch.sync("uav", 2.0, pose(0.0), (100.0, True))
    assert ch.ledger[-1].delivered


# ----- end to end -------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def lossy_records():
    from agos import Env
    from agos.agents.registry import make_policy
    from agos.world.episodes.sampling import sample_episode
    from agos.world.sim.scene import Scene
    from agos.world.towns.asset import open_town

    town = open_town("grid-s7")
    with Scene(town.layout, look="flat") as scene:
        spec = sample_episode(town, scene, "easy", 0, seed=1)
        records = []
        for _ in range(2):  # an Env each: the second renders the episode's setup again
            with Env(spec, EpisodeConfig(look="flat", comm=load_profile("lossy")), run_id="links", worker_id="w",
                     scene=scene, town=town) as env:
                records.append(env.play({role: make_policy("heuristic", role) for role in ("uav", "ugv")}))
    return records


def test_episode_is_deterministic_under_lossy_link(lossy_records):
    a, b = lossy_records
    assert msgspec.structs.replace(a, wall_time_s=0.0) == msgspec.structs.replace(b, wall_time_s=0.0)


def test_episode_link_stats_match_ledger(lossy_records):
    rec = lossy_records[0]
    assert rec.status == "finished" and rec.comm_profile == "lossy"
    assert rec.link is not None and rec.link.profile == "lossy"
    assert rec.link.sent == len(rec.ledger) > 0
    kinds = {e.kind for e in rec.ledger}
    assert {"sync", "beacon"} <= kinds
    assert rec.link.delivered == sum(e.delivered for e in rec.ledger)
    assert rec.link.delivered + sum(rec.link.dropped.values()) == rec.link.sent
    assert set(rec.link.dropped) <= {"loss"}  # lossy: Bernoulli loss only
    assert rec.link.bytes_sent == sum(e.size_bytes for e in rec.ledger)
    assert [e.seq for e in rec.ledger] == list(range(1, len(rec.ledger) + 1))
    assert all(e.size_bytes > 0 for e in rec.ledger)
    # beacons go out every beacon_s of sim time, from each role
    beacon_s = load_profile("lossy").beacon_s
    for role in ("uav", "ugv"):
        times = [e.sent_s for e in rec.ledger if e.kind == "beacon" and e.sender == role]
        assert times == pytest.approx([beacon_s * (k + 1) for k in range(len(times))])
        assert len(times) in (int(rec.sim_time_s // beacon_s), int(rec.sim_time_s // beacon_s) - 1)
