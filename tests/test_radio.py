"""Tests of the radio link model (range, tunnels, rate cap, loss, latency) and the cangw-style gateway."""
from __future__ import annotations

import math
import struct

import numpy as np
import pytest

from ecu_sim.codec import TrainDb
from hil.radio import RadioGateway, RadioIds, RadioLink, Route, build_links, standard_routes
from hil.radio.gateway import reverse_link_name

IDS = RadioIds.from_db(TrainDb.load())
from hil.radio.link import STAT_KEYS, loss_rate_expected
from hil.scenario.model import Blackout, LossModel, RadioConfig

MS = 1_000_000  # ns


def make(seed: int = 0, name: str = "1>2", **kw) -> RadioLink:
    return RadioLink(RadioConfig(**kw), np.random.default_rng(seed), name)


def run(link: RadioLink, n: int, period_ns: int = MS, sender: float = 0.0, receiver: float = 0.0) -> list[int | None]:
    return [link.offer(k * period_ns, sender, receiver) for k in range(n)]


def check_stats_add_up(link: RadioLink) -> None:
    s = link.stats
    assert set(s) == set(STAT_KEYS)
    assert s["offered"] == sum(s[k] for k in STAT_KEYS if k != "offered")


# --------------------------------------------------------------------------- latency


def test_perfect_link_delivers_at_offer_time() -> None:
    link = make()
    times = [0, 7, 1_000, 123_456_789]
    assert [link.offer(t, 100.0, 200.0) for t in times] == times
    assert link.stats["delivered"] == 4 and link.stats["offered"] == 4
    check_stats_add_up(link)


def test_fixed_latency_is_added_exactly() -> None:
    link = make(latency_s=0.0125)
    assert link.offer(3 * MS, 0.0, 0.0) == 3 * MS + 12_500_000
    assert link.offer(4 * MS, 0.0, 0.0) == 4 * MS + 12_500_000


