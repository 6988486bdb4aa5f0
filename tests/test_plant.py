"""Plant: exact coupler dynamics, resistance, track, actuators, fail-safe, disturbances, divergence."""
from __future__ import annotations

import math
import time

import numpy as np
import pytest
from scipy.integrate import solve_ivp

from ecu_sim.view import BrakeMode
from hil.scenario.layout import TrainLayout
from hil.plant import Plant, PlantDiverged
from hil.plant import dynamics
from ecu_sim.track import G
from hil.scenario.model import PlantConfig, TrackConfig, TrainsConfig

M = 80e3
K = 1.6e5
NEVER = {"hold_s": 1e9, "emergency_after_s": 1e9}  # fail-safe that never triggers
FREE = {"davis_c0": 0.0, "davis_c1": 0.0, "davis_c2": 0.0}  # no running resistance
OFF = {"enabled": False}


def layout(count: int = 1, units: int = 4, rot: float = 0.0) -> TrainLayout:
    heads = [1000.0 - 1000.0 * i for i in range(count)]
    trains = TrainsConfig(
        count=count, units=units, unit_mass_kg=M, unit_length_m=25.0, rotating_mass_factor=rot,
        head_positions_m=heads, speeds_mps=[0.0] * count, spacing_m=300.0, emergency_gap_m=100.0,
    )
    return TrainLayout.from_config(trains)


def plant(lay: TrainLayout, v0: float | np.ndarray = 0.0, dx: np.ndarray | None = None, track: TrackConfig | None = None,
          seed: int = 0, dt: float | None = None, head: float = 1000.0, **cfg) -> Plant:
    """A plant at rest-length spacing (plus dx), train i's head at head - its slot offset."""
    heads = [head - float(o) for o in lay.offset_m[lay.heads()]]
    x0 = lay.initial_positions(heads) + (0.0 if dx is None else dx)
    v = np.broadcast_to(np.asarray(v0, dtype=float), (lay.n_units,)).copy()
    cfg.setdefault("failsafe", NEVER)
    return Plant(PlantConfig(**cfg), track or TrackConfig(), lay, x0, v, np.random.default_rng(seed), dt=dt)


def run(p: Plant, seconds: float) -> None:
    for _ in range(int(round(seconds / p.dt))):
        p.step()


# ------------------------------------------------------------------ energy of the coupler chain

@pytest.mark.parametrize("dt", [1e-3, 1e-2])
def test_free_chain_conserves_energy_over_1000_s(dt: float) -> None:
    # 4 units x 80 t, k = 1.6e5, d = 0, no resistance: omega = 1.08, 2.0, 2.61 rad/s.
    # Measured drift of this exact discretisation: 7e-11 (1 ms) and 1.5e-12 (10 ms), i.e. roundoff.
    # RK4 on the same chain over 1000 s (measured): -4.3e-11 at 1 ms, -1.1e-7 at 10 ms (it bleeds ~(w h)^6/72
    # per step). The bound asked for is 1e-6; 1e-9 is asserted, which RK4 at 10 ms would fail.
    lay = layout(units=4)
    dx = np.array([0.03, 0.0, -0.02, 0.01])  # far from x = 0, where ulp(x) = 1.5e-11 m must not leak into e
    p = plant(lay, dx=dx, head=1.0e5, limits=OFF, coupler_damping_ns_per_m=0.0, **FREE, dt=dt)
    e0 = p.energy()
    assert e0 == pytest.approx(0.5 * K * (0.03**2 + 0.02**2 + 0.03**2), rel=1e-6)  # e = 0.03, 0.02, -0.03
    worst = 0.0
    for _ in range(100):
        run(p, 10.0)
        worst = max(worst, abs(p.energy() / e0 - 1.0))
    assert worst < 1e-9
    assert np.abs(p.v).max() > 0.01  # it kept oscillating (not frozen)


