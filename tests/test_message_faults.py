"""Message faults as link stages (agos.runtime.links ``duplicate`` and ``corruption``, docs/COMMS.md
"Message faults"): what the channel delivers and records, that the stages keep to their own random
streams (every older profile replays exactly as before), and the configuration hash.

Statistical checks use a 99.9 % Wilson interval, as tests/test_links.py does.
"""

from __future__ import annotations

import hashlib
import math
import string
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from agos.deploy.run.sweep import with_param
from agos.runtime.episode_config import EpisodeConfig, config_hash
from agos.runtime.links import (
    IDEAL,
    PRINTABLE,
    CommProfile,
    CorruptionSpec,
    DuplicateSpec,
    LatencySpec,
    LossSpec,
    ProfileError,
    corrupt_text,
    links_for,
    load_profile,
)
from agos.runtime.schemas import Candidate, Pose
from agos.world.sim.comms import STATUS_RANK, Channel, RoleView, sync_payload

Z999 = 3.2905
NEAR = (10.0, True)


def wilson(k: int, n: int, z: float = Z999) -> tuple[float, float]:
    p = k / n
    denom = 1 + z * z / n
    centre = (p + z * z / (2 * n)) / denom
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / denom
    return centre - half, centre + half


def assert_rate(k: int, n: int, p: float) -> None:
    lo, hi = wilson(k, n)
    assert lo <= p <= hi, f"rate {k}/{n} = {k / n:.4f}: 99.9 % interval [{lo:.4f}, {hi:.4f}] excludes {p}"


def pose(x: float, y: float = 0.0) -> Pose:
    return Pose(position_world_m=(x, y, 0.0), yaw_rad=0.0)


def cand(cid: str, status: str) -> Candidate:
    return Candidate(candidate_id=cid, cell="B2", polygon_world_m=[(0.0, 0.0), (1.0, 0.0), (1.0, 1.0)],
                     center_world_m=(0.5, 0.5), status=status, created_sim_time_s=0.0)


START = {"uav": pose(0.0), "ugv": pose(50.0)}


def profile(**sections) -> CommProfile:
    return CommProfile(name="test", **sections)


# ----- (a) syncs merge the same whatever their order or duplication --------------------------------
@st.composite
def sync_sets(draw):
    """A set of sync payloads from one sender (distinct send times; each candidate goes pending ->
    arrived -> one final status) and an arrival order in which each arrives at least once."""
    ids = [f"C{i:03d}" for i in range(1, draw(st.integers(1, 4)) + 1)]
    final = {cid: draw(st.sampled_from(["rejected", "confirmed", "false_confirm"])) for cid in ids}
    chain = {cid: ["pending", "arrived", final[cid]] for cid in ids}
    times = draw(st.lists(st.integers(1, 100_000), min_size=1, max_size=6, unique=True))
    payloads = []
    for k in times:
        held = draw(st.dictionaries(st.sampled_from(ids), st.integers(0, 2)))
        where = draw(st.tuples(st.floats(-500, 500), st.floats(-500, 500)))
        payloads.append(sync_payload([cand(cid, chain[cid][rank]) for cid, rank in sorted(held.items())],
                                     pose(*where), k / 10))
    order = list(draw(st.permutations(range(len(payloads)))))
    for _ in range(draw(st.integers(0, 8))):  # duplicates, anywhere
        order.insert(draw(st.integers(0, len(order))), draw(st.integers(0, len(payloads) - 1)))
    return payloads, order


def received(payloads: list[dict], order: list[int]) -> RoleView:
    view = RoleView(teammate_pose=START["uav"], teammate_info_s=0.0)  # as the Channel starts it
    for i in order:
        view.receive_sync(payloads[i])
    return view


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(sync_sets())
def test_sync_merge_is_order_and_duplicate_independent(case):
    payloads, order = case
    view = received(payloads, order)
    best: dict[str, Candidate] = {}
    for p in payloads:
        for c in p["candidates"]:
            if c.candidate_id not in best or STATUS_RANK[c.status] > STATUS_RANK[best[c.candidate_id].status]:
                best[c.candidate_id] = c
    assert view.candidates == best  # per candidate, the status of the highest rank heard
    newest = max(payloads, key=lambda p: p["t"])
    assert (view.teammate_pose, view.teammate_info_s) == (newest["pose"], newest["t"])
    once = received(payloads, list(range(len(payloads))))
    assert (view.candidates, view.teammate_pose, view.teammate_info_s) == (
        once.candidates, once.teammate_pose, once.teammate_info_s)


