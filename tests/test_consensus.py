"""Ordinary (linear) consensus baseline: hand-computed outputs, coupler option, gains, safety, a closed loop."""
from __future__ import annotations

import pytest
from pydantic import ValidationError

from ecu_sim.controllers import build_controller
import ecu_sim.controllers.consensus as consensus_module
from ecu_sim.controllers.base import PlantInfo
from ecu_sim.controllers.consensus import ConsensusParams, OrdinaryConsensus
from ecu_sim.controllers.finite_time import FiniteTimeParams
from ecu_sim.view import AgentInfo, BrakeMode, ReferenceView
from tests.law_views import M, PLANT, R, agent, nb, view





def ctl(a: AgentInfo, plant: PlantInfo = PLANT, **params) -> OrdinaryConsensus:
    c = build_controller("consensus", params, a, plant)
    assert isinstance(c, OrdinaryConsensus)
    return c




def test_default_gains_are_the_linear_counterpart_of_the_finite_time_gains():
    c, f = ConsensusParams(), FiniteTimeParams()
    assert (c.kx_intra, c.kv_intra, c.kx_inter, c.kv_inter) == (f.p1, f.p3, f.p2, f.p4)
    assert (c.kx_ref, c.kv_ref) == (f.mu1, f.mu2)
    assert c.cancel_coupler is False
    for name, field in ConsensusParams.model_fields.items():
        assert field.description, f"gain {name} is undocumented"
    assert "depends entirely on these" in " ".join((consensus_module.__doc__ or "").split())
    with pytest.raises(ValidationError, match="kx_intra"):
        ConsensusParams(kx_intra=-1.0)
    with pytest.raises(ValidationError, match="kp"):
        ConsensusParams(kp=1.0)


def test_head_with_reference_and_both_kinds_of_neighbours_hand_computed():
    # Head of train 2: offset 3320 (4 units x 80 m + l_s). x_r = 20000 -> x* = 16680.
    # x = 16670 -> x~ = -10; v = 70, v_r = 72 -> v~ = -2.
    # intra behind (offset 3400): x_q = 16589.97 -> Delta = (16589.97 - 16670) + 80 = -0.03; dv = 70.4 - 70 = 0.4
    #   20 * -0.03 + 10 * 0.4 = -0.6 + 4 = 3.4
    # inter ahead (tail of train 1, offset 240): x_q = 20000 -> Delta = (20000 - 16670) + (240 - 3320) = 250; dv = 3
    #   1e-4 * 250 + 1 * 3 = 3.025
    # pinning: -(0.05 * -10 + 0.1 * -2) = 0.7
    # R(70) = 0.01176 + 0.0543312 + 0.0784 = 0.1444912
    # u^ = 3.4 + 3.025 + 0.7 + 0.1444912 = 7.2694912
    c = ctl(agent(train=1, offset=3320.0))
    cmd = c.step(view(16670.0, 70.0, [nb("intra", "behind", 3400.0, 16589.97, 70.4), nb("inter", "ahead", 240.0, 20000.0, 73.0)],
                      ReferenceView(x=20000.0, v=72.0, valid=True)))
    assert cmd.mode == BrakeMode.NORMAL
    assert cmd.accel_mps2 == pytest.approx(7.2694912, abs=1e-9)
    assert cmd.force_n == pytest.approx(M * cmd.accel_mps2, rel=1e-12)  # = 581559.3 N


def test_cancel_coupler_subtracts_k_hat_times_displacement():
    # unit behind the head, e = Delta = 0.05, dv = 0, v = 0:
    #   default: 20 * 0.05 + c0 = 1.01176;   cancel: (20 - 1.6e5/8e4) * 0.05 + c0 = 0.9 + c0 = 0.91176
    a = agent(unit=1, offset=80.0)
    v = view(0.0, 0.0, [nb("intra", "ahead", 0.0, 80.05, 0.0)])
    assert ctl(a).step(v).accel_mps2 == pytest.approx(1.01176, abs=1e-12)
    assert ctl(a, cancel_coupler=True).step(v).accel_mps2 == pytest.approx(0.91176, abs=1e-12)