def test_coupler_damping_decays_at_the_lowest_mode_rate() -> None:
    # Equal masses, D = d L proportional to K = k L: mode j's energy decays as exp(-d lambda_j t / m),
    # lambda_1 = 2 - 2 cos(pi/4) for a 4-unit chain; start in that mode shape.
    d, lam1 = 600.0, 2.0 - 2.0 * math.cos(math.pi / 4)
    shape = np.cos(math.pi * (np.arange(4) + 0.5) / 4)  # lowest Laplacian eigenvector of the path graph
    lay = layout(units=4)
    p = plant(lay, dx=0.05 * shape, limits=OFF, coupler_damping_ns_per_m=d, **FREE, dt=1e-2)
    e0 = p.energy()
    for t_check in (150.0, 300.0, 600.0):
        run(p, t_check - p.t)
        expected = math.exp(-d * lam1 * t_check / M)
        assert p.energy() / e0 == pytest.approx(expected, rel=0.02)  # ripple of a mode with zeta ~ 2e-3


def test_moving_train_has_the_same_coupler_motion_as_a_standing_one() -> None:
    # Galilean invariance, also across the periodic re-basing of the train origin (every 1024 steps).
    lay = layout(units=4)
    dx = np.array([0.03, 0.0, -0.02, 0.01])
    standing = plant(lay, 0.0, dx=dx, limits=OFF, **FREE)
    moving = plant(lay, 83.0, dx=dx, limits=OFF, **FREE)
    run(standing, 5.0)
    run(moving, 5.0)
    assert np.allclose(moving.coupler_displacements(), standing.coupler_displacements(), atol=1e-9)
    assert np.allclose(moving.x - standing.x, 83.0 * 5.0, atol=1e-6)
    assert np.allclose(moving.coupler_displacements(), lay.coupler_displacements(moving.x), atol=1e-8)


# ------------------------------------------------------------------ single unit against closed forms

def test_single_unit_linear_resistance_matches_closed_form() -> None:
    rot, F, c1, v0 = 0.08, 20e3, 0.00077616, 10.0
    lay = layout(units=1, rot=rot)
    m_eff = M * (1 + rot)
    p = plant(lay, v0, limits=OFF, davis_c0=0.0, davis_c1=c1, davis_c2=0.0)
    x0 = float(p.x[0])
    p.command(0, F, BrakeMode.NORMAL, 0.0)
    run(p, 200.0)
    v_inf, rate = F / (M * c1), c1 * M / m_eff
    v = v_inf + (v0 - v_inf) * math.exp(-rate * 200.0)
    x = x0 + v_inf * 200.0 + (v0 - v_inf) * (1.0 - math.exp(-rate * 200.0)) / rate
    assert p.v[0] == pytest.approx(v, abs=1e-9)
    assert p.x[0] == pytest.approx(x, abs=1e-7)


def test_single_unit_with_davis_resistance_matches_solve_ivp() -> None:
    cfg = PlantConfig()  # default Davis c0, c1, c2
    rot, F, v0, T, dt = 0.06, 30e3, 60.0, 200.0, 1e-3
    m_eff = M * (1 + rot)
    lay = layout(units=1, rot=rot)
    p = plant(lay, v0, limits=OFF)
    x0 = float(p.x[0])
    p.command(0, F, BrakeMode.NORMAL, 0.0)
    run(p, T)

    def rhs(_t, z):
        v = z[1]
        return [v, (F - M * (cfg.davis_c0 * np.sign(v) + cfg.davis_c1 * v + cfg.davis_c2 * v * abs(v))) / m_eff]

    ref = solve_ivp(rhs, (0.0, T), [x0, v0], method="DOP853", rtol=1e-10, atol=1e-10)
    a_max = abs(rhs(0, [0, v0])[1])
    # c0, c2 are held over each step (ZOH): the force lags by dt/2, so v is off by about a * dt / 2 and x by
    # the integral of that; tolerances: one step's velocity change, and that times the run length.
    assert p.v[0] == pytest.approx(ref.y[1, -1], abs=a_max * dt)
    assert p.x[0] == pytest.approx(ref.y[0, -1], abs=a_max * dt * T)
    assert abs(p.v[0] - ref.y[1, -1]) > 1e-9  # it is not the exact solution: the bound above is meaningful


# ------------------------------------------------------------------ couplers

def test_pulling_the_head_stretches_the_couplers_and_drags_the_rest() -> None:
    lay = layout(units=3)
    p = plant(lay, limits=OFF, **FREE)
    p.command(0, 100e3, BrakeMode.NORMAL, 0.0)
    for u in (1, 2):
        p.command(u, 0.0, BrakeMode.NORMAL, 0.0)
    run(p, 0.5)
    e = p.coupler_displacements()
    assert np.all(e > 0.0)  # stretched
    assert np.all(p.v[1:] > 0.0) and np.all(p.a[1:] > 0.0)  # the rear units are pulled forward
    assert p.a[0] < 100e3 / M  # the head is held back by the coupler
    assert float(np.sum(M * p.v)) == pytest.approx(100e3 * 0.5, rel=1e-9)  # internal forces cancel


