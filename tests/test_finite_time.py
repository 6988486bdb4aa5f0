"""Seed-000 finite-time law (13): hand-computed outputs, weight shapes, safety rules, a closed loop."""
from __future__ import annotations

import math
import random
import time

import pytest
from pydantic import ValidationError

from ecu_sim.controllers import build_controller
from ecu_sim.controllers.base import PlantInfo
from ecu_sim.controllers.finite_time import FiniteTimeCruise, coupler_weight, gap_weight
from ecu_sim.view import AgentInfo, BrakeMode, ReferenceView
from tests.law_views import L, M, PLANT, R, agent, nb, view

A2 = 2 * 0.9 / 1.9  # alpha2 = 2 alpha1 / (alpha1 + 1) = 0.947368...
KHAT_P1 = 1.6e5 / 80e3 / 20.0  # k^/p1 = 2 / 20 = 0.1




def ctl(a: AgentInfo, plant: PlantInfo = PLANT, **params) -> FiniteTimeCruise:
    c = build_controller("finite_time", params, a, plant)
    assert isinstance(c, FiniteTimeCruise)
    return c




# ----------------------------------------------------------------------------- hand-computed outputs


def test_head_without_neighbours_sees_only_pinning_and_resistance():
    # x_r = 1000, offset 0 -> x* = 1000; x = 996 -> x~ = -4; v = 79, v_r = 80 -> v~ = -1.
    # pinning: -(0.05 sig(-4)^0.9 + 0.1 sig(-1)^a2) = 0.05 * 4^0.9 + 0.1 * 1
    #          4^0.9 = exp(0.9 ln 4) = exp(1.247665) = 3.482202 -> 0.174110 + 0.1 = 0.274110
    # R(79) = 0.01176 + 0.00077616*79 + 1.6e-5*79^2 = 0.01176 + 0.06131664 + 0.099856 = 0.17293264
    # u^ = 0.44704275 m/s^2, force = 8e4 * u^ = 35763.4 N
    c = ctl(agent())
    cmd = c.step(view(996.0, 79.0, ref=ReferenceView(x=1000.0, v=80.0, valid=True)))
    assert cmd.mode == BrakeMode.NORMAL
    assert cmd.accel_mps2 == pytest.approx(0.174110 + 0.1 + 0.17293264, abs=2e-6)
    assert cmd.force_n == pytest.approx(M * cmd.accel_mps2, rel=1e-12)
    assert cmd.force_n == pytest.approx(35763.4, abs=0.2)


def test_slot_offset_enters_the_pinning_position_error():
    # head of train 2: offset 3320 m (4 units of 80 m + l_s) -> x* = 110000 - 3320 = 106680;
    # x = 106690 -> x~ = +10; v = v_r = 80 -> v~ = 0.
    # u^ = -0.05 * 10^0.9 + R(80) = -0.05 * 7.943282 + (0.01176 + 0.0620928 + 0.1024) = -0.397164 + 0.1762528
    c = ctl(agent(train=1, offset=3320.0))
    cmd = c.step(view(106690.0, 80.0, ref=ReferenceView(x=110000.0, v=80.0, valid=True)))
    assert cmd.accel_mps2 == pytest.approx(-0.397164 + 0.1762528, abs=2e-6)


def test_intra_neighbour_terms_hand_computed():
    # unit 2 (offset 80), unit ahead at offset 0: Delta = (x_q - x) + (0 - 80) = e.
    # x = 0, x_q = 80.02 -> e = 0.02 (flat zone): a = 1 - k^/p1 = 0.9.
    # v = 50, v_q = 50.5 -> dv = 0.5.
    # u^ = 0.9 * (20 * 0.02^0.9 + 10 * 0.5^a2) + R(50)
    #    0.02^0.9 = exp(0.9 ln 0.02) = exp(-3.520821) = 0.0295752
    #    0.5^0.947368 = exp(-0.656666) = 0.518578
    #    -> 0.9 * (0.591503 + 5.185775) = 5.199550;  R(50) = 0.01176 + 0.038808 + 0.04 = 0.090568
    c = ctl(agent(unit=1, offset=80.0))
    cmd = c.step(view(0.0, 50.0, [nb("intra", "ahead", 0.0, 80.02, 50.5)]))
    assert cmd.accel_mps2 == pytest.approx(5.199550 + 0.090568, abs=2e-6)


