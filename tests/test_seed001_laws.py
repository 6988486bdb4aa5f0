"""Seed 001 laws (STSMCA, SMCA, PIDCA, CCA): hand-computed outputs, sign conventions, super-twisting on a
scalar system, the neighbour-acceleration exchange options, and a short run over CAN against the ideal loop."""
from __future__ import annotations

import math

import numpy as np
import pytest

from ecu_sim.controllers import build_controller
from ecu_sim.controllers.base import PlantInfo
from ecu_sim.controllers.chain import ChainErrors, chain_errors
from ecu_sim.controllers.stsmca import NeighbourAccelFilter
from ecu_sim.view import AgentInfo, LocalView, NeighbourView, ReferenceView
from hil.runtime.ideal import IdealLoop
from hil.runtime.virtual import VirtualRig
from hil.scenario import load_scenario

M, L = 80e3, 81.0
K_HAT, LAM_HAT = 1.6e5 / M, 600.0 / M
PLANT = PlantInfo(davis_c0=0.01176, davis_c1=0.00077616, davis_c2=1.6e-5, coupler_stiffness=1.6e5,
                  coupler_damping=600.0, spacing_m=3000.0, emergency_gap_m=1500.0, radio_range_m=10_000.0,
                  emergency_brake_mps2=1.2)


def R(v: float) -> float:
    return 0.01176 + 0.00077616 * v + 1.6e-5 * v * v


def car(unit: int, n: int = 6) -> AgentInfo:
    return AgentInfo(train=0, unit=unit, n_trains=1, n_units=n, mass_kg=M, length_m=L, offset_m=unit * L,
                     has_reference=(unit == 0))


def nbr(side: str, unit: int, x: float, v: float, a: float = math.nan) -> NeighbourView:
    return NeighbourView("intra", side, unit * L, x=x, v=v, a=a, age_s=0.0, valid=True)  # type: ignore[arg-type]


def middle_view(x: float, v: float, x_front: float, x_rear: float, v_front: float, v_rear: float,
                a_front: float = 0.0, a_rear: float = 0.0, dt: float = 0.01) -> LocalView:
    """Car 3 (unit 2) between car 2 (unit 1) and car 4 (unit 3)."""
    return LocalView(t=0.0, dt=dt, x=x, v=v, neighbours=[nbr("ahead", 1, x_front, v_front, a_front),
                                                          nbr("behind", 3, x_rear, v_rear, a_rear)])


def test_spacing_error_is_zero_at_81_m_with_positions_decreasing_along_the_train():
    e = chain_errors(middle_view(1000.0, 50.0, 1081.0, 919.0, 50.0, 50.0), car(2), PLANT, ChainErrors())
    assert (e.e_x, e.e_v, e.coupler_accel, e.degree) == (pytest.approx(0.0, abs=1e-12), 0.0, pytest.approx(0.0, abs=1e-12), 2.0)


def test_signs_car_ahead_of_its_slot_and_the_physical_coupler_forces():
    # car 3 is 5 cm ahead of its slot: front coupler compressed by 5 cm, rear coupler stretched by 5 cm;
    # it is 0.1 m/s faster than the car ahead, 0.2 m/s faster than the car behind.
    e = chain_errors(middle_view(1000.05, 50.3, 1081.0, 919.0, 50.2, 50.1), car(2), PLANT, ChainErrors())
    assert e.e_x == pytest.approx(0.1)  # sum_j (x~_i - x~_j) = 0.05 + 0.05
    assert e.e_v == pytest.approx(0.3)  # (50.3 - 50.2) + (50.3 - 50.1)
    # both couplers push car 3 back: f = k^ (-0.05 - 0.05) + lambda^ (-0.1 - 0.2)
    assert e.coupler_accel == pytest.approx(-K_HAT * 0.1 - LAM_HAT * 0.3)
    c = build_controller("stsmca", {}, car(2), PLANT)
    cmd = c.step(middle_view(1000.05, 50.3, 1081.0, 919.0, 50.2, 50.1, a_front=0.1, a_rear=-0.04))
    s = 2.0 * 0.1 + 0.3  # c_3 = 2
    u1 = -2.0 * math.sqrt(s)  # w = 0 on the first cycle
    accel = (-2.0 * 0.3 + (0.1 - 0.04) + u1) / 2.0
    assert c.s == pytest.approx(s) and accel < 0  # ahead and too fast: brake
    assert cmd.accel_mps2 == pytest.approx(accel)
    assert cmd.force_n == pytest.approx(M * (accel - e.coupler_accel + R(50.3)))
    assert c.w == pytest.approx(-0.9 * 0.01)  # w' = -k2 sgn(s), k2 of car 3 = 0.9, after u1 is formed