def test_trains_are_not_coupled_to_each_other() -> None:
    lay = layout(count=2, units=2)
    p = plant(lay, limits=OFF, **FREE)
    p.command(0, 100e3, BrakeMode.NORMAL, 0.0)
    run(p, 1.0)
    assert np.all(p.v[:2] > 0) and np.all(p.v[2:] == 0.0)


# ------------------------------------------------------------------ actuator

def one_unit(v0: float, **limits) -> Plant:
    return plant(layout(units=1), v0, limits={"enabled": True, **limits}, **FREE)


def test_traction_envelope_and_brake_limit() -> None:
    fast = {"rate_limit_n_per_s": 1e12}  # no rate limit in this test
    p = one_unit(50.0, **fast)
    p.command(0, 1e6, BrakeMode.NORMAL, 0.0)
    p.step()
    assert p.force_applied[0] == pytest.approx(2.4e6 / 50.0)  # power-limited: P / v
    p = one_unit(5.0, **fast)
    p.command(0, 1e6, BrakeMode.NORMAL, 0.0)
    p.step()
    assert p.force_applied[0] == pytest.approx(300e3)  # below the base speed: max traction
    p = one_unit(50.0, **fast)
    p.command(0, -1e6, BrakeMode.NORMAL, 0.0)
    p.step()
    assert p.force_applied[0] == pytest.approx(-300e3)
    p = one_unit(50.0, **fast)
    p.command(0, 12345.0, BrakeMode.NORMAL, 0.0)
    p.step()
    assert p.force_applied[0] == 12345.0  # inside the envelope: untouched


def test_rate_limit_ramps_the_applied_force() -> None:
    p = one_unit(50.0, rate_limit_n_per_s=200e3)
    p.command(0, 40e3, BrakeMode.NORMAL, 0.0)
    applied = []
    for _ in range(300):
        p.step()
        applied.append(float(p.force_applied[0]))
    k = np.arange(1, 301)
    assert np.allclose(applied, np.minimum(200.0 * k, 40e3))  # 200 N per 1 ms step, then held


def test_disabled_limits_pass_the_command_through() -> None:
    p = plant(layout(units=1), 50.0, limits=OFF, **FREE)
    p.command(0, 5e6, BrakeMode.NORMAL, 0.0)
    p.step()
    assert p.force_applied[0] == 5e6
    assert p.a[0] == pytest.approx(5e6 / M, rel=1e-12)
    p.command(0, -7e6, BrakeMode.NORMAL, p.t)
    p.step()
    assert p.force_applied[0] == -7e6


def test_failsafe_hold_then_service_then_emergency_with_events() -> None:
    lay = layout(units=2)
    fs = {"hold_s": 0.1, "emergency_after_s": 2.0, "service_brake_mps2": 0.8, "emergency_brake_mps2": 1.2}
    p = plant(lay, 30.0, limits=OFF, failsafe=fs, **FREE)
    applied = {}
    while p.t < 2.5 - 1e-9:
        p.command(1, 5e3, BrakeMode.NORMAL, p.t)  # unit 1 keeps talking, unit 0 said something once
        if p.t == 0.0:
            p.command(0, 10e3, BrakeMode.NORMAL, 0.0)
        p.step()
        applied[round(p.t - p.dt, 3)] = float(p.force_applied[0])
    assert applied[0.05] == 10e3 and applied[0.099] == 10e3  # held for hold_s
    assert applied[0.102] == pytest.approx(-0.8 * M) and applied[1.999] == pytest.approx(-0.8 * M)
    assert applied[2.002] == pytest.approx(-1.2 * M) and applied[2.499] == pytest.approx(-1.2 * M)
    assert p.force_applied[1] == 5e3  # fail-safe emergency is per unit, not the train line
    levels = [(round(t, 3), level) for t, level, _ in p.events]
    assert levels == [(0.101, "WARN"), (2.001, "ERROR")]
    assert "train 1 unit 1" in p.events[0][2] and "service" in p.events[0][2]
    p.command(0, 1e3, BrakeMode.NORMAL, p.t)  # commands resume: released
    p.step()
    assert p.force_applied[0] == 1e3
    assert p.events[-1][1] == "INFO" and "released" in p.events[-1][2]
    p.step()
    assert len(p.events) == 3  # events only on changes