def test_inter_neighbour_terms_hand_computed():
    # head of train 2 (offset 3080: 1 unit of 80 m + l_s), train ahead's tail at offset 0... one unit per train.
    # Gap error g = Delta = (x_q - x) + (0 - 3080); x_q = 10000, x = 6000 -> Delta = 920 -> a = 1 (0 < 920 < 6000)
    # dv = 2 -> u^ = 1e-4 * 920^0.9 + 1 * 2^a2 + R(v) with v = 60, no reference
    #    920^0.9 = exp(0.9 * 6.824374) = exp(6.141937) = 464.953;  2^0.947368 = exp(0.656666) = 1.928352
    #    R(60) = 0.01176 + 0.0465696 + 0.0576 = 0.1159296
    c = ctl(agent(train=1, offset=3080.0, ref=False, n_units=1))
    cmd = c.step(view(6000.0, 60.0, [nb("inter", "ahead", 0.0, 10000.0, 62.0)]))
    assert cmd.accel_mps2 == pytest.approx(0.0464953 + 1.928352 + 0.1159296, abs=2e-6)


# ----------------------------------------------------------------------------- intra (coupler) weights


@pytest.mark.parametrize(
    "e, w_hand",
    [
        (0.02, 1.0),  # flat zone
        (0.08, 0.0075 / (0.01 - 0.0064)),  # (2*0.1*0.05 - 0.05^2)/(0.1^2 - 0.08^2) = 0.0075/0.0036 = 2.08333
        (-0.085, 9e-4 / 0.015**2),  # 0.03^2/(0.1 - 0.085)^2 = 9e-4/2.25e-4 = 4
    ],
)
def test_coupled_pair_uses_one_weight_and_forces_are_opposite(e, w_hand):
    # Unit j (offset 0) sees the unit behind (offset 80) at Delta = -e; unit j+1 sees j at Delta = +e.
    # Equal speeds (v = 0: R = c0) and no reference: u^ - c0 = p1 a sig(Delta)^0.9, so the two units
    # get exactly opposite accelerations iff they use the same weight a = w(e) - k^/p1.
    front, rear = ctl(agent(unit=0, ref=False)), ctl(agent(unit=1, offset=80.0))
    x_front, x_rear = 1000.0, 1000.0 - 80.0 - e
    u_front = front.step(view(x_front, 0.0, [nb("intra", "behind", 80.0, x_rear, 0.0)])).accel_mps2 - 0.01176
    u_rear = rear.step(view(x_rear, 0.0, [nb("intra", "ahead", 0.0, x_front, 0.0)])).accel_mps2 - 0.01176
    expected = 20.0 * (w_hand - KHAT_P1) * math.copysign(abs(e) ** 0.9, e)
    assert u_rear == pytest.approx(expected, rel=1e-9)
    assert u_front == pytest.approx(-expected, rel=1e-9)
    assert front.intra_weight(e) == pytest.approx(w_hand - KHAT_P1, rel=1e-12)


def test_coupler_weight_continuous_at_switching_points():
    h, d1, d2, cap = 0.1, 0.05, 0.03, 100.0
    for edge in (0.1 - 0.05, -(0.1 - 0.03)):  # stretch zone starts at 0.05, compression zone at -0.07
        for eps in (1e-9, 1e-12):
            below, above = coupler_weight(edge - eps, h, h, d1, d2, cap), coupler_weight(edge + eps, h, h, d1, d2, cap)
            assert below == pytest.approx(1.0, abs=1e-7) and above == pytest.approx(1.0, abs=1e-7)


def test_coupler_weight_grows_toward_band_edge_and_stays_finite_beyond():
    h, d1, d2, cap = 0.1, 0.05, 0.03, 100.0
    stretch = [0.05 + 0.0499 * k / 50 for k in range(51)]  # 0.05 ... 0.0999
    ws = [coupler_weight(e, h, h, d1, d2, cap) for e in stretch]
    assert all(b >= a for a, b in zip(ws, ws[1:])) and ws[-1] > 30  # 0.0075/(0.01-0.0999^2) = 37.5
    comp = [-0.07 - 0.0299 * k / 50 for k in range(51)]  # -0.07 ... -0.0999
    wc = [coupler_weight(e, h, h, d1, d2, cap) for e in comp]
    assert all(b >= a for a, b in zip(wc, wc[1:])) and wc[-1] == cap  # 9e-4/1e-8 = 9e4 -> capped
    # 100 is reached at e = -0.097 (0.03^2/0.003^2) and e = sqrt(0.01 - 7.5e-5) = 0.0996243
    assert coupler_weight(-0.0969, h, h, d1, d2, cap) < cap <= coupler_weight(-0.0971, h, h, d1, d2, cap)
    assert coupler_weight(0.09962, h, h, d1, d2, cap) < cap <= coupler_weight(0.09963, h, h, d1, d2, cap)
    for e in (0.1, 0.1000001, 0.2, 5.0, -0.1, -0.3, -5.0):  # at and beyond the band: the cap, never inf/NaN
        assert coupler_weight(e, h, h, d1, d2, cap) == cap