def test_receive_sync_again_changes_nothing():
    view = RoleView()
    payload = sync_payload([cand("C001", "arrived")], pose(3.0), 4.0)
    assert view.receive_sync(payload) is True
    assert view.receive_sync(payload) is False
    assert view.candidates == {"C001": cand("C001", "arrived")} and view.teammate_info_s == 4.0


# ----- the profile sections ------------------------------------------------------------------------
def test_faults_are_off_by_default_and_make_a_link_non_ideal():
    assert IDEAL.duplicate == DuplicateSpec(p=0.0, delay_s=0.05)
    assert IDEAL.corruption == CorruptionSpec(char_error_rate=0.0)
    assert IDEAL.ideal
    assert not profile(duplicate={"p": 0.01}).ideal
    assert not profile(corruption={"char_error_rate": 1e-4}).ideal
    assert profile(duplicate={"delay_s": 2.0}).ideal  # a delay without duplicates is nothing
    ch = Channel(profile(duplicate={"p": 0.01}), 1, dict(START))
    assert ch.next_beacon_s() == 5.0  # beacons run on a link with faults


@pytest.mark.parametrize("name,check", [
    ("duplicating", lambda p: p.duplicate.p == 0.05 and p.duplicate.delay_s == 0.05 and p.latency.mean_s == 0.05),
    ("garbled", lambda p: p.corruption.char_error_rate == 0.01 and p.duplicate.p == 0),
])
def test_shipped_fault_profiles(name, check):
    prof = load_profile(name)
    assert prof.name == name and prof.description and not prof.ideal
    assert check(prof)


def test_fault_params_are_sweep_params():
    assert with_param(IDEAL, "duplicate.p", 0.2).duplicate.p == 0.2
    assert with_param(IDEAL, "duplicate.delay_s", 0.5).duplicate.delay_s == 0.5
    swept = with_param(load_profile("garbled"), "corruption.char_error_rate", 0.05)
    assert swept.corruption.char_error_rate == 0.05 and swept.name == "garbled[corruption.char_error_rate=0.05]"
    with pytest.raises(ValueError, match=r"duplicate\.p=1\.5"):
        with_param(IDEAL, "duplicate.p", 1.5)
    with pytest.raises(ValueError, match="not a field"):
        with_param(IDEAL, "corruption.rate", 0.1)


# ----- (e) bad profiles ----------------------------------------------------------------------------
@pytest.mark.parametrize("text,field", [
    ("[duplicate]\np = -0.1\n", "duplicate.p"),
    ("[duplicate]\np = 0.1\ndelay_s = -1.0\n", "duplicate.delay_s"),
    ("[duplicate]\nprobability = 0.1\n", "duplicate.probability"),
    ("[corruption]\nchar_error_rate = 1.5\n", "corruption.char_error_rate"),
    ("[garbling]\nchar_error_rate = 0.1\n", "garbling"),
])
def test_bad_fault_section_is_one_line_naming_file_and_field(tmp_path: Path, text, field):
    path = tmp_path / "bad.toml"
    path.write_text(text)
    with pytest.raises(ProfileError) as exc:
        load_profile(path)
    msg = str(exc.value)
    assert "\n" not in msg
    assert str(path) in msg and f": {field}: " in msg


# ----- (b) duplicates ------------------------------------------------------------------------------
def play(prof: CommProfile, seed: int, n: int = 300) -> Channel:
    """A fixed mix of syncs, beacons and messages both ways, delivered as it goes."""
    ch = Channel(prof, seed, dict(START))
    ch.views["uav"].candidates["C001"] = cand("C001", "pending")
    for i in range(n):
        t = i * 0.7
        role = ("uav", "ugv")[i % 2]
        geometry = (float((i * 37) % 320), i % 3 != 0)
        if i % 5 == 4:
            ch.message(role, t, f"message {i}: " + "the red car is parked by the corner. " * (i % 4), geometry)
        else:
            ch.sync(role, t, pose(float(i)), geometry, kind="beacon" if i % 3 == 0 else "sync")
        ch.deliver_until(t)
    ch.deliver_until(1e9)
    return ch


