"""Seed 004's laws by hand: the fractional-order finite-time law (19)-(21) and the PID baseline, on one car."""
from __future__ import annotations

import math

import numpy as np
import pytest

from ecu_sim.controllers.base import PlantInfo, build_controller
from ecu_sim.controllers.fractional_ftc import PAPER_CENTRES, FractionalFiniteTime, FractionalParams
from ecu_sim.controllers.pid_tracking import PidParams, PidTracking, closed_loop_poles, sampled_spectral_radius
from ecu_sim.view import AgentInfo, LocalView, ReferenceView

M = 50e3 * 1.095  # nominal effective mass
LAM = (0.5, 0.3, 0.5, 0.3, 0.6, 0.4, 0.6, 0.4)
PLANT = PlantInfo(davis_c0=0.0067689, davis_c1=0.00022249, davis_c2=1.9071e-5, coupler_stiffness=1.6e5,
                  coupler_damping=600.0, spacing_m=3000.0, emergency_gap_m=1500.0, radio_range_m=1e4,
                  emergency_brake_mps2=1.2)
R, NU, C1, ETA, G1, G2 = 4 / 9, 0.8, 2e5, 2e5, 0.1, 0.1


def car(unit: int = 2, ref: bool = True) -> AgentInfo:
    return AgentInfo(train=0, unit=unit, n_trains=1, n_units=8, mass_kg=M, length_m=25.0, offset_m=25.0 * unit,
                     has_reference=ref)


def view(t: float, e: float, de: float, unit: int = 2, x_r: float = 2000.0, v_r: float = 50.0, a_r: float = 0.0,
         dt: float = 0.01) -> LocalView:
    """A view whose tracking errors are exactly (e, de) for car ``unit`` (X_d = x_r - 25 unit)."""
    return LocalView(t=t, dt=dt, x=x_r - 25.0 * unit + e, v=v_r + de,
                     ref=ReferenceView(x=x_r, v=v_r, a=a_r, age_s=0.0, valid=True))


def sig(z: float, a: float) -> float:
    return math.copysign(abs(z) ** a, z)


def frac(unit: int = 2, **params) -> FractionalFiniteTime:
    return FractionalFiniteTime(FractionalParams(**params), car(unit), PLANT)


# ------------------------------------------------------------------ fractional law


@pytest.mark.parametrize("e, de, expected_s0", [
    (0.01, 0.002, 0.002 + G1 * 0.01 + G2 * 0.01**NU),  # |E| >= eps: sig(E)^nu
    (-0.01, 0.0, -G1 * 0.01 - G2 * 0.01**NU),
    (5e-4, 0.001, 0.001 + G1 * 5e-4 + G2 * 5e-4**2),  # |E| < eps = 1 mm: E^2 sign(E)
    (-5e-4, 0.0, -G1 * 5e-4 - G2 * 5e-4**2),
])
def test_filtered_error_s0(e: float, de: float, expected_s0: float) -> None:
    assert frac().s0(e, de) == pytest.approx(expected_s0, rel=1e-14)


@pytest.mark.parametrize("unit_name, scale", [("N", 1.0), ("kN", 1000.0)])
def test_first_cycle_force_is_the_law_with_empty_integrals(unit_name: str, scale: float) -> None:
    law = frac(unit=4, force_unit=unit_name)
    e, de = 0.005, 0.005  # seed 004's initial errors
    s = de + G1 * e + G2 * e**NU  # I^r of one sample is 0: S = S0
    cmd = law.step(view(0.0, e, de, unit=4))
    assert cmd.force_n == pytest.approx(-LAM[4] * (C1 * s + ETA * s**NU) * scale, rel=1e-9)
    assert cmd.force_n < 0  # ahead and too fast: brake
    # rho^ after one period of the held input (exact for the linear decay), Phi = 0 far from the centres
    assert law.rho_hat == pytest.approx((1 - math.exp(-0.01 * 0.01)) / 0.01 * 10.0 * s * s, rel=1e-9)


def test_second_cycle_adds_the_fractional_integrals_by_the_trapezoid_weights() -> None:
    # I^r over one interval of linear f: h^r / Gamma(r + 2) (f_1 + r f_0), independent of the window
    law = frac(c2=0.0)
    e, de, h = 0.02, -0.003, 0.01
    s0 = de + G1 * e + G2 * e**NU
    law.step(view(0.0, e, de))
    cmd = law.step(view(h, e, de))
    w = h**R / math.gamma(R + 2) * (1 + R)
    s = s0 + w * s0 + w * sig(s0, NU)
    assert cmd.force_n == pytest.approx(-LAM[2] * (C1 * s + ETA * sig(s, NU)), rel=1e-9)


def test_a_missed_cycle_holds_the_last_sample() -> None:
    a, b = frac(c2=0.0), frac(c2=0.0)
    for law in (a, b):
        law.step(view(0.0, 0.01, 0.0))
    b.step(view(0.01, 0.01, 0.0))  # b sees the same sample at t = 0.01; a misses that cycle
    assert a.step(view(0.02, 0.01, 0.0)).force_n == pytest.approx(b.step(view(0.02, 0.01, 0.0)).force_n, rel=1e-9)