@pytest.mark.parametrize("dist", ["uniform", "normal", "exponential"])
def test_jitter_bounds_and_no_reordering(dist: str) -> None:
    # Frames 1 ms apart with up to 20 ms of jitter: without the FIFO rule many would overtake.
    lat, jit = 5 * MS, 20 * MS
    link = make(seed=3, latency_s=lat / 1e9, jitter_s=jit / 1e9, jitter_distribution=dist)
    sent = np.arange(5000) * MS
    got = np.array([link.offer(int(t), 0.0, 0.0) for t in sent])
    assert np.all(np.diff(got) >= 0), "a frame overtook an earlier one"
    assert np.all(got >= sent + lat)
    if dist == "uniform":  # each delivery is <= some earlier frame's t' + lat + jit <= t + lat + jit
        assert np.all(got <= sent + lat + jit)
    assert np.any(got - sent > lat + jit // 4)  # jitter is really applied


def test_jitter_distributions_have_the_configured_shape() -> None:
    # Offers 1 s apart, jitter at most tens of ms: the FIFO rule never binds, so delay - latency = raw jitter.
    jit_s = 0.01
    n = 20_000
    d = {}
    for dist in ("uniform", "normal", "exponential"):
        link = make(seed=5, latency_s=0.002, jitter_s=jit_s, jitter_distribution=dist)
        got = np.array(run(link, n, period_ns=1_000 * MS), dtype=float)
        d[dist] = (got - np.arange(n) * 1e9) / 1e9 - 0.002
    assert d["uniform"].min() >= 0 and d["uniform"].max() <= jit_s
    assert d["uniform"].mean() == pytest.approx(jit_s / 2, rel=0.02)
    assert d["exponential"].mean() == pytest.approx(jit_s, rel=0.03)
    # half-normal clipped at 0: half the frames get no jitter, the mean is sd / sqrt(2 pi)
    assert np.mean(d["normal"] == 0) == pytest.approx(0.5, abs=0.015)
    assert d["normal"].mean() == pytest.approx(jit_s / math.sqrt(2 * math.pi), rel=0.03)


# --------------------------------------------------------------------------- loss


def test_bernoulli_loss_rate_within_binomial_bounds() -> None:
    n, p = 100_000, 0.1
    link = make(seed=11, loss=LossModel(model="bernoulli", p=p))
    got = run(link, n)
    lost = sum(d is None for d in got)
    assert lost == link.stats["lost"]
    assert abs(lost - n * p) < 4.5 * math.sqrt(n * p * (1 - p))  # 4.5 sigma of Binomial(n, p)
    check_stats_add_up(link)


def test_gilbert_elliott_long_run_loss_matches_stationary_formula() -> None:
    p_gb, p_bg, l_good, l_bad = 0.02, 0.2, 0.01, 0.6
    pi_bad = p_gb / (p_gb + p_bg)  # 1/11
    expected = (1 - pi_bad) * l_good + pi_bad * l_bad  # 0.0636...
    assert expected == pytest.approx(0.063636, abs=1e-6)
    cfg = dict(loss=LossModel(model="gilbert_elliott", p_good_to_bad=p_gb, p_bad_to_good=p_bg, loss_good=l_good, loss_bad=l_bad))
    assert loss_rate_expected(RadioConfig(**cfg)) == pytest.approx(expected)
    n = 200_000
    lost = sum(d is None for d in run(make(seed=12, **cfg), n))
    # losses are correlated over ~1/(p_gb+p_bg) frames: allow ~10x the binomial variance
    sigma = math.sqrt(10 * expected * (1 - expected) / n)
    assert abs(lost / n - expected) < 4 * sigma


def test_gilbert_elliott_burst_lengths() -> None:
    # loss_bad = 1, loss_good = 0: a loss burst is a stay in the bad state, geometric with mean 1/p_bg;
    # a gap between bursts is a stay in the good state, mean 1/p_gb.
    p_gb, p_bg = 0.05, 0.25
    link = make(seed=13, loss=LossModel(model="gilbert_elliott", p_good_to_bad=p_gb, p_bad_to_good=p_bg, loss_good=0.0, loss_bad=1.0))
    lost = np.array([d is None for d in run(link, 100_000)], dtype=np.int8)
    edges = np.flatnonzero(np.diff(np.concatenate(([0], lost, [0]))))
    bursts = edges[1::2] - edges[0::2]
    gaps = edges[2::2] - edges[1:-1:2]
    assert len(bursts) > 3000
    # sd of a geometric(p) run is sqrt(1-p)/p; allow 4.5 standard errors of the mean
    assert abs(bursts.mean() - 1 / p_bg) < 4.5 * math.sqrt(1 - p_bg) / p_bg / math.sqrt(len(bursts))
    assert abs(gaps.mean() - 1 / p_gb) < 4.5 * math.sqrt(1 - p_gb) / p_gb / math.sqrt(len(gaps))


# --------------------------------------------------------------------------- range, blackouts, rate cap


def test_range_cut_off() -> None:
    link = make(range_m=1000.0)
    assert link.offer(0, 5000.0, 4001.0) == 0  # 999 m
    assert link.offer(1, 5000.0, 4000.0) == 1  # exactly at range: passes
    assert link.offer(2, 5000.0, 3999.5) is None  # 1000.5 m
    assert link.offer(3, 3999.5, 5000.0) is None  # distance is symmetric
    assert link.offer(4, 5000.0, None) == 4  # never heard the other end: assumed in range
    assert link.stats["out_of_range"] == 2 and link.stats["delivered"] == 3
    check_stats_add_up(link)


def test_blackout_segments() -> None:
    link = make(blackouts=[Blackout(start_m=2000.0, end_m=3000.0), Blackout(start_m=8000.0, end_m=8500.0)])
    cases = [
        (1999.9, 1500.0, True),
        (2000.0, 1500.0, False),  # start is inside
        (2999.99, 1500.0, False),
        (3000.0, 2500.0, False),  # receiver inside
        (3000.0, 3100.0, True),  # end is outside
        (8200.0, 7900.0, False),  # second tunnel
        (8200.0, None, False),  # sender alone decides when the receiver is unknown
        (1000.0, None, True),
    ]
    for k, (s, r, passes) in enumerate(cases):
        assert (link.offer(k, s, r) is not None) == passes, (s, r)
    assert link.stats["blackout"] == 5
    check_stats_add_up(link)


def test_bad_blackout_is_reported() -> None:
    with pytest.raises(ValueError, match=r"blackouts\[1\].*end_m \(5.0\).*start_m \(9.0\)"):
        make(blackouts=[Blackout(start_m=0.0, end_m=1.0), Blackout(start_m=9.0, end_m=5.0)])


def test_rate_cap_token_bucket_burst_one() -> None:
    # 10 Hz cap, 100 Hz offers for 10 s: exactly one frame per 100 ms passes.
    link = make(rate_cap_hz=10.0)
    got = run(link, 1000, period_ns=10 * MS)
    passed = [t for t in got if t is not None]
    assert len(passed) == 100 and link.stats["rate_capped"] == 900
    assert passed[:3] == [0, 100 * MS, 200 * MS]
    # burst 1: after a long silence only one frame passes, not a saved-up burst
    assert link.offer(20_000 * MS, 0.0, 0.0) is not None
    assert link.offer(20_001 * MS, 0.0, 0.0) is None
    # below the cap nothing is dropped
    slow = make(rate_cap_hz=10.0)
    assert all(d is not None for d in run(slow, 100, period_ns=101 * MS))


def test_dropped_frames_take_no_token_but_lost_ones_do() -> None:
    link = make(rate_cap_hz=10.0, range_m=100.0, loss=LossModel(model="bernoulli", p=1.0))
    assert link.offer(0, 0.0, 500.0) is None  # out of range: no token used
    assert link.offer(1, 0.0, 0.0) is None  # takes the token, lost on the air
    assert link.offer(2, 0.0, 0.0) is None  # bucket empty
    assert link.stats == dict(offered=3, delivered=0, out_of_range=1, blackout=0, lost=1, rate_capped=1)


def test_time_going_backwards_is_an_error() -> None:
    link = make()
    link.offer(10, 0.0, 0.0)
    with pytest.raises(ValueError, match=r"1>2.*t_ns=5"):
        link.offer(5, 0.0, 0.0)


# --------------------------------------------------------------------------- reproducibility


LOSSY = dict(latency_s=0.01, jitter_s=0.005, loss=LossModel(model="gilbert_elliott", p_good_to_bad=0.05, p_bad_to_good=0.3, loss_bad=0.8))


def test_same_seed_same_deliveries() -> None:
    a = run(make(seed=42, **LOSSY), 5000)
    b = run(make(seed=42, **LOSSY), 5000)
    c = run(make(seed=43, **LOSSY), 5000)
    assert a == b
    assert a != c


def test_common_random_numbers_across_configurations() -> None:
    # Frame k sees the same draws whatever the range: frames in range in both runs share fate and delivery time.
    # (Offers 1 s apart so the FIFO rule never binds.)
    far = run(make(seed=7, range_m=10_000.0, **LOSSY), 3000, period_ns=1000 * MS, receiver=500.0)
    link = make(seed=7, range_m=400.0, **LOSSY)
    mixed = [link.offer(k * 1000 * MS, 0.0, 500.0 if k % 2 else 0.0) for k in range(3000)]
    assert mixed[0::2] == far[0::2]
    assert all(m is None for m in mixed[1::2]) and link.stats["out_of_range"] == 1500
    assert sum(f is None for f in far) > 100  # the lossy link really loses frames


def test_build_links_children_keyed_by_name() -> None:
    cfg = RadioConfig(**LOSSY)
    small = build_links(cfg, 2, np.random.default_rng(9))
    big = build_links(cfg, 5, np.random.default_rng(9))
    assert sorted(small) == ["1>2", "2>1"]
    assert sorted(big) == ["1>2", "2>1", "2>3", "3>2", "3>4", "4>3", "4>5", "5>4"]
    # adding links (trains) does not change an existing link's draws
    assert run(small["1>2"], 3000) == run(big["1>2"], 3000)
    assert run(small["2>1"], 3000) == run(big["2>1"], 3000)
    # different links draw independently: loss indicators are uncorrelated
    bern = RadioConfig(loss=LossModel(model="bernoulli", p=0.5))
    links = build_links(bern, 3, np.random.default_rng(9))
    x = {name: np.array([d is None for d in run(link, 20_000)], dtype=float) for name, link in links.items()}
    names = sorted(x)
    for i, a in enumerate(names):
        for b in names[i + 1 :]:
            assert abs(np.corrcoef(x[a], x[b])[0, 1]) < 0.03, (a, b)  # 4 sigma at n = 20000


def test_link_rng_is_keyed_by_direction() -> None:
    from hil.radio.gateway import link_rng

    a = link_rng(np.random.default_rng(1), 0, 1).random(4)
    b = link_rng(np.random.default_rng(1), 0, 1).random(4)
    assert np.array_equal(a, b)
    assert not np.array_equal(a, link_rng(np.random.default_rng(1), 1, 0).random(4))


# --------------------------------------------------------------------------- gateway


def pos_of(frame_id: int, data: bytes) -> float | None:
    """Test stand-in for the DBC decode: AgentState (0x100..0x11F) carries a float64 position."""
    return struct.unpack("<d", data)[0] if 0x100 <= frame_id < 0x120 else None


def state(x: float) -> bytes:
    return struct.pack("<d", x)


def test_standard_routes_table() -> None:
    routes = standard_routes(3, 4, forward_aux=True, ids=IDS)
    assert set(routes) == {
        Route(0, 0x103, 1, 0x180, "1>2"),
        Route(0, 0x123, 1, 0x181, "1>2"),
        Route(1, 0x100, 0, 0x188, "2>1"),
        Route(1, 0x120, 0, 0x189, "2>1"),
        Route(1, 0x103, 2, 0x180, "2>3"),
        Route(1, 0x123, 2, 0x181, "2>3"),
        Route(2, 0x100, 1, 0x188, "3>2"),
        Route(2, 0x120, 1, 0x189, "3>2"),
    }
    assert len(routes) == 8
    assert (IDS.ahead_state, IDS.ahead_aux, IDS.behind_state, IDS.behind_aux) == (0x180, 0x181, 0x188, 0x189)
    assert set(standard_routes(3, 4, forward_aux=False, ids=IDS)) == {r for r in routes if r.dst_id in (0x180, 0x188)}
    assert standard_routes(1, 4, True, IDS) == []
    with pytest.raises(ValueError, match="units_per_train"):
        standard_routes(2, 0, True, IDS)


def test_gateway_routes_and_remaps_with_payload_unchanged() -> None:
    links = build_links(RadioConfig(latency_s=0.003), 3, np.random.default_rng(0))
    gw = RadioGateway(standard_routes(3, 4, True, IDS), links, pos_of)
    assert gw.ids_for_bus(0) == {0x103, 0x123}
    assert gw.ids_for_bus(1) == {0x100, 0x120, 0x103, 0x123}
    assert gw.ids_for_bus(2) == {0x100, 0x120}
    data = state(1234.5)
    out = gw.on_frame(0, 0x103, data, 10 * MS)
    assert out == [(1, 0x180, data, 13 * MS)]
    assert out[0][2] is data  # forwarded as is
    aux = bytes(range(8))
    assert gw.on_frame(0, 0x123, aux, 11 * MS) == [(1, 0x181, aux, 14 * MS)]
    assert gw.on_frame(1, 0x100, state(900.0), 12 * MS) == [(0, 0x188, state(900.0), 15 * MS)]
    assert gw.on_frame(2, 0x120, aux, 12 * MS) == [(1, 0x189, aux, 15 * MS)]
    assert links["1>2"].stats["delivered"] == 2 and links["2>3"].stats["offered"] == 0
    assert gw.links is links


def test_gateway_ignores_ids_not_in_table() -> None:
    links = build_links(RadioConfig(), 2, np.random.default_rng(0))
    gw = RadioGateway(standard_routes(2, 4, True, IDS), links, pos_of)
    assert gw.on_frame(0, 0x100, state(0.0), 0) == []  # head of the first train: nobody ahead
    assert gw.on_frame(0, 0x180, state(0.0), 0) == []  # a radio frame is never re-forwarded
    assert gw.on_frame(5, 0x103, state(0.0), 0) == []  # unknown bus
    assert gw.ids_for_bus(5) == set()
    assert all(link.stats["offered"] == 0 for link in links.values())


def test_single_unit_trains_fan_out_both_ways() -> None:
    links = build_links(RadioConfig(), 3, np.random.default_rng(0))
    gw = RadioGateway(standard_routes(3, 1, False, IDS), links, pos_of)
    out = gw.on_frame(1, 0x100, state(0.0), 5)
    assert sorted(out) == [(0, 0x188, state(0.0), 5), (2, 0x180, state(0.0), 5)]


def test_gateway_judges_range_from_positions_in_frames() -> None:
    cfg = RadioConfig(range_m=1000.0, blackouts=[Blackout(start_m=10_000.0, end_m=10_500.0)])
    links = build_links(cfg, 2, np.random.default_rng(0))
    gw = RadioGateway(standard_routes(2, 4, True, IDS), links, pos_of)
    tail, head = 0x103, 0x100
    # train 2's head never heard yet: in range whatever the tail's position
    assert gw.on_frame(0, tail, state(5000.0), 0) != []
    assert gw.position("1>2") == 5000.0 and gw.position("2>1") is None
    # head of train 2 at 3500 m, 1500 m behind the tail's last position: out of range
    assert gw.on_frame(1, head, state(3500.0), 1) == []
    assert links["2>1"].stats["out_of_range"] == 1
    # tail now at 4000 m: 500 m to the head's last position -> passes, both ways
    assert gw.on_frame(0, tail, state(4000.0), 2) != []
    assert gw.on_frame(1, 0x120, b"aux", 3) != []  # aux carries no position: head's last (3500) used
    # tail moves to 6000 m: its state is dropped, and so is its aux (judged at the last known 6000 m)
    assert gw.on_frame(0, tail, state(6000.0), 4) == []
    assert gw.on_frame(0, 0x123, b"aux", 5) == []
    assert links["1>2"].stats["out_of_range"] == 2
    # tunnel [10000, 10500): judged from either end's position carried in the frames
    assert gw.on_frame(1, head, state(9800.0), 6) == []  # 3800 m from the tail (6000): out of range
    assert gw.on_frame(0, tail, state(10_400.0), 7) == []  # 600 m apart, but the tail is in the tunnel
    assert links["1>2"].stats["blackout"] == 1
    assert gw.on_frame(1, head, state(9850.0), 8) == []  # the head is outside; the other end is not
    assert links["2>1"].stats["blackout"] == 1
    assert gw.on_frame(0, tail, state(10_500.0), 9) == [(1, 0x180, state(10_500.0), 9)]  # tunnel end is exclusive
    assert gw.on_frame(1, head, state(9900.0), 10) == [(0, 0x188, state(9900.0), 10)]


def test_gateway_errors_name_the_route() -> None:
    links = build_links(RadioConfig(), 2, np.random.default_rng(0))
    with pytest.raises(ValueError, match=r"route 0 .*'7>8'"):
        RadioGateway([Route(0, 0x103, 1, 0x180, "7>8")], links, pos_of)
    with pytest.raises(ValueError, match="listed twice"):
        RadioGateway([Route(0, 0x103, 1, 0x180, "1>2")] * 2, links, pos_of)
    with pytest.raises(ValueError, match="'a>b'"):
        reverse_link_name("radio12")
    assert reverse_link_name("1>2") == "2>1"


def test_the_routed_ids_are_the_dbcs(tmp_path) -> None:
    """The gateway takes its IDs from the compiled DBC: a DBC with other radio IDs gives other routes."""
    import cantools

    from ecu_sim.codec import default_dbc_path

    names = {m.name: m.frame_id for m in cantools.database.load_file(str(default_dbc_path())).messages}
    assert IDS.state[0] == names["AgentState_U01"] and IDS.aux[15] == names["AgentAux_U16"]
    assert (IDS.ahead_state, IDS.behind_aux) == (names["RadioAheadState"], names["RadioBehindAux"])
    text = default_dbc_path().read_text().replace("BO_ 384 RadioAheadState", "BO_ 400 RadioAheadState")
    text = text.replace(" BO_ 384 ", " BO_ 400 ")  # its comments and attributes
    other = tmp_path / "other.dbc"
    other.write_text(text)
    moved = RadioIds.from_db(TrainDb.load(other))
    assert moved.ahead_state == 400
    assert {r.dst_id for r in standard_routes(2, 4, False, moved)} == {400, IDS.behind_state}