def test_coupled_pair_gets_opposite_accelerations():
    front, rear = ctl(agent(unit=0, ref=False)), ctl(agent(unit=1, offset=80.0))
    xf, xr = 500.0, 500.0 - 80.0 + 0.04  # coupler compressed by 0.04 m, rear 0.3 m/s faster
    uf = front.step(view(xf, 10.0, [nb("intra", "behind", 80.0, xr, 10.3)])).accel_mps2 - R(10.0)
    ur = rear.step(view(xr, 10.3, [nb("intra", "ahead", 0.0, xf, 10.0)])).accel_mps2 - R(10.3)
    assert ur == pytest.approx(20 * -0.04 + 10 * -0.3)  # = -3.8
    assert uf == pytest.approx(-ur)


def test_radio_neighbour_beyond_range_is_not_adjacent():
    # gap error beyond beta - l_s = 7000 m -> a = 0: only R(v) remains (no reference)
    c = ctl(agent(train=1, offset=3080.0, ref=False, n_units=1))
    far = nb("inter", "ahead", 0.0, 3080.0 + 7000.5, 5.0)
    assert c.step(view(0.0, 0.0, [far])).accel_mps2 == pytest.approx(0.01176)
    near = nb("inter", "ahead", 0.0, 3080.0 + 6999.5, 5.0)  # 1e-4 * 6999.5 + 1 * 5 + c0
    assert c.step(view(0.0, 0.0, [near])).accel_mps2 == pytest.approx(0.69995 + 5.0 + 0.01176)


def test_emergency_rule_invalid_neighbours_and_weights():
    c = ctl(agent(train=1, offset=3080.0, n_units=1))
    ref = ReferenceView(x=20000.0, v=80.0, valid=True)
    close = nb("inter", "ahead", 0.0, 10000.0, 80.0)  # Delta = -1501 -> s = 1499 < l_e
    cmd = c.step(view(10000.0 - 3080.0 + 1501.0, 80.0, [close], ref))
    assert cmd.mode == BrakeMode.EMERGENCY and cmd.accel_mps2 == pytest.approx(-1.2)
    rear = ctl(agent(unit=1, offset=80.0))
    good = nb("intra", "ahead", 0.0, 80.05, 1.0)
    base = rear.step(view(0.0, 0.0, [good])).accel_mps2
    junk = nb("intra", "behind", 160.0, float("nan"), 0.0, valid=False)
    assert rear.step(view(0.0, 0.0, [good, junk])).accel_mps2 == base
    quarter = nb("intra", "ahead", 0.0, 80.05, 1.0, weight=0.25)  # 0.25 * (20*0.05 + 10*1) + c0
    assert rear.step(view(0.0, 0.0, [quarter])).accel_mps2 == pytest.approx(0.25 * 11.0 + 0.01176)
    head = ctl(agent())
    assert head.step(view(5.0, 3.0, ref=ReferenceView(x=0.0, v=0.0, valid=False))).accel_mps2 == pytest.approx(R(3.0))


def test_closed_loop_pinned_head_converges():
    # One head pinned to v_r = 80 m/s, x_r(0) = 0, starting at x~ = -50 m, v = 75 m/s; double integrator
    # with Davis resistance, 10 ms command hold, 2 ms semi-implicit Euler. The linearised error dynamics
    # are s^2 + 0.1 s + 0.05 (omega_n = 0.224 rad/s, damping ratio 0.224): the envelope decays as
    # exp(-0.05 t), so from |v~| ~ 10 m/s it needs about ln(1000)/0.05 = 138 s to fall below 0.01 m/s.
    c = ctl(agent())
    x, v, vr, dt, sub = -50.0, 75.0, 80.0, 0.01, 5
    worst_late, worst_early = 0.0, 0.0
    for k in range(int(200 / dt)):
        t = k * dt
        a = c.step(view(x, v, ref=ReferenceView(x=vr * t, v=vr, valid=True))).accel_mps2
        for _ in range(sub):
            v += (a - R(v)) * dt / sub
            x += v * dt / sub
        if t + dt >= 170.0:
            worst_late = max(worst_late, abs(v - vr))
        elif t + dt <= 100.0:
            worst_early = max(worst_early, abs(v - vr))
    assert worst_late < 0.01
    assert worst_early > 0.1  # it did have to converge
