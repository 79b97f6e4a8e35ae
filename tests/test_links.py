"""The link models of agos.runtime.links: measured behaviour against the profile parameters.

Every test is seeded, so it is deterministic; the tolerances are the statistical ones a correct
model passes for (almost) any seed: 3 standard errors for means, a 99.9 % interval for rates.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from agos.runtime.links import (
    IDEAL,
    PROFILE_DIR,
    BandwidthSpec,
    Blackout,
    CommProfile,
    Delivery,
    LatencySpec,
    Link,
    LossSpec,
    ProfileError,
    RangeSpec,
    links_for,
    load_profile,
)

N = 20_000
Z999 = 3.2905  # two-sided 99.9 % normal quantile
PROFILE_NAMES = sorted(p.stem for p in PROFILE_DIR.glob("*.toml"))


def link(seed: int = 11, direction: tuple[str, str] = ("uav", "ugv"), **sections) -> Link:
    return links_for(CommProfile(name="test", **sections), seed)[direction]


def delays(lk: Link, n: int = N, dt: float = 0.01, size: int = 100) -> np.ndarray:
    out = []
    for i in range(n):
        t = i * dt
        d = lk.transmit(t, size)
        assert d.delivered and d.reason is None
        out.append(d.arrive_s - t)
    return np.array(out)


def wilson(k: int, n: int, z: float = Z999) -> tuple[float, float]:
    p = k / n
    denom = 1 + z * z / n
    centre = (p + z * z / (2 * n)) / denom
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / denom
    return centre - half, centre + half


def assert_rate(k: int, n: int, p: float) -> None:
    lo, hi = wilson(k, n)
    assert lo <= p <= hi, f"rate {k}/{n} = {k / n:.4f}: 99.9 % interval [{lo:.4f}, {hi:.4f}] excludes {p}"


# ----- latency -----------------------------------------------------------------------------------
@pytest.mark.parametrize("mean_s,jitter_s", [(0.15, 0.05), (1.0, 0.2)])
def test_normal_latency_mean_and_std(mean_s, jitter_s):
    d = delays(link(latency=LatencySpec(mean_s=mean_s, jitter_s=jitter_s, distribution="normal")))
    se = jitter_s / math.sqrt(N)
    assert abs(d.mean() - mean_s) < 3 * se
    assert d.std(ddof=1) == pytest.approx(jitter_s, rel=0.05)


def test_zero_jitter_latency_is_constant():
    d = delays(link(latency=LatencySpec(mean_s=0.25, jitter_s=0.0)), n=1000)
    assert np.allclose(d, 0.25, atol=1e-9)


def test_uniform_latency_bounds_and_std():
    mean_s, jitter_s = 0.4, 0.1
    d = delays(link(latency=LatencySpec(mean_s=mean_s, jitter_s=jitter_s, distribution="uniform")))
    eps = 1e-9  # arrive_s - t_send rounding
    assert d.min() >= mean_s - jitter_s - eps
    assert d.max() <= mean_s + jitter_s + eps
    # it really spreads over the whole interval
    assert d.min() < mean_s - 0.99 * jitter_s and d.max() > mean_s + 0.99 * jitter_s
    assert abs(d.mean() - mean_s) < 3 * (jitter_s / math.sqrt(3)) / math.sqrt(N)
    assert d.std(ddof=1) == pytest.approx(jitter_s / math.sqrt(3), rel=0.03)


def test_exponential_latency_mean():
    mean_s = 0.2
    d = delays(link(latency=LatencySpec(mean_s=mean_s, jitter_s=0.05, distribution="exponential")))
    assert d.min() >= 0
    assert abs(d.mean() - mean_s) < 3 * mean_s / math.sqrt(N)  # the std of an exponential is its mean
    assert d.std(ddof=1) == pytest.approx(mean_s, rel=0.05)  # jitter_s is ignored


@pytest.mark.parametrize("mean_s,jitter_s", [(0.3, 0.15), (0.1, 0.1)])
def test_lognormal_latency_mean_and_std(mean_s, jitter_s):
    d = delays(link(latency=LatencySpec(mean_s=mean_s, jitter_s=jitter_s, distribution="lognormal")))
    assert d.min() > 0
    assert abs(d.mean() - mean_s) < 3 * jitter_s / math.sqrt(N)
    # the sample std of a skewed distribution converges slowly: a looser (still ~4 SE) tolerance
    assert d.std(ddof=1) == pytest.approx(jitter_s, rel=0.08)


def test_lognormal_zero_mean_is_zero_delay():
    d = delays(link(latency=LatencySpec(mean_s=0.0, jitter_s=0.1, distribution="lognormal")), n=100)
    assert np.all(d == 0)


@pytest.mark.parametrize("distribution", ["normal", "uniform"])
def test_delays_never_negative_when_jitter_exceeds_mean(distribution):
    d = delays(link(latency=LatencySpec(mean_s=0.05, jitter_s=0.2, distribution=distribution)))
    assert d.min() >= 0
    assert np.sum(d == 0) > 0.1 * N  # a good part of the draws was clamped, none went negative


# ----- Bernoulli loss ----------------------------------------------------------------------------
def outcomes(lk: Link, n: int = N, **kw) -> list[Delivery]:
    return [lk.transmit(i * 0.01, 100, **kw) for i in range(n)]


@pytest.mark.parametrize("p", [0.05, 0.3, 0.7])
def test_bernoulli_loss_rate(p):
    res = outcomes(link(loss=LossSpec(model="bernoulli", p=p)))
    lost = [d for d in res if not d.delivered]
    assert {d.reason for d in lost} == {"loss"}
    assert all(d.arrive_s is None for d in lost)
    assert_rate(len(lost), N, p)


def test_bernoulli_losses_are_independent():
    p = 0.3
    lost = np.array([not d.delivered for d in outcomes(link(loss=LossSpec(model="bernoulli", p=p)))])
    # P(lost | previous lost) is p too (no bursts)
    after_loss = lost[1:][lost[:-1]]
    assert_rate(int(after_loss.sum()), len(after_loss), p)


def test_bernoulli_p0_never_drops_p1_always_drops():
    assert all(d.delivered for d in outcomes(link(loss=LossSpec(model="bernoulli", p=0.0)), n=5000))
    res = outcomes(link(loss=LossSpec(model="bernoulli", p=1.0)), n=5000)
    assert all(not d.delivered and d.reason == "loss" and d.arrive_s is None for d in res)


def test_no_loss_model_never_drops():
    assert all(d.delivered for d in outcomes(link(loss=LossSpec(model="none", p=1.0)), n=2000))


# ----- Gilbert-Elliott -----------------------------------------------------------------------------
def runs(mask: np.ndarray) -> list[int]:
    """Lengths of the runs of True in ``mask``, leaving out a run cut by the end of the sample."""
    lengths, cur = [], 0
    for x in mask:
        if x:
            cur += 1
        elif cur:
            lengths.append(cur)
            cur = 0
    return lengths


@pytest.mark.parametrize("p_gb,p_bg", [(0.1, 0.25), (0.02, 0.5)])
def test_gilbert_elliott_bursts_and_stationary_rate(p_gb, p_bg):
    n = 50_000
    spec = LossSpec(model="gilbert_elliott", p_good_to_bad=p_gb, p_bad_to_good=p_bg, loss_good=0.0, loss_bad=1.0)
    res = outcomes(link(loss=spec), n=n)
    assert {d.reason for d in res if not d.delivered} == {"loss"}
    lost = np.array([not d.delivered for d in res])
    # stationary loss rate; the chain is autocorrelated (lambda = 1 - p_gb - p_bg), which inflates the
    # variance of the sample mean by (1 + lambda) / (1 - lambda)
    pi_bad = p_gb / (p_gb + p_bg)
    lam = 1 - p_gb - p_bg
    se = math.sqrt(pi_bad * (1 - pi_bad) / n * (1 + lam) / (1 - lam))
    assert abs(lost.mean() - pi_bad) < 3.5 * se
    # burst length is geometric with mean 1 / p_bg (std sqrt(1 - p_bg) / p_bg)
    bursts = runs(lost)
    mean_burst = 1 / p_bg
    se_burst = math.sqrt(1 - p_bg) / p_bg / math.sqrt(len(bursts))
    assert abs(np.mean(bursts) - mean_burst) < 3.5 * se_burst
    # and the gaps between bursts have mean 1 / p_gb
    gaps = runs(~lost)[1:]
    se_gap = math.sqrt(1 - p_gb) / p_gb / math.sqrt(len(gaps))
    assert abs(np.mean(gaps) - 1 / p_gb) < 3.5 * se_gap


def test_gilbert_elliott_bursty_profile_loss_rate():
    """The deploy profile (lossy in both states): rate = pi_good * loss_good + pi_bad * loss_bad."""
    prof = load_profile("bursty")
    loss = prof.loss
    n = 50_000
    lk = links_for(prof, 3)[("uav", "ugv")]
    lost = np.array([not lk.transmit(i * 0.5, 200).delivered for i in range(n)])
    pi_bad = loss.p_good_to_bad / (loss.p_good_to_bad + loss.p_bad_to_good)
    expected = pi_bad * loss.loss_bad + (1 - pi_bad) * loss.loss_good
    lam = 1 - loss.p_good_to_bad - loss.p_bad_to_good
    se = math.sqrt(expected * (1 - expected) / n * (1 + lam) / (1 - lam))  # an upper bound for a hidden chain
    assert abs(lost.mean() - expected) < 3.5 * se
    # and losses cluster: a loss is followed by a loss far more often than the mean rate
    after_loss = lost[1:][lost[:-1]].mean()
    assert after_loss > 2 * expected


def test_gilbert_elliott_never_leaves_good_state():
    spec = LossSpec(model="gilbert_elliott", p_good_to_bad=0.0, p_bad_to_good=0.5, loss_good=0.0, loss_bad=1.0)
    assert all(d.delivered for d in outcomes(link(loss=spec), n=5000))


# ----- bandwidth -----------------------------------------------------------------------------------
def test_bandwidth_throughput_matches_cap_under_overload():
    bits_per_s, size, period = 80_000.0, 500, 0.04  # offered 12.5 kB/s against a 10 kB/s cap
    lk = link(bandwidth=BandwidthSpec(bits_per_s=bits_per_s, queue_bytes=5000),
              latency=LatencySpec(mean_s=0.1, jitter_s=0.01))
    res = [lk.transmit(i * period, size) for i in range(N)]
    got = [d for d in res if d.delivered]
    assert {d.reason for d in res if not d.delivered} == {"queue_full"}
    arrivals = np.array([d.arrive_s for d in got])
    span = arrivals.max() - arrivals.min()
    throughput = (len(got) - 1) * size / span
    assert throughput == pytest.approx(bits_per_s / 8, rel=0.02)
    # what does not fit is dropped: about 1 - cap / offered of the messages
    assert (N - len(got)) / N == pytest.approx(1 - (bits_per_s / 8) / (size / period), abs=0.01)


def test_bandwidth_no_latency_is_back_to_back():
    bits_per_s, size = 80_000.0, 500
    lk = link(bandwidth=BandwidthSpec(bits_per_s=bits_per_s, queue_bytes=10**9))
    res = [lk.transmit(i * 0.01, size) for i in range(2000)]  # 5x overload, unbounded queue
    assert all(d.delivered for d in res)
    arrivals = np.array([d.arrive_s for d in res])
    assert np.allclose(np.diff(arrivals), size * 8 / bits_per_s)
    assert arrivals[0] == pytest.approx(size * 8 / bits_per_s)


@pytest.mark.parametrize("size,bits_per_s,latency_s", [(1000, 80_000.0, 0.2), (32, 64_000.0, 0.0), (4000, 1e6, 0.05)])
def test_lone_message_serialization_delay(size, bits_per_s, latency_s):
    lk = link(bandwidth=BandwidthSpec(bits_per_s=bits_per_s), latency=LatencySpec(mean_s=latency_s))
    d = lk.transmit(3.0, size)
    assert d.delivered
    assert d.arrive_s == pytest.approx(3.0 + size * 8 / bits_per_s + latency_s, abs=1e-9)


def test_queue_full_drops_what_does_not_fit():
    size = 500
    lk = link(bandwidth=BandwidthSpec(bits_per_s=80_000.0, queue_bytes=5000))
    burst = [lk.transmit(0.0, size) for _ in range(30)]
    assert [d.delivered for d in burst] == [True] * 10 + [False] * 20
    assert {d.reason for d in burst[10:]} == {"queue_full"}
    assert [d.arrive_s for d in burst[:10]] == pytest.approx([0.05 * (i + 1) for i in range(10)])
    # once the queue has drained, messages fit again
    later = lk.transmit(1.0, size)
    assert later.delivered and later.arrive_s == pytest.approx(1.05)
    # a message larger than the whole queue never fits
    assert lk.transmit(5.0, 5001).reason == "queue_full"


def test_bandwidth_below_cap_never_drops_or_queues():
    bits_per_s, size, period = 80_000.0, 500, 0.1  # 5 kB/s offered, 10 kB/s cap
    lk = link(bandwidth=BandwidthSpec(bits_per_s=bits_per_s, queue_bytes=600), latency=LatencySpec(mean_s=0.2))
    for i in range(N // 4):
        t = i * period
        d = lk.transmit(t, size)
        assert d.delivered, (i, d)
        assert d.arrive_s == pytest.approx(t + size * 8 / bits_per_s + 0.2, abs=1e-9)


# ----- range and line of sight -------------------------------------------------------------------
def test_beyond_max_range_always_drops():
    lk = link(range=RangeSpec(max_range_m=100.0))
    far = outcomes(lk, n=5000, distance_m=100.5)
    assert all(not d.delivered and d.reason == "out_of_range" for d in far)
    near = outcomes(lk, n=5000, distance_m=99.5)
    assert all(d.delivered for d in near)
    assert lk.transmit(1e6, 100, distance_m=100.0).delivered  # the limit itself is in range


@pytest.mark.parametrize("nlos_loss", [0.1, 0.6])
def test_nlos_loss_rate(nlos_loss):
    lk = link(range=RangeSpec(max_range_m=500.0, nlos_loss=nlos_loss))
    res = outcomes(lk, distance_m=50.0, line_of_sight=False)
    lost = [d for d in res if not d.delivered]
    assert {d.reason for d in lost} == {"nlos"}
    assert_rate(len(lost), N, nlos_loss)


def test_line_of_sight_never_drops_for_nlos():
    lk = link(range=RangeSpec(nlos_loss=1.0))
    assert all(d.delivered for d in outcomes(lk, n=5000, distance_m=10.0, line_of_sight=True))
    assert all(d.reason == "nlos" for d in outcomes(lk, n=100, distance_m=10.0, line_of_sight=False))


def test_nlos_and_bernoulli_loss_combine():
    nlos, p = 0.4, 0.25
    lk = link(range=RangeSpec(nlos_loss=nlos), loss=LossSpec(model="bernoulli", p=p))
    res = outcomes(lk, line_of_sight=False)
    n_nlos = sum(d.reason == "nlos" for d in res)
    n_loss = sum(d.reason == "loss" for d in res)
    assert_rate(n_nlos, N, nlos)
    assert_rate(n_loss, N - n_nlos, p)  # loss applies to what survived the nlos stage


# ----- blackouts -----------------------------------------------------------------------------------
def test_blackouts_drop_inside_only():
    intervals = [(10.0, 20.0), (50.0, 55.5)]
    lk = link(blackouts=[Blackout(start_s=a, end_s=b) for a, b in intervals])
    inside = outside = 0
    for i in range(10_000):
        t = i * 0.01 + 0.005  # never exactly on an interval boundary
        d = lk.transmit(t, 100)
        if any(a <= t < b for a, b in intervals):
            inside += 1
            assert not d.delivered and d.reason == "blackout" and d.arrive_s is None, t
        else:
            outside += 1
            assert d.delivered and d.arrive_s == t, t
    assert inside == 1550 and outside == 8450


def test_stage_order_blackout_range_nlos_loss():
    lk = link(blackouts=[Blackout(start_s=0.0, end_s=1.0)], range=RangeSpec(max_range_m=10.0, nlos_loss=1.0),
              loss=LossSpec(model="bernoulli", p=1.0))
    assert lk.transmit(0.5, 100, distance_m=20.0, line_of_sight=False).reason == "blackout"
    assert lk.transmit(1.5, 100, distance_m=20.0, line_of_sight=False).reason == "out_of_range"
    assert lk.transmit(2.5, 100, distance_m=5.0, line_of_sight=False).reason == "nlos"
    assert lk.transmit(3.5, 100, distance_m=5.0, line_of_sight=True).reason == "loss"


# ----- determinism -----------------------------------------------------------------------------------
def scenario(lk: Link, n: int = 3000) -> list[tuple[bool, float | None, str | None]]:
    """A fixed mix of times, sizes, distances and line of sight that reaches every stage of every profile."""
    out = []
    for i in range(n):
        t = i * 0.2  # 0 .. 600 s: crosses the blackout profile's intervals
        size = 200 + (i * 7919) % 3000
        distance = (i * 37) % 320  # crosses long-range's 250 m
        los = i % 3 != 0
        d = lk.transmit(t, size, distance_m=float(distance), line_of_sight=los)
        out.append((d.delivered, d.arrive_s, d.reason))
    return out


def stochastic(profile: CommProfile) -> bool:
    return profile.latency.jitter_s > 0 or profile.loss.model != "none" or profile.range.nlos_loss > 0


def test_profiles_cover_deterministic_and_stochastic():
    kinds = {name: stochastic(load_profile(name)) for name in PROFILE_NAMES}
    assert True in kinds.values() and False in kinds.values()


@pytest.mark.parametrize("name", PROFILE_NAMES)
def test_same_seed_is_bit_identical(name):
    prof = load_profile(name)
    for direction in (("uav", "ugv"), ("ugv", "uav")):
        a = scenario(links_for(prof, 42)[direction])
        b = scenario(links_for(load_profile(name), 42)[direction])
        assert a == b  # floats compared exactly


@pytest.mark.parametrize("name", PROFILE_NAMES)
def test_other_seed_differs_for_stochastic_profiles(name):
    prof = load_profile(name)
    a = scenario(links_for(prof, 42)[("uav", "ugv")])
    b = scenario(links_for(prof, 43)[("uav", "ugv")])
    if stochastic(prof):
        assert a != b
    else:
        assert a == b  # nothing random in it


@pytest.mark.parametrize("name", PROFILE_NAMES)
def test_directions_are_independent_streams(name):
    prof = load_profile(name)
    links = links_for(prof, 42)
    assert links[("uav", "ugv")] is not links[("ugv", "uav")]
    assert links[("uav", "ugv")].rng is not links[("ugv", "uav")].rng
    a = scenario(links[("uav", "ugv")])
    b = scenario(links[("ugv", "uav")])
    if stochastic(prof):
        assert a != b


def test_directions_do_not_interfere():
    """Traffic on one direction does not change the other direction's outcomes."""
    prof = load_profile("lossy")
    alone = scenario(links_for(prof, 5)[("ugv", "uav")], n=500)
    links = links_for(prof, 5)
    mixed = []
    for i in range(500):
        links[("uav", "ugv")].transmit(i * 0.2, 300)
        links[("uav", "ugv")].transmit(i * 0.2 + 0.1, 300)
        mixed.append(scenario_step(links[("ugv", "uav")], i))
    assert mixed == alone