def test_law_output_finite_with_coupler_beyond_band():
    # e = 0.15 (> h1): weight = cap - k^/p1 = 99.9; u^ = 20 * 99.9 * 0.15^0.9 + c0
    #   0.15^0.9 = exp(0.9 ln 0.15) = exp(-1.707408) = 0.181335 -> 362.308 + 0.01176
    c = ctl(agent(unit=1, offset=80.0))
    cmd = c.step(view(0.0, 0.0, [nb("intra", "ahead", 0.0, 80.15, 0.0)]))
    assert math.isfinite(cmd.force_n)
    assert cmd.accel_mps2 == pytest.approx(362.308 + 0.01176, rel=1e-6)


# ----------------------------------------------------------------------------- inter (radio) weights


def test_gap_weight_cases():
    z, bh, g1, g2, cap = 1500.0, 7000.0, 1000.0, 600.0, 100.0  # zeta = l_s - l_e, beta^ = beta - l_s
    assert gap_weight(7000.5, z, bh, g1, g2, cap) == 0.0  # s > beta: out of range
    assert gap_weight(20000.0, z, bh, g1, g2, cap) == 0.0
    assert gap_weight(6500.0, z, bh, g1, g2, cap) == pytest.approx(0.5)  # (7000 - 6500)/1000
    assert gap_weight(6999.0, z, bh, g1, g2, cap) == pytest.approx(0.001)
    assert gap_weight(0.0, z, bh, g1, g2, cap) == 1.0
    assert gap_weight(-800.0, z, bh, g1, g2, cap) == 1.0  # s = 2200 > l_e + gamma2 = 2100
    # s = 1800: (2*600*1500 - 600^2)/(1500^2 - 1200^2) = 1440000/810000 = 1.777...
    assert gap_weight(-1200.0, z, bh, g1, g2, cap) == pytest.approx(16 / 9)
    # continuity: 1 at s = l_e + gamma2 and at the start of the range fade; 0 at the range limit
    assert gap_weight(-900.0 - 1e-9, z, bh, g1, g2, cap) == pytest.approx(1.0, abs=1e-9)
    assert gap_weight(6000.0 + 1e-6, z, bh, g1, g2, cap) == pytest.approx(1.0, abs=1e-8)
    assert gap_weight(7000.0, z, bh, g1, g2, cap) == 0.0
    # grows toward s = l_e, finite at and beyond it
    ws = [gap_weight(-900.0 - 599.0 * k / 40, z, bh, g1, g2, cap) for k in range(41)]
    assert all(b >= a for a, b in zip(ws, ws[1:]))
    for g in (-1500.0, -1600.0, -1e6):
        assert gap_weight(g, z, bh, g1, g2, cap) == cap


def test_inter_weight_same_from_both_sides_of_the_gap():
    # Head of train 2 sees the train ahead at Delta = g = 6500 (weight 0.5); the tail of train 1 sees
    # the head of train 2 at Delta = -6500. Equal speeds, no reference, v = 0:
    # u^ - c0 = +/- 0.5 * 1e-4 * 6500^0.9;  6500^0.9 = exp(0.9 * 8.779557) = exp(7.901602) = 2701.61
    follower = ctl(agent(train=1, offset=3080.0, ref=False, n_units=1))
    leader = ctl(agent(train=0, offset=0.0, ref=False, n_units=1))
    x_lead, x_follow = 10000.0, 10000.0 - 3080.0 - 6500.0
    uf = follower.step(view(x_follow, 0.0, [nb("inter", "ahead", 0.0, x_lead, 0.0)])).accel_mps2 - 0.01176
    ul = leader.step(view(x_lead, 0.0, [nb("inter", "behind", 3080.0, x_follow, 0.0)])).accel_mps2 - 0.01176
    assert uf == pytest.approx(0.5 * 1e-4 * 2701.61, rel=1e-5)
    assert ul == pytest.approx(-uf, rel=1e-12)