DUPLICATING = profile(latency=LatencySpec(mean_s=0.1, jitter_s=0.03), loss=LossSpec(model="bernoulli", p=0.2),
                      duplicate=DuplicateSpec(p=0.3, delay_s=0.25))


def test_duplicates_replay_and_are_counted():
    a, b = play(DUPLICATING, 9), play(DUPLICATING, 9)
    assert a.ledger == b.ledger
    assert a.views["ugv"].messages == b.views["ugv"].messages
    assert play(DUPLICATING, 10).ledger != a.ledger
    copies = [i for i, e in enumerate(a.ledger) if e.fault == "duplicate"]
    assert copies
    for i in copies:  # each copy right after its delivered original
        copy, orig = a.ledger[i], a.ledger[i - 1]
        assert orig.delivered and orig.fault is None and copy.delivered and copy.drop_reason is None
        assert copy.seq == orig.seq + 1
        assert (copy.kind, copy.sender, copy.receiver, copy.sent_s, copy.size_bytes) == (
            orig.kind, orig.sender, orig.receiver, orig.sent_s, orig.size_bytes)
        assert copy.arrive_s == pytest.approx(orig.arrive_s + 0.25, abs=2e-4)
    assert [e.seq for e in a.ledger] == list(range(1, len(a.ledger) + 1))
    stats = a.stats([cand("C001", "pending")])
    made = [e for e in a.ledger if e.fault != "duplicate"]
    assert stats.duplicated == len(copies)
    assert stats.sent == len(made) and stats.delivered == sum(e.delivered for e in made)
    assert stats.bytes_sent == sum(e.size_bytes for e in made)
    assert stats.corrupted == 0
    # the message list holds each duplicated message twice
    sent = sum(e.kind == "message" and e.receiver == "ugv" and e.delivered for e in a.ledger)
    assert len(a.views["ugv"].messages) == sent


def test_duplicate_rate_and_delay_on_the_link():
    n, p = 20_000, 0.05
    lk = links_for(profile(latency=LatencySpec(mean_s=0.05, jitter_s=0.02), loss=LossSpec(model="bernoulli", p=0.3),
                           duplicate=DuplicateSpec(p=p, delay_s=0.05)), 4)[("uav", "ugv")]
    res = [lk.transmit(i * 0.1, 100) for i in range(n)]
    delivered = [d for d in res if d.delivered]
    dups = [d for d in delivered if d.duplicate_arrive_s is not None]
    assert all(d.duplicate_arrive_s is None and d.corrupt_seed is None for d in res if not d.delivered)
    assert_rate(len(dups), len(delivered), p)  # a share of what was delivered
    assert all(d.duplicate_arrive_s == pytest.approx(d.arrive_s + 0.05) for d in dups)


def test_duplicates_leave_the_deliveries_and_final_views_alone():
    """The fault stream is separate: with duplicates on, every original is delivered as without them,
    the syncs merge to the same views, and each message arrives twice."""
    base = profile(latency=LatencySpec(mean_s=0.1, jitter_s=0.03), loss=LossSpec(model="bernoulli", p=0.2))
    always = base.model_copy(update={"duplicate": DuplicateSpec(p=1.0, delay_s=0.3)})
    plain, doubled = play(base, 3), play(always, 3)
    originals = [e for e in doubled.ledger if e.fault is None]
    key = [(e.kind, e.sender, e.sent_s, e.size_bytes, e.delivered, e.arrive_s, e.drop_reason) for e in plain.ledger]
    assert [(e.kind, e.sender, e.sent_s, e.size_bytes, e.delivered, e.arrive_s, e.drop_reason) for e in originals] == key
    assert len(doubled.ledger) - len(plain.ledger) == sum(e.delivered for e in plain.ledger)
    for role in ("uav", "ugv"):
        v, w = plain.views[role], doubled.views[role]
        assert (v.candidates, v.teammate_pose, v.teammate_info_s) == (w.candidates, w.teammate_pose, w.teammate_info_s)
        assert sorted(m.text for m in w.messages) == sorted(2 * [m.text for m in v.messages])


# ----- (c) corruption ------------------------------------------------------------------------------
TEXT = ("The red sedan is parked at the corner of the second block, next to a bus stop. " * 2500)