def test_constant_error_integrates_like_t_to_the_r() -> None:
    # S = S0 (1 + g3 t^r / Gamma(1 + r)) + g4 sig(S0)^nu t^r / Gamma(1 + r) for constant S0
    law = frac(c2=0.0, eta=0.0)
    e, de = 0.02, 0.0
    s0 = G1 * e + G2 * e**NU
    for j in range(1001):
        cmd = law.step(view(0.01 * j, e, de))
    g = 10.0**R / math.gamma(1 + R)
    assert cmd.force_n == pytest.approx(-LAM[2] * C1 * (s0 + g * s0 + g * s0**NU), rel=1e-9)


def test_rbf_layer_is_zero_far_from_its_centres_and_known_at_them() -> None:
    law = frac()
    law._origin = 0.0
    assert law.phi(1000.0, 1000.0) == 0.0  # absolute positions, as written: inert
    law2 = frac(rbf_origin="start")
    law2.step(view(0.0, 0.0, 0.0))
    x0 = law2._origin
    # phi_j = exp(-((z1 - c)^2 + (z2 - c)^2) / (2 b^2)), b^2 = 1/2, at z = 0: exp(-2 c^2); Phi = sqrt(sum phi_j^2)
    expected = math.sqrt(sum(math.exp(-4 * c * c) for c in PAPER_CENTRES))
    assert law2.phi(x0, x0) == pytest.approx(expected, rel=1e-9)
    assert law2.phi(x0 + 0.2, x0 + 0.1) == pytest.approx(
        math.sqrt(sum(math.exp(-2 * ((0.2 - c) ** 2 + (0.1 - c) ** 2)) for c in PAPER_CENTRES)), rel=1e-9)


def test_adaptive_gain_grows_with_s_squared() -> None:
    law = frac(rbf_origin="start")
    for j in range(3):
        law.step(view(0.01 * j, 0.05, 0.05))
    assert law.rho_hat > 0 and law.stats["k_over_c1_max"] > 1.0 and law.stats["phi_max"] > 2.0


def test_feedforward_is_ours_and_adds_the_nominal_force() -> None:
    plain, ff = frac(c2=0.0), frac(c2=0.0, feedforward=True)
    v = view(0.0, 0.0, 0.0, v_r=60.0, a_r=0.3)
    extra = ff.step(v).force_n - plain.step(v).force_n
    r = 0.0067689 + 0.00022249 * 60 + 1.9071e-5 * 3600
    assert extra == pytest.approx(M * (0.3 + r) / LAM[2], rel=1e-9)


def test_needs_the_reference_on_every_car_and_a_distribution_entry() -> None:
    with pytest.raises(ValueError, match="reference_units"):
        FractionalFiniteTime(FractionalParams(), car(3, ref=False), PLANT)
    with pytest.raises(ValueError, match="no entry for unit 3"):
        FractionalFiniteTime(FractionalParams(distribution=[0.5, 0.3]), car(2), PLANT)


def test_stale_reference_commands_nothing_and_bad_state_raises() -> None:
    law = frac()
    v = view(0.0, 0.0, 0.0)
    v.ref.valid = False
    assert law.step(v).force_n == 0.0
    v = view(0.0, 0.0, 0.0)
    v.ref.x = math.nan
    with pytest.raises(ValueError, match="not finite"):
        law.step(v)


def test_registered_under_its_name() -> None:
    law = build_controller("fractional_finite_time", {"force_unit": "kN"}, car(0), PLANT)
    assert isinstance(law, FractionalFiniteTime) and law.car.scale == 1000.0
    assert isinstance(build_controller("pid_tracking", {}, car(0), PLANT), PidTracking)


# ------------------------------------------------------------------ PID


def test_pid_is_lambda_times_pid_with_a_trapezoid_integral() -> None:
    law = PidTracking(PidParams(), car(5), PLANT)
    law.step(view(0.0, 0.01, 0.0, unit=5))
    cmd = law.step(view(0.01, 0.03, 0.002, unit=5))
    integral = 0.5 * (0.01 + 0.03) * 0.01
    assert cmd.force_n == pytest.approx(-LAM[5] * (2e5 * 0.03 + 2e5 * 0.002 + 2e6 * integral), rel=1e-9)
    kn = PidTracking(PidParams(force_unit="kN"), car(5), PLANT)
    assert kn.step(view(0.0, 0.01, 0.0, unit=5)).force_n == pytest.approx(-LAM[5] * 2e5 * 0.01 * 1000, rel=1e-9)


def _routh_stable(a3: float, a2: float, a1: float, a0: float) -> bool:
    return min(a3, a2, a1, a0) > 0 and a2 * a1 > a3 * a0


@pytest.mark.parametrize("lam", sorted(set(LAM)))
@pytest.mark.parametrize("mass", [44e3 * 1.08, 63e3 * 1.11])
def test_pid_poles_si_unstable_kn_stable_like_routh(lam: float, mass: float) -> None:
    for scale, stable in ((1.0, False), (1000.0, True)):
        g = lam * lam * scale
        poles = closed_loop_poles(mass, g, 2e5, 2e5, 2e6)
        assert bool(np.max(poles.real) < 0) == stable == _routh_stable(mass, g * 2e5, g * 2e5, g * 2e6)


def test_pid_kn_sampled_needs_a_sub_millisecond_period() -> None:
    m, g = 45e3 * 1.09, 0.6**2 * 1000.0  # the lightest car with the largest share
    assert sampled_spectral_radius(m, g, 2e5, 2e5, 2e6, 0.0002) < 1.0
    assert sampled_spectral_radius(m, g, 2e5, 2e5, 2e6, 0.005) > 1.0
    assert sampled_spectral_radius(m, 0.6**2, 2e5, 2e5, 2e6, 0.01) > 1.0  # SI: unstable sampled too