# ----------------------------------------------------------------------------- safety and degraded inputs


def test_emergency_below_emergency_gap():
    c = ctl(agent(train=1, offset=3080.0, n_units=1))
    ref = ReferenceView(x=20000.0, v=80.0, valid=True)
    # Delta = -1501 -> s = 3000 - 1501 = 1499 < 1500 -> emergency
    x = 10000.0 - 3080.0 + 1501.0
    cmd = c.step(view(x, 80.0, [nb("inter", "ahead", 0.0, 10000.0, 80.0)], ref))
    assert cmd.mode == BrakeMode.EMERGENCY
    assert cmd.force_n == pytest.approx(-1.2 * M) and cmd.accel_mps2 == pytest.approx(-1.2)
    # s = 1501 -> normal
    x = 10000.0 - 3080.0 + 1499.0
    assert c.step(view(x, 80.0, [nb("inter", "ahead", 0.0, 10000.0, 80.0)], ref)).mode == BrakeMode.NORMAL
    # the same small gap from an invalid neighbour is ignored (the runtime owns lost-contact rules)
    x = 10000.0 - 3080.0 + 1501.0
    assert c.step(view(x, 80.0, [nb("inter", "ahead", 0.0, 10000.0, 80.0, valid=False)], ref)).mode == BrakeMode.NORMAL


def test_invalid_neighbours_ignored_and_weight_scales_terms():
    c = ctl(agent(unit=1, offset=80.0, ref=False))
    good = nb("intra", "ahead", 0.0, 80.02, 50.5)
    base = c.step(view(0.0, 50.0, [good])).accel_mps2
    junk = nb("intra", "behind", 160.0, float("nan"), 1e9, valid=False)
    assert c.step(view(0.0, 50.0, [good, junk])).accel_mps2 == base
    half = nb("intra", "ahead", 0.0, 80.02, 50.5, weight=0.5)
    r50 = R(50.0)
    assert c.step(view(0.0, 50.0, [half])).accel_mps2 - r50 == pytest.approx(0.5 * (base - r50), rel=1e-12)


def test_invalid_reference_drops_pinning():
    c = ctl(agent())
    stale = ReferenceView(x=1e6, v=0.0, valid=False)
    assert c.step(view(996.0, 79.0, ref=stale)).accel_mps2 == pytest.approx(R(79.0), rel=1e-12)


def test_bad_inputs_and_parameters_are_named():
    c = ctl(agent())
    with pytest.raises(ValueError, match="own measured state"):
        c.step(view(float("nan"), 1.0))
    with pytest.raises(ValueError, match="intra neighbour ahead"):
        ctl(agent(unit=1, offset=80.0)).step(view(0.0, 1.0, [nb("intra", "ahead", 0.0, float("nan"), 1.0)]))
    with pytest.raises(ValidationError, match="delta1"):
        ctl(agent(), delta1=0.2)
    with pytest.raises(ValidationError, match="p5"):
        ctl(agent(), p5=1.0)
    with pytest.raises(ValueError, match="gamma2"):
        ctl(agent(), gamma2=1500.0)  # must be below l_s - l_e = 1500
    with pytest.raises(ValueError, match="gamma1"):
        ctl(agent(), gamma1=7000.0)  # must be below beta - l_s = 7000


def test_step_is_cheap():
    # Budget: ~10-20 us per call with 2-3 neighbours (measured about 4 us); 100 us leaves room for a busy CI.
    c = ctl(agent(unit=0, train=1, offset=3320.0))
    v = view(105000.0, 80.0, [nb("intra", "behind", 3400.0, 104920.02, 80.1), nb("inter", "ahead", 240.0, 108000.0, 85.0)],
             ReferenceView(x=109000.0, v=87.0, valid=True))
    n = 2000
    t0 = time.perf_counter()
    for _ in range(n):
        c.step(v)
    assert (time.perf_counter() - t0) / n < 100e-6


# ----------------------------------------------------------------------------- cross-check with the linear law