def test_head_pins_to_the_reference_with_its_acceleration():
    c = build_controller("stsmca", {}, car(0), PLANT)
    view = LocalView(t=0.0, dt=0.005, x=500.0, v=20.0, neighbours=[nbr("behind", 1, 419.0, 20.0, 0.2)],
                     ref=ReferenceView(x=500.0, v=20.0, a=0.2, age_s=0.0, valid=True))
    cmd = c.step(view)
    assert c.s == 0.0
    assert cmd.accel_mps2 == pytest.approx((0.2 + 0.2) / 2.0)  # (a_2 + b a_r) / D, D = 1 + b = 2
    # a stale reference drops out of D and of the sums
    view.ref.valid = False
    e = chain_errors(view, car(0), PLANT, ChainErrors())
    assert (e.degree, e.ref_accel, e.pinned) == (1.0, 0.0, False)


def test_super_twisting_on_a_scalar_system_rejects_a_lipschitz_disturbance_in_finite_time():
    """One pinned car alone is the textbook scalar case: s' = u1 + d with u1 = -k1 |s|^1/2 sgn s + w, w' = -k2 sgn s.

    Simulated independently here (double integrator, fine step); the law must bring s to ~0 in finite time
    and its integrator w must converge to -d(t), the known super-twisting behaviour."""
    agent = AgentInfo(train=0, unit=0, n_trains=1, n_units=1, mass_kg=M, length_m=L, offset_m=0.0, has_reference=True)
    ctl = build_controller("stsmca", {"c": 1.0, "k1": 2.0, "k2": 0.9}, agent, PLANT)
    dt, x, v = 1e-3, 0.0, 0.0
    d = lambda t: 0.3 * math.sin(t) + 0.1  # noqa: E731  (|d'| <= 0.3 < k2)
    view = LocalView(t=0.0, dt=dt, x=x, v=v, ref=ReferenceView(x=0.5, v=0.2, a=0.0, age_s=0.0, valid=True))
    s_hist, w_err = [], []
    for k in range(int(12.0 / dt)):
        t = k * dt
        view.t, view.x, view.v = t, x, v
        view.ref.x = 0.5 + 0.2 * t
        accel = ctl.step(view).accel_mps2
        a = accel + d(t)
        x, v = x + v * dt + 0.5 * a * dt * dt, v + a * dt
        s_hist.append(ctl.s)
        w_err.append(ctl.w + d(t))
    s_hist, w_err = np.abs(s_hist), np.abs(w_err)
    assert s_hist[0] > 0.4  # x~ = -0.5, v~ = -0.2: s = -0.7 at the start
    assert s_hist[int(6.0 / dt):].max() < 2e-4  # finite-time: sliding from a few s on, O(dt^2)-ish accuracy
    assert w_err[int(6.0 / dt):].max() < 0.02  # w estimates -d
    # on the surface s = 0: x~' = -c x~, so the tracking error decays exponentially afterwards
    assert abs(x - (0.5 + 0.2 * 12.0)) < 0.01