def scenario_step(lk: Link, i: int) -> tuple[bool, float | None, str | None]:
    d = lk.transmit(i * 0.2, 200 + (i * 7919) % 3000, distance_m=float((i * 37) % 320), line_of_sight=i % 3 != 0)
    return d.delivered, d.arrive_s, d.reason


def test_loss_stream_does_not_depend_on_earlier_fates():
    """Random numbers are drawn in a fixed order whatever happens: blackouts do not shift later outcomes."""
    base = dict(loss=LossSpec(model="bernoulli", p=0.5), latency=LatencySpec(mean_s=0.1, jitter_s=0.05))
    plain = link(seed=9, **base)
    dark = link(seed=9, blackouts=[Blackout(start_s=0.0, end_s=10.0)], **base)
    a = [plain.transmit(i * 0.1, 100) for i in range(300)]
    b = [dark.transmit(i * 0.1, 100) for i in range(300)]
    assert all(d.reason == "blackout" for d in b[:100])
    assert a[100:] == b[100:]


# ----- profiles ---------------------------------------------------------------------------------------
def test_profile_dir_has_the_profiles():
    assert {"ideal", "lossy", "bursty", "narrowband", "long-range", "blackout"} <= set(PROFILE_NAMES)


@pytest.mark.parametrize("name", PROFILE_NAMES)
def test_every_profile_loads(name):
    by_name = load_profile(name)
    by_path = load_profile(PROFILE_DIR / f"{name}.toml")
    assert by_name == by_path
    assert by_name.name == name
    assert by_name.description
    assert by_name.ideal == (name == "ideal")