def test_no_command_yet_holds_zero_then_fails_safe() -> None:
    fs = {"hold_s": 0.1, "emergency_after_s": 2.0}
    p = plant(layout(units=1), 30.0, limits=OFF, failsafe=fs, **FREE)
    run(p, 0.101)  # steps starting at t = 0 ... 0.1: age <= hold_s
    assert p.force_applied[0] == 0.0 and p.events == []
    p.step()  # starts at t = 0.101
    assert p.force_applied[0] == pytest.approx(-0.8 * M)
    assert [level for _, level, _ in p.events] == ["WARN"]


def test_emergency_on_one_unit_brakes_its_whole_train_only() -> None:
    lay = layout(count=2, units=3)
    p = plant(lay, 30.0, limits={"enabled": True}, **FREE)
    for u in range(6):
        p.command(u, 2e3, BrakeMode.NORMAL, 0.0)
    p.command(1, 2e3, BrakeMode.EMERGENCY, 0.0)
    p.step()
    assert np.allclose(p.force_applied[:3], -1.2 * M)  # train line: every unit of train 1, no rate limit
    assert np.allclose(p.force_applied[3:], 200.0)  # train 2 ramps towards its command (200 kN/s)
    assert p.events[-1][1] == "ERROR" and "train 1" in p.events[-1][2] and "train 1 unit 2" in p.events[-1][2]
    p.command(1, 2e3, BrakeMode.NORMAL, p.t)
    p.step()
    assert p.events[-1][1] == "INFO" and "train 1" in p.events[-1][2]
    assert np.allclose(p.force_applied[:3], -1.2 * M + 200.0)  # ramps on from the brake force


def test_service_mode_brakes_only_its_unit() -> None:
    p = plant(layout(units=2), 30.0, limits=OFF, **FREE)
    p.command(0, 2e3, BrakeMode.SERVICE, 0.0)
    p.command(1, 2e3, BrakeMode.NORMAL, 0.0)
    p.step()
    assert p.force_applied[0] == pytest.approx(-0.8 * M) and p.force_applied[1] == 2e3


@pytest.mark.parametrize("mode", [BrakeMode.SERVICE, BrakeMode.EMERGENCY])
def test_braking_never_drives_a_train_backwards(mode: BrakeMode) -> None:
    lay = layout(units=3)
    p = plant(lay, 3.0, limits={"enabled": True})  # default Davis resistance
    for u in range(3):
        p.command(u, 0.0, mode, 0.0)
    lowest = np.inf
    for _ in range(30):
        run(p, 1.0)
        lowest = min(lowest, float(p.v.min()))
    assert lowest > -1e-3  # at most the c0 sign chatter (c0 dt ~ 1e-5 m/s)
    assert np.abs(p.v).max() < 1e-3
    x_stop = p.x.copy()
    run(p, 10.0)
    assert np.abs(p.x - x_stop).max() < 1e-3  # stays put under the brake


def test_normal_brake_command_at_standstill_does_not_reverse_with_limits() -> None:
    p = plant(layout(units=1), 0.0, limits={"enabled": True})
    p.command(0, -200e3, BrakeMode.NORMAL, 0.0)
    run(p, 5.0)
    assert abs(p.v[0]) < 1e-6 and p.force_applied[0] == 0.0


def test_brake_holds_a_unit_on_an_uphill() -> None:
    track = TrackConfig(grades=[{"start_m": -1e4, "end_m": 1e4, "grade_permille": 20.0}])
    p = plant(layout(units=1), 0.0, track=track, limits={"enabled": True})
    p.command(0, 0.0, BrakeMode.EMERGENCY, 0.0)
    run(p, 20.0)
    # the brake opposes the roll-back; it balances gravity at v = -0.1 * g * 0.02 / 1.2 (< 2 cm/s)
    assert -0.1 * G * 0.02 / 1.2 * 1.01 < p.v[0] < 0.0


# ------------------------------------------------------------------ track