def test_smca_reaching_law_is_minus_k_sign_s_and_pidca_cca_hand_computed():
    view = middle_view(1000.05, 50.3, 1081.0, 919.0, 50.2, 50.1, a_front=0.1, a_rear=-0.04)
    smca = build_controller("smca", {}, car(2), PLANT)
    cmd = smca.step(view)
    assert smca.s == pytest.approx(0.1 + 0.3)  # c = 1
    assert cmd.accel_mps2 == pytest.approx((-1.0 * 0.3 + 0.06 - 2.0) / 2.0)
    pid = build_controller("pidca", {}, car(2), PLANT)
    err = 0.1 + 0.3
    assert pid.step(view).accel_mps2 == pytest.approx(-10.0 * err)  # first cycle: no integral, no derivative
    view.x += 0.001
    err2 = 0.1 + 0.002 + 0.3
    cmd2 = pid.step(view)
    assert cmd2.accel_mps2 == pytest.approx(-(10.0 * err2 + 15.0 * err * 0.01 + 0.1 * (err2 - err) / 0.01))
    assert cmd2.force_n == pytest.approx(M * (cmd2.accel_mps2 + R(50.3)))  # couplers not cancelled
    cca = build_controller("cca", {"kx": 1.0, "kv": 2.0}, car(2), PLANT)
    assert cca.step(view).accel_mps2 == pytest.approx(-(1.0 * 0.102 + 2.0 * 0.3))


def test_per_car_gains_check_the_train_length():
    with pytest.raises(ValueError, match="k2 has 5 values, but the train has 6 cars"):
        build_controller("stsmca", {"k2": [1.0] * 5}, car(0), PLANT)
    assert build_controller("stsmca", {}, car(3), PLANT).c == 3.0  # c = diag{3, 1.5, 2, 3, 1, 1.5}


def test_exchange_options_last_mean2_lowpass_none():
    dt = 0.01
    last, mean2 = NeighbourAccelFilter("last", 0.05), NeighbourAccelFilter("mean2", 0.05)
    low, none = NeighbourAccelFilter("lowpass", 0.04), NeighbourAccelFilter("none", 0.05)
    seq = [[1.0, math.nan], [-1.0, 2.0], [1.0, 2.0]]
    assert [last.apply(r, dt) for r in seq] == [1.0, 1.0, 3.0]
    assert [mean2.apply(r, dt) for r in seq] == [1.0, 0.0 + 2.0, 0.0 + 2.0]  # an alternation averages to 0
    alpha = dt / (0.04 + dt)
    assert [low.apply(r, dt) for r in seq] == pytest.approx([1.0, 1.0 + alpha * (-2.0) + 2.0, (1 - 2 * alpha) + alpha * (2 * alpha) + 2.0])
    assert [none.apply(r, dt) for r in seq] == [0.0, 0.0, 0.0]
    c = build_controller("stsmca", {"accel_gain": 0.5}, car(2), PLANT)
    cmd = c.step(middle_view(1000.0, 50.0, 1081.0, 919.0, 50.0, 50.0, a_front=0.2, a_rear=0.2))
    assert cmd.accel_mps2 == pytest.approx(0.5 * 0.4 / 2.0)  # s = 0: only kappa sum a_j / D


@pytest.fixture(scope="module")
def short_runs():
    sc = load_scenario("seed001", {"recording.period_s": 0.01})
    return VirtualRig(sc).run(6.0), IdealLoop(sc, control_period_s=0.001).run(6.0)


def close_time(log, tol: float = 0.01) -> float | None:
    """First recorded t from which every spacing stays within tol of 81 m (to the end of the log)."""
    closed = np.all(np.abs(log.couplers) <= tol, axis=1)
    bad = np.flatnonzero(~closed)
    k = bad[-1] + 1 if len(bad) else 0
    return float(log.t[k]) if k < len(log.t) else None


def test_over_can_the_spacing_closes_to_81_m_within_about_4_s_like_the_ideal_loop(short_runs):
    """seed001 over CAN (5 ms ECUs, front-to-back schedule) against the ideal loop at 1 ms, the near-continuous
    oracle of the law (the ideal loop at 5 ms exchanges accelerations Jacobi-style, a different schedule)."""
    can_log, ideal_log = short_runs
    for log in (can_log, ideal_log):
        assert np.abs(log.couplers[0]).max() == pytest.approx(0.5, abs=1e-9)  # the seed's uneven start
        t_close = close_time(log)
        assert t_close is not None and 2.5 < t_close < 4.5
    assert abs(close_time(can_log) - close_time(ideal_log)) < 0.5
    assert np.abs(can_log.couplers[-1] - ideal_log.couplers[-1]).max() < 5e-3
    assert np.abs(can_log.speed_error[-1]).max() < 0.02 and np.abs(ideal_log.speed_error[-1]).max() < 0.02