@pytest.mark.parametrize("rate", [1e-3, 1e-2, 0.3])
def test_char_error_rate_is_observed(rate):
    out = corrupt_text(TEXT, rate, 12345)
    assert len(out) == len(TEXT)
    changed = [(a, b) for a, b in zip(TEXT, out, strict=True) if a != b]
    assert_rate(len(changed), len(TEXT), rate)
    assert all(b in PRINTABLE for _, b in changed)


def test_every_character_can_be_hit_and_always_changes():
    text = PRINTABLE + "äö€\n\t"
    out = corrupt_text(text, 1.0, 7)
    assert all(a != b and b in PRINTABLE for a, b in zip(text, out, strict=True))
    hits = {corrupt_text("a", 1.0, s) for s in range(3000)}
    assert hits == set(PRINTABLE) - {"a"}  # any other printable character, never itself


def test_rate_zero_changes_nothing_and_the_seed_decides():
    assert corrupt_text(TEXT, 0.0, 3) == TEXT
    assert corrupt_text("", 0.5, 3) == ""
    assert corrupt_text(TEXT, 0.01, 3) == corrupt_text(TEXT, 0.01, 3)
    assert corrupt_text(TEXT, 0.01, 3) != corrupt_text(TEXT, 0.01, 4)
    lk = links_for(profile(corruption=CorruptionSpec(char_error_rate=0.0)), 1)[("uav", "ugv")]
    assert all(lk.transmit(i * 1.0, 80).corrupt_seed is None for i in range(100))


GARBLED = profile(latency=LatencySpec(mean_s=0.05, jitter_s=0.02), corruption=CorruptionSpec(char_error_rate=0.05))


def test_corrupted_messages_in_the_channel():
    a, b = play(GARBLED, 21), play(GARBLED, 21)
    assert a.ledger == b.ledger and a.views["ugv"].messages == b.views["ugv"].messages  # same seed, same text
    clean = play(GARBLED.model_copy(update={"corruption": CorruptionSpec()}), 21)
    marked = [e for e in a.ledger if e.fault == "corrupted"]
    assert marked and all(e.kind == "message" and e.delivered for e in marked)
    assert a.stats([]).corrupted == len(marked)
    assert clean.stats([]).corrupted == 0 and all(e.fault is None for e in clean.ledger)
    # delivered messages differ from the clean run's exactly where the ledger says so
    for role in ("uav", "ugv"):
        got, sent = a.views[role].messages, clean.views[role].messages
        assert [m.sent_sim_time_s for m in got] == [m.sent_sim_time_s for m in sent]
        faulty = {e.sent_s for e in marked if e.receiver == role}
        for m, c in zip(got, sent, strict=True):
            assert (m.text != c.text) == (round(m.sent_sim_time_s, 4) in faulty)
            assert len(m.text) == len(c.text)
    # syncs and beacons are never corrupted: the views are the clean run's
    for role in ("uav", "ugv"):
        assert a.views[role].candidates == clean.views[role].candidates
        assert a.views[role].teammate_pose == clean.views[role].teammate_pose


def test_a_corrupted_message_that_is_duplicated_arrives_twice_the_same():
    prof = profile(corruption=CorruptionSpec(char_error_rate=0.2), duplicate=DuplicateSpec(p=1.0, delay_s=1.0))
    ch = Channel(prof, 2, dict(START))
    ch.message("uav", 1.0, "hello ugv, candidate C001 is the red sedan", NEAR)
    first, copy = ch.ledger
    assert (first.fault, copy.fault) == ("corrupted", "duplicate")
    ch.deliver_until(10.0)
    texts = [m.text for m in ch.views["ugv"].messages]
    assert len(texts) == 2 and texts[0] == texts[1] != "hello ugv, candidate C001 is the red sedan"
    assert [m.delivered_sim_time_s for m in ch.views["ugv"].messages] == [1.0, 2.0]


# ----- (d) profiles without faults replay exactly as before the fault stages ------------------------
def fixed_sequence(name: str, seed: int = 7, n: int = 400) -> list[tuple[bool, str | None, str | None]]:
    links = links_for(load_profile(name), seed)
    out = []
    for i in range(n):
        for direction in (("uav", "ugv"), ("ugv", "uav")):
            d = links[direction].transmit(i * 0.05, 200 + (i * 7919) % 3000, distance_m=float((i * 37) % 320),
                                          line_of_sight=i % 3 != 0)
            assert d.duplicate_arrive_s is None and d.corrupt_seed is None
            out.append((d.delivered, None if d.arrive_s is None else d.arrive_s.hex(), d.reason))
    return out