def test_uphill_grade_decelerates_by_g_times_grade() -> None:
    cfg = PlantConfig()
    track = TrackConfig(grades=[{"start_m": 0.0, "end_m": 5000.0, "grade_permille": 10.0}])
    p = plant(layout(units=1), 20.0, track=track, limits=OFF)  # head at 1000 m: on the grade
    p.step()
    resist = cfg.davis_c0 + cfg.davis_c1 * 20.0 + cfg.davis_c2 * 400.0
    assert p.a[0] == pytest.approx(-(0.0981 + resist), abs=1e-6)  # -0.1317832 m/s^2
    assert p.a[0] == pytest.approx(-0.1317832, abs=1e-6)


def test_grade_and_curve_by_position() -> None:
    track = TrackConfig(
        grades=[{"start_m": 900.0, "end_m": 990.0, "grade_permille": -5.0}],
        curves=[{"start_m": 960.0, "end_m": 2000.0, "radius_m": 1000.0}],
        curve_coefficient=600.0,
    )
    lay = layout(units=4)  # fronts at 1000, 975, 950, 925
    p = plant(lay, 10.0, track=track, limits=OFF, **FREE, coupler_stiffness_n_per_m=0.0, coupler_damping_ns_per_m=0.0)
    p.step()
    curve = G * 600.0 / 1000.0 / 1000.0
    expected = [-curve, -curve + G * 0.005, G * 0.005, G * 0.005]  # downhill -5 permille accelerates
    assert np.allclose(p.a, expected, atol=1e-9)


def test_overlapping_segments_are_rejected() -> None:
    track = TrackConfig(grades=[{"start_m": 0.0, "end_m": 100.0, "grade_permille": 1.0},
                                {"start_m": 50.0, "end_m": 150.0, "grade_permille": 2.0}])
    with pytest.raises(ValueError, match=r"track.grades\[0\].*overlaps.*track.grades\[1\]"):
        plant(layout(units=1), track=track)


# ------------------------------------------------------------------ disturbances

def free_units(count: int, units: int, disturbances: list[dict], seed: int = 0) -> Plant:
    """Uncoupled, resistance-free units: a * m = the disturbance force held over the step."""
    return plant(layout(count=count, units=units), 0.0, seed=seed, limits=OFF, disturbances=disturbances, **FREE,
                 coupler_stiffness_n_per_m=0.0, coupler_damping_ns_per_m=0.0)


def test_deterministic_disturbances_act_in_their_window_on_their_units() -> None:
    dist = [
        {"kind": "pulse", "train": 1, "start_s": 0.2, "end_s": 0.4, "amplitude_n": 1000.0},
        {"kind": "step", "unit": 2, "start_s": 0.3, "end_s": 10.0, "amplitude_n": -500.0},
        {"kind": "sine", "train": 2, "unit": 1, "start_s": 0.1, "end_s": 0.6, "amplitude_n": 2000.0, "frequency_hz": 2.0},
    ]
    p = free_units(2, 2, dist)
    for _ in range(700):
        t = p.t
        p.step()
        force = p.a * M
        pulse = 1000.0 * (0.2 <= t < 0.4) * np.array([1, 1, 0, 0])
        step = -500.0 * (0.3 <= t < 10.0) * np.array([0, 1, 0, 1])
        sine = 2000.0 * math.sin(2 * math.pi * 2.0 * (t - 0.1)) * (0.1 <= t < 0.6) * np.array([0, 0, 1, 0])
        assert np.allclose(force, pulse + step + sine, atol=1e-6), t


def test_random_disturbance_is_seeded_and_has_its_stddev() -> None:
    dist = [{"kind": "random", "train": 1, "start_s": 0.0, "end_s": 1e3, "amplitude_n": 3000.0, "correlation_s": 0.05}]
    a, b, c = (free_units(2, 1, dist, seed=s) for s in (7, 7, 8))
    for _ in range(2000):
        for p in (a, b, c):
            p.step()
    assert np.array_equal(a.x, b.x) and not np.array_equal(a.x, c.x)
    assert a.v[0] != 0.0 and a.v[1] == 0.0  # train 2 untouched
    forces = []
    for _ in range(60000):
        a.step()
        forces.append(a.a[0] * M)
    f = np.array(forces)
    assert np.std(f) == pytest.approx(3000.0, rel=0.1)  # 60 s / 0.05 s = 1200 correlation times
    lag = int(0.05 / 1e-3)
    assert np.corrcoef(f[:-lag], f[lag:])[0, 1] == pytest.approx(math.exp(-1.0), abs=0.1)