def _random_views(rng: random.Random, n: int):
    """Views of a synthetic unit with every kind of neighbour (the laws do not check topology),
    errors inside the flat weight zones: e in (-0.07, 0.05) for both couplers, gap error in (-900, 6000]."""
    for _ in range(n):
        x = rng.uniform(-1e4, 1e4)
        v = rng.uniform(0, 90)
        nbs = [
            nb("intra", "ahead", 3160.0, x + 80.0 + rng.uniform(-0.049, 0.049), v + rng.uniform(-2, 2), weight=rng.random()),
            nb("intra", "behind", 3320.0, x - 80.0 + rng.uniform(-0.049, 0.069), v + rng.uniform(-2, 2)),
            nb("inter", "ahead", 0.0, x + 3240.0 + rng.uniform(-800, 5900), v + rng.uniform(-5, 5)),
        ]
        ref = ReferenceView(x=x + 3240.0 + rng.uniform(-500, 500), v=v + rng.uniform(-5, 5), valid=True)
        yield view(x, v, nbs, ref)


@pytest.mark.parametrize("stiffness", [0.0, 1.6e5])
def test_alpha_one_reduces_to_linear_consensus(stiffness):
    # alpha1 = 1 -> alpha2 = 1 and sig(z)^1 = z. In the flat zones the intra weight is 1 - k^/p1, so
    # (13) becomes (p1 - k^) Delta + p3 (1 - k^/p1) dv for a coupled unit: the consensus with
    # cancel_coupler, kx = p1 and kv = p3 (1 - k^/p1). With k = 0 these are simply kx = p1, kv = p3.
    plant = PLANT.model_copy(update={"coupler_stiffness": stiffness})
    a = agent(unit=0, train=1, offset=3240.0, ref=True)
    khat_p1 = stiffness / M / 20.0
    ft = ctl(a, plant, alpha1=1.0)
    lin = build_controller("consensus", dict(
        kx_intra=20.0, kv_intra=10.0 * (1 - khat_p1), kx_inter=1e-4, kv_inter=1.0, kx_ref=0.05, kv_ref=0.1,
        cancel_coupler=True), a, plant)
    for v in _random_views(random.Random(7), 200):
        assert ft.step(v).accel_mps2 == pytest.approx(lin.step(v).accel_mps2, rel=1e-10, abs=1e-12)


# ----------------------------------------------------------------------------- closed loop


def _simulate_two_trains(law: str, t_end: float, dt: float = 0.01, sub: int = 5):
    """Two trains of one unit each (both heads pinned, linked by radio) as double integrators with
    Davis resistance; commands held for one 10 ms cycle, semi-implicit Euler at 2 ms inside it.
    v_r = 80 m/s, x_r(0) = 0. Start: x~ = -200 m / -400 m, v = 75 / 72 m/s. Returns samples
    (t, x~1, v~1, x~2, v~2, gap) after every cycle."""
    vr, offs = 80.0, (0.0, L + 3000.0)
    ctls = [build_controller(law, {}, agent(train=i, offset=offs[i], n_units=1), PLANT) for i in range(2)]
    x, v = [-200.0 - offs[0], -400.0 - offs[1]], [75.0, 72.0]
    out = []
    for k in range(int(round(t_end / dt))):
        t = k * dt
        ref = ReferenceView(x=vr * t, v=vr, valid=True, age_s=0.0)
        views = (
            view(x[0], v[0], [nb("inter", "behind", offs[1], x[1], v[1])], ref),
            view(x[1], v[1], [nb("inter", "ahead", offs[0], x[0], v[0])], ref),
        )
        acc = [c.step(w).force_n / M for c, w in zip(ctls, views)]
        h = dt / sub
        for _ in range(sub):
            for i in (0, 1):
                v[i] += (acc[i] - R(v[i])) * h
                x[i] += v[i] * h
        te = t + dt
        out.append((te, x[0] - vr * te + offs[0], v[0] - vr, x[1] - vr * te + offs[1], v[1] - vr, x[0] - L - x[1]))
    return out


def test_closed_loop_heads_converge_to_reference():
    # Measured: both |v~| stay below 0.01 m/s from t = 295.6 s on; before that the speed overshoots
    # (v~ peaks above +30 m/s: mu2 = 0.1 damps the pinning weakly), as CONTROLLERS.md warns.
    out = _simulate_two_trains("finite_time", 320.0)
    late = [s for s in out if s[0] >= 300.0]
    assert max(max(abs(s[2]), abs(s[4])) for s in late) < 0.01
    assert max(max(abs(s[1]), abs(s[3])) for s in late) < 0.5  # position errors well on their way too
    assert min(s[5] for s in out) > PLANT.emergency_gap_m
    early = [s for s in out if s[0] <= 200.0]
    assert max(abs(s[2]) for s in early) > 0.01  # not trivially converged