# Recorded on the tree before the fault stages existed: sha256 of the repr of the sequence (floats
# as hex, exact), the number delivered, and the first delivery's arrival.
PINNED_DELIVERIES = {
    "lossy": ("ea267a5ef164f3ed", 624, "0x1.f92f274ac0d96p-4"),
    "bursty": ("abe2e7cfb61120c0", 672, "0x1.58120d55cfdeap-4"),
    "narrowband": ("ddffd5168dd2f15d", 342, "0x1.16312d3efa065p-2"),
}


@pytest.mark.parametrize("name", sorted(PINNED_DELIVERIES))
def test_existing_profiles_deliver_exactly_as_before(name):
    seq = fixed_sequence(name)
    digest, delivered, first = PINNED_DELIVERIES[name]
    assert seq[0][1] == first
    assert sum(d for d, _, _ in seq) == delivered
    assert hashlib.sha256(repr(seq).encode()).hexdigest()[:16] == digest


PINNED_LEDGERS = {"lossy": ("add1d49840c5f2ca", 161), "bursty": ("7ee27c66c2334e3d", 163),
                  "narrowband": ("a3758732f587a362", 200)}


def pinned_play(name: str) -> Channel:
    """The channel script the ledgers above were recorded with."""
    ch = Channel(load_profile(name), 5, dict(START))
    ch.views["uav"].candidates["C001"] = cand("C001", "pending")
    for i in range(200):
        t = i * 0.7
        role = ("uav", "ugv")[i % 2]
        geometry = (float((i * 37) % 320), i % 3 != 0)
        if i % 5 == 4:
            ch.message(role, t, f"message {i} " * (i % 7), geometry)
        else:
            ch.sync(role, t, pose(float(i)), geometry, kind="beacon" if i % 3 == 0 else "sync")
        ch.deliver_until(t)
    ch.deliver_until(1e9)
    return ch


@pytest.mark.parametrize("name", sorted(PINNED_LEDGERS))
def test_existing_profiles_keep_their_channel_ledgers(name):
    ch = pinned_play(name)
    rows = [(e.seq, e.kind, e.sender, e.receiver, e.sent_s, e.size_bytes, e.delivered, e.arrive_s, e.delay_s,
             e.drop_reason) for e in ch.ledger]
    assert all(e.fault is None for e in ch.ledger)
    digest, delivered = PINNED_LEDGERS[name]
    assert sum(r[6] for r in rows) == delivered
    assert hashlib.sha256(repr(rows).encode()).hexdigest()[:16] == digest


# ----- the configuration hash ----------------------------------------------------------------------
# Measured before the fault sections existed (runtime/episode_config.py, HASHED_ONLY_WHEN_NOT).
DEFAULT_HASH, LOSSY_HASH = "b5a0190b18bf", "8db433fa82b0"


def test_config_hash_unchanged_without_faults():
    assert EpisodeConfig().config_hash() == DEFAULT_HASH
    assert EpisodeConfig(comm=load_profile("lossy")).config_hash() == LOSSY_HASH
    # a configuration stored before the sections existed hashes the same as the object read from it
    stored = EpisodeConfig(comm=load_profile("lossy")).model_dump(mode="json")
    del stored["comm"]["duplicate"], stored["comm"]["corruption"]
    assert config_hash(stored) == LOSSY_HASH
    assert EpisodeConfig.model_validate(stored).config_hash() == LOSSY_HASH


@pytest.mark.parametrize("update", [{"duplicate": DuplicateSpec(p=0.05)}, {"duplicate": DuplicateSpec(delay_s=0.1)},
                                    {"corruption": CorruptionSpec(char_error_rate=0.01)}])
def test_config_hash_sees_faults_that_are_set(update):
    comm = load_profile("lossy").model_copy(update=update)
    assert EpisodeConfig(comm=comm).config_hash() != LOSSY_HASH


def test_printable_is_printable_ascii():
    printable = "".join(sorted(c for c in string.printable if c not in "\t\n\r\x0b\x0c"))
    assert printable == PRINTABLE