def test_disturbance_on_a_missing_train_is_an_error() -> None:
    with pytest.raises(ValueError, match=r"plant.disturbances\[0\].train = 3"):
        free_units(2, 1, [{"kind": "pulse", "train": 3, "start_s": 0.0, "end_s": 1.0, "amplitude_n": 1.0}])


# ------------------------------------------------------------------ divergence, sensors, cost

def test_nan_command_raises_naming_the_unit() -> None:
    p = plant(layout(count=2, units=2))
    with pytest.raises(PlantDiverged, match=r"train 2 unit 1"):
        p.command(2, float("nan"), BrakeMode.NORMAL, 0.0)


def test_non_finite_state_raises_naming_the_unit() -> None:
    p = plant(layout(units=3))
    p.v[1] = np.inf
    with np.errstate(invalid="ignore"), pytest.raises(PlantDiverged, match=r"t = 0\.000000 s.*train 1 unit 2"):
        p.step()


def test_runaway_force_diverges_and_is_reported() -> None:
    p = plant(layout(units=2), limits=OFF)
    p.command(0, 1e300, BrakeMode.NORMAL, 0.0)
    with np.errstate(over="ignore", invalid="ignore"), pytest.raises(PlantDiverged, match=r"train 1 unit 1"):
        run(p, 1.0)
    assert p.t < 0.01


def test_measure_returns_noisy_copies() -> None:
    lay = layout(units=4)
    p = plant(lay, 10.0, sensor={"position_noise_m": 0.5, "speed_noise_mps": 0.0})
    x, v = p.measure()
    assert np.array_equal(v, p.v) and v is not p.v
    assert 0.0 < np.abs(x - p.x).max() < 5 * 0.5
    x[:] = 0.0
    assert p.x.min() > 0.0
    xs = np.array([p.measure()[0] - p.x for _ in range(2000)])
    assert np.std(xs) == pytest.approx(0.5, rel=0.05)


def test_block_propagator_matches_dense(monkeypatch: pytest.MonkeyPatch) -> None:
    lay = layout(count=3, units=4)
    dense = plant(lay, 50.0, dx=np.linspace(-0.02, 0.03, 12))
    monkeypatch.setattr(dynamics, "DENSE_MAX_UNITS", 0)
    block = plant(lay, 50.0, dx=np.linspace(-0.02, 0.03, 12))
    assert not block._prop.dense and dense._prop.dense
    for p in (dense, block):
        for u in range(12):
            p.command(u, 1e3 * u, BrakeMode.NORMAL, 0.0)
        run(p, 2.0)
    assert np.allclose(block.x, dense.x, rtol=0, atol=1e-9) and np.allclose(block.v, dense.v, rtol=0, atol=1e-12)
    assert np.allclose(block.a, dense.a, rtol=0, atol=1e-9)


def test_step_cost() -> None:
    lay = layout(count=3, units=4)
    p = plant(lay, 80.0, limits={"enabled": True})
    for u in range(12):
        p.command(u, 50e3, BrakeMode.NORMAL, 0.0)
    n = 5000
    best = np.inf
    for _ in range(3):
        t0 = time.perf_counter()
        for _ in range(n):
            p.step()
        best = min(best, (time.perf_counter() - t0) / n)
    print(f"plant step at 12 units, limits on: {best * 1e6:.1f} us")
    assert best < 100e-6  # measured 7-14 us on the 2-core dev machine; generous for loaded CI


def test_bad_inputs_are_named() -> None:
    lay = layout(units=2)
    p = plant(lay)
    with pytest.raises(IndexError, match="unit index 2"):
        p.command(2, 0.0, BrakeMode.NORMAL, 0.0)
    with pytest.raises(ValueError, match=r"mode 7 for train 1 unit 2"):
        p.command(1, 0.0, 7, 0.0)
    with pytest.raises(ValueError, match=r"x0 has shape \(3,\)"):
        Plant(PlantConfig(), TrackConfig(), lay, np.zeros(3), np.zeros(2), np.random.default_rng(0))
    with pytest.raises(ValueError, match=r"v0 has non-finite values at units \[1\]"):
        Plant(PlantConfig(), TrackConfig(), lay, np.zeros(2), np.array([0.0, np.nan]), np.random.default_rng(0))