def test_ideal_flag():
    assert IDEAL.ideal
    assert CommProfile(name="x", beacon_s=1.0).ideal
    assert not CommProfile(name="x", latency=LatencySpec(mean_s=0.01)).ideal
    assert not CommProfile(name="x", latency=LatencySpec(jitter_s=0.01)).ideal
    assert not CommProfile(name="x", loss=LossSpec(model="bernoulli", p=0.0)).ideal
    assert not CommProfile(name="x", bandwidth=BandwidthSpec(bits_per_s=1e9)).ideal
    assert not CommProfile(name="x", range=RangeSpec(max_range_m=1e6)).ideal
    assert not CommProfile(name="x", range=RangeSpec(nlos_loss=0.1)).ideal
    assert not CommProfile(name="x", blackouts=[Blackout(start_s=1, end_s=2)]).ideal


def test_unknown_profile_lists_known_ones():
    with pytest.raises(ProfileError) as exc:
        load_profile("no-such-profile")
    msg = str(exc.value)
    assert "no-such-profile" in msg
    for name in PROFILE_NAMES:
        assert name in msg


def write(tmp_path: Path, text: str, name: str = "bad.toml") -> Path:
    path = tmp_path / name
    path.write_text(text)
    return path


@pytest.mark.parametrize("text,field", [
    ('[loss]\nmodel = "bernoulli"\np = 2\n', "loss.p"),
    ("[latency]\nmean_s = -0.1\n", "latency.mean_s"),
    ('[latency]\ndistribution = "cauchy"\n', "latency.distribution"),
    ("[bandwidth]\nbits_per_s = 0\n", "bandwidth.bits_per_s"),
    ("[range]\nnlos_loss = 1.5\n", "range.nlos_loss"),
    ("[latency]\nmean = 0.1\n", "latency.mean"),  # unknown field
    ("beacon_s = 0\n", "beacon_s"),
    ("[[blackouts]]\nstart_s = -1\nend_s = 2\n", "blackouts.0.start_s"),
])
def test_bad_field_names_file_and_field(tmp_path, text, field):
    path = write(tmp_path, text)
    with pytest.raises(ProfileError) as exc:
        load_profile(path)
    msg = str(exc.value)
    assert str(path) in msg
    assert field in msg


def test_bad_toml_names_file(tmp_path):
    path = write(tmp_path, "[loss\nmodel = \n")
    with pytest.raises(ProfileError) as exc:
        load_profile(path)
    assert str(path) in str(exc.value)


def test_profile_from_path_takes_file_stem_as_name(tmp_path):
    path = write(tmp_path, '[loss]\nmodel = "bernoulli"\np = 0.5\n', name="half.toml")
    prof = load_profile(path)
    assert prof.name == "half" and prof.loss.p == 0.5 and not prof.ideal
    named = load_profile(write(tmp_path, 'name = "custom"\n', name="other.toml"))
    assert named.name == "custom" and named.ideal


def test_profile_error_is_a_value_error():
    assert issubclass(ProfileError, ValueError)
