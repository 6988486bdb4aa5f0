"""Per-unit plant features (seed 004): masses, rotating-mass factors, Davis resistance, the actuator chain
lambda (h rho Q(F) + nu), health faults and their API, the seeded draw, and unchanged defaults."""
from __future__ import annotations

import numpy as np
import pytest
from pydantic import ValidationError

from hil.scenario.layout import TrainLayout
from hil.plant import Plant
from ecu_sim.track import G
from hil.plant.units import specific_to_per_kg, unit_params
from hil.scenario.model import PlantConfig, Scenario, TrackConfig, TrainsConfig

M = 50e3
NEVER = {"hold_s": 1e9, "emergency_after_s": 1e9}
OFF = {"enabled": False}
FREE = {"davis_c0": 0.0, "davis_c1": 0.0, "davis_c2": 0.0}


def layout(units: int = 3, count: int = 1) -> TrainLayout:
    trains = TrainsConfig(count=count, units=units, unit_mass_kg=M, unit_length_m=25.0, rotating_mass_factor=0.1,
                          head_positions_m=[1000.0 - 1000.0 * i for i in range(count)], speeds_mps=[0.0] * count,
                          spacing_m=300.0, emergency_gap_m=100.0)
    return TrainLayout.from_config(trains)


def make(lay: TrainLayout, v0: float = 10.0, seed: int = 0, **cfg) -> Plant:
    cfg.setdefault("failsafe", NEVER)
    cfg.setdefault("limits", OFF)
    x0 = lay.initial_positions([1000.0 - 1000.0 * i for i in range(lay.n_trains)])
    return Plant(PlantConfig(**cfg), TrackConfig(), lay, x0, np.full(lay.n_units, v0), np.random.default_rng(seed))


def run(p: Plant, seconds: float) -> None:
    for _ in range(int(round(seconds / p.dt))):
        p.step()


def command_all(p: Plant, force: float) -> None:
    for u in range(p.layout.n_units):
        p.command(u, force, 0, p.t)


# ------------------------------------------------------------------ per-unit masses and resistance


def test_per_unit_masses_and_c0_give_each_unit_its_own_acceleration() -> None:
    # No couplers (k = d = 0), c1 = c2 = 0: m_eff dv/dt = F - m c0 (v > 0) exactly, per unit.
    lay = layout(3)
    mass, rot, c0 = [40e3, 50e3, 63e3], [0.08, 0.10, 0.11], [0.005, 0.010, 0.020]
    p = make(lay, coupler_stiffness_n_per_m=0.0, coupler_damping_ns_per_m=0.0, step_s=1e-3,
             units={"mass_kg": {"values": mass}, "rotating_mass_factor": {"values": rot},
                    "resistance": {"form": "per_kg", "c0": {"values": c0}, "c1": {"values": [0.0] * 3}, "c2": {"values": [0.0] * 3}}})
    np.testing.assert_array_equal(p.layout.mass_kg, mass)
    np.testing.assert_allclose(p.layout.effective_mass_kg, np.multiply(mass, 1 + np.array(rot)), rtol=1e-15)
    command_all(p, 20e3)
    run(p, 5.0)
    expected = 10.0 + (20e3 - np.multiply(mass, c0)) * 5.0 / (np.multiply(mass, 1 + np.array(rot)))
    np.testing.assert_allclose(p.v, expected, rtol=1e-9)


def test_per_unit_c1_is_inside_the_exact_step_map() -> None:
    # c1 only (no couplers, no force): v(t) = v0 exp(-c1 m / m_eff t), whatever the step.
    lay = layout(2)
    c1 = [1e-3, 4e-3]
    p = make(lay, coupler_stiffness_n_per_m=0.0, coupler_damping_ns_per_m=0.0, step_s=0.01,
             units={"resistance": {"form": "per_kg", "c0": {"values": [0.0, 0.0]}, "c1": {"values": c1}, "c2": {"values": [0.0, 0.0]}}})
    run(p, 100.0)
    expected = 10.0 * np.exp(-np.array(c1) / 1.1 * 100.0)
    np.testing.assert_allclose(p.v, expected, rtol=1e-10)


def test_specific_resistance_converts_the_crh5_formula() -> None:
    # CRH5: w0 = 0.69 + 0.0063 V + 0.00015 V^2 N/kN (V in km/h), i.e. a0 = 69, a1 = 63, a2 = 1.5.
    v = 300 / 3.6
    w0 = 0.69 + 0.0063 * 300 + 0.00015 * 300**2  # 16.08 N/kN
    c0, c1, c2 = specific_to_per_kg(np.array(69.0), np.array(63.0), np.array(1.5))
    assert c0 + c1 * v + c2 * v * v == pytest.approx(w0 * G / 1000, rel=1e-12)
    assert c0 == pytest.approx(0.69 * G / 1000) and c1 * v == pytest.approx(0.0063 * 300 * G / 1000)


def test_specific_resistance_acts_on_the_physical_mass() -> None:
    lay = layout(1)
    p = make(lay, v0=50.0, step_s=1e-3, units={"resistance": {"form": "specific_kmh", "a0": {"values": [69.0]},
                                                              "a1": {"values": [0.0]}, "a2": {"values": [0.0]}}})
    run(p, 1.0)  # constant resistance 0.69 N/kN of the weight, decelerating the effective mass
    assert p.v[0] == pytest.approx(50.0 - 0.69e-3 * G / 1.1, rel=1e-9)


# ------------------------------------------------------------------ the seeded draw


def _drawn(seed: int, run_seed: int = 0) -> Plant:
    units = {"seed": seed, "mass_kg": {"uniform": [44e3, 63e3]}, "rotating_mass_factor": {"uniform": [0.08, 0.11]},
             "resistance": {"form": "specific_kmh", "a0": {"uniform": [50, 85]}, "a1": {"uniform": [30, 100]},
                            "a2": {"uniform": [0.1, 6.5]}}}
    return make(layout(8), seed=run_seed, units=units, actuator={"slope": {"uniform": [0.9, 1.0]}})


def test_drawn_values_are_reproducible_in_range_independent_of_the_run_seed_and_logged() -> None:
    a, b, other_run, other_draw = _drawn(4), _drawn(4), _drawn(4, run_seed=99), _drawn(5)
    for arr in ("mass_kg", "effective_mass_kg"):
        np.testing.assert_array_equal(getattr(a.layout, arr), getattr(b.layout, arr))
        np.testing.assert_array_equal(getattr(a.layout, arr), getattr(other_run.layout, arr))
    assert not np.array_equal(a.layout.mass_kg, other_draw.layout.mass_kg)
    assert np.all((a.layout.mass_kg >= 44e3) & (a.layout.mass_kg <= 63e3))
    assert len(set(a.layout.mass_kg.tolist())) == 8  # drawn per unit
    ratio = a.layout.effective_mass_kg / a.layout.mass_kg
    assert np.all((ratio >= 1.08) & (ratio <= 1.11))
    lo, hi = specific_to_per_kg(*np.array([50.0, 30.0, 0.1])), specific_to_per_kg(*np.array([85.0, 100.0, 6.5]))
    for c, a_lo, a_hi in zip((a.units.c0, a.units.c1, a.units.c2), lo, hi):
        assert np.all((c >= a_lo) & (c <= a_hi))
    assert np.all((a.units.slope >= 0.9) & (a.units.slope <= 1.0))
    # the draw is in the event log at t = 0, value by value
    (t, level, text), = a.events
    assert t == 0.0 and "draw seed 4" in text
    for m in a.layout.mass_kg:
        assert f"{m:.6g}" in text


def test_a_quantity_draws_the_same_whatever_else_is_drawn() -> None:
    lay = layout(8)
    only_mass = unit_params(lay, PlantConfig(units={"seed": 4, "mass_kg": {"uniform": [44e3, 63e3]}}))
    both = unit_params(lay, PlantConfig(units={"seed": 4, "mass_kg": {"uniform": [44e3, 63e3]},
                                               "rotating_mass_factor": {"uniform": [0.08, 0.11]}}))
    np.testing.assert_array_equal(only_mass.layout.mass_kg, both.layout.mass_kg)


def test_per_train_lists_repeat_and_group_lists_apply_unit_by_unit() -> None:
    lay = layout(2, count=2)
    per_train = unit_params(lay, PlantConfig(actuator={"distribution": {"values": [0.5, 0.3]}}))
    np.testing.assert_array_equal(per_train.distribution, [0.5, 0.3, 0.5, 0.3])
    group = unit_params(lay, PlantConfig(actuator={"distribution": {"values": [0.5, 0.3, 0.6, 0.4]}}))
    np.testing.assert_array_equal(group.distribution, [0.5, 0.3, 0.6, 0.4])


# ------------------------------------------------------------------ the actuator chain and health faults


def test_distribution_slope_notch_and_offset_shape_the_applied_force() -> None:
    lay = layout(2)
    p = make(lay, actuator={"distribution": {"values": [0.5, 0.3]}, "slope": {"values": [0.9, 1.0]}, "notch_step_n": 1000.0},
             actuator_faults=[{"unit": 2, "start_s": 0.0, "offset_n": -400.0}])
    p.command(0, 12_345.0, 0, 0.0)
    p.command(1, -7_760.0, 0, 0.0)
    p.step()
    # lambda (h rho Q(F) + nu): Q rounds to 1 kN notches
    np.testing.assert_allclose(p.force_applied, [0.5 * 0.9 * 12_000.0, 0.3 * (1.0 * -8_000.0 - 400.0)], rtol=1e-15)
    np.testing.assert_array_equal(p.force_cmd, [12_345.0, -7_760.0])  # the ECU's command is recorded unshaped


def test_health_fault_scales_the_force_from_its_time_and_ramps() -> None:
    lay = layout(3)
    p = make(lay, step_s=1e-3, actuator={"distribution": {"values": [0.5, 0.3, 0.5]}},
             actuator_faults=[{"unit": 2, "start_s": 1.0, "health": 0.6},
                              {"unit": 3, "start_s": 1.0, "health": 0.5, "ramp_s": 2.0}])
    command_all(p, 10e3)
    applied = []
    while p.t < 3.5 - 1e-9:
        t = p.t
        p.step()
        applied.append((t, p.force_applied.copy()))
    before = [f for t, f in applied if t < 1.0 - 1e-9]
    np.testing.assert_allclose(before[-1], [5e3, 3e3, 5e3])  # healthy up to the step before 1 s
    at = dict((round(t, 6), f) for t, f in applied)
    np.testing.assert_allclose(at[1.0], [5e3, 0.6 * 3e3, 5e3])  # the step is exact at its start
    np.testing.assert_allclose(at[2.0], [5e3, 0.6 * 3e3, 0.75 * 5e3])  # half way down the ramp
    np.testing.assert_allclose(at[3.4], [5e3, 0.6 * 3e3, 0.5 * 5e3])  # ramp done, held
    np.testing.assert_allclose(p.health, [1.0, 0.6, 0.5])
    texts = [(round(t, 6), text) for t, _, text in p.events]
    assert (1.0, "train 1 unit 2 (#1): actuator health 1 -> 0.6") in texts
    assert any(t == 1.0 and "unit 3" in text and "over 2 s" in text for t, text in texts)


def test_set_health_api_total_loss_and_repair_at_run_time() -> None:
    lay = layout(2)
    p = make(lay, step_s=1e-3)
    command_all(p, 10e3)
    run(p, 0.5)
    p.set_health(1, 0.0, at_s=1.0)  # total traction loss of car 2 at t = 1 s
    run(p, 0.6)
    np.testing.assert_allclose(p.force_applied, [10e3, 0.0])
    p.set_health(1, 1.0, at_s=None, ramp_s=1.0)  # repair from now over 1 s
    run(p, 0.5)
    assert 4e3 < p.force_applied[1] < 6e3
    run(p, 0.6)
    assert p.force_applied[1] == 10e3
    with pytest.raises(ValueError, match="health 1.5"):
        p.set_health(0, 1.5)
    with pytest.raises(IndexError):
        p.set_health(7, 0.5)


def test_service_brake_bypasses_the_faulty_actuator() -> None:
    lay = layout(1)
    p = make(lay, step_s=1e-3, actuator_faults=[{"unit": 1, "start_s": 0.0, "health": 0.0}])
    p.command(0, 0.0, 1, 0.0)  # SERVICE
    p.step()
    assert p.force_applied[0] == pytest.approx(-0.8 * lay.effective_mass_kg[0])


# ------------------------------------------------------------------ defaults stay as they were


def test_defaults_keep_scalars_and_no_chain() -> None:
    p = make(layout(3))
    assert p.units.configured == {} and isinstance(p.units.c0, float) and isinstance(p.units.c1, float)
    assert not p._act._chain and p.events == []


def test_per_unit_values_equal_to_the_scalars_run_bit_for_bit_like_the_default() -> None:
    lay = layout(4)
    base = {"coupler_stiffness_n_per_m": 1.6e5, "step_s": 1e-3}
    same = {"units": {"mass_kg": {"values": [M] * 4}, "rotating_mass_factor": {"values": [0.1] * 4},
                      "resistance": {"form": "per_kg", "c0": {"values": [0.01176] * 4}, "c1": {"values": [0.00077616] * 4},
                                     "c2": {"values": [1.6e-5] * 4}}}}
    a, b = make(lay, **base), make(lay, **base, **same)
    for p in (a, b):
        p.command(0, 40e3, 0, 0.0)
        p.command(3, -10e3, 0, 0.0)
        run(p, 20.0)
    np.testing.assert_array_equal(a.x, b.x)
    np.testing.assert_array_equal(a.v, b.v)


def test_the_firmware_keeps_the_nominal_masses() -> None:
    # the plant's cars are drawn; the ECU's AgentInfo (assembly's layout) keeps [trains]' nominal car
    lay = layout(3)
    p = make(lay, units={"mass_kg": {"uniform": [44e3, 63e3]}})
    assert lay.agent_info(1).mass_kg == pytest.approx(M * 1.1)
    assert not np.allclose(p.layout.mass_kg, M)


# ------------------------------------------------------------------ bad input


@pytest.mark.parametrize("plant, message", [
    ({"units": {"mass_kg": {"values": [1.0, 2.0]}}}, "plant.units.mass_kg.values has 2 values"),
    ({"actuator_faults": [{"unit": 9, "start_s": 1.0, "health": 0.5}]}, "actuator_faults\\[0\\]: train 1 unit 9"),
    ({"units": {"mass_kg": {"uniform": [63e3, 44e3]}}}, "lo <= hi"),
    ({"units": {"mass_kg": {"values": [1.0], "uniform": [1.0, 2.0]}}}, "exactly one of values or uniform"),
    ({"actuator_faults": [{"unit": 1, "start_s": 1.0, "health": 1.2}]}, "less than or equal to 1"),
    ({"actuator": {"distribution": {"values": [1.5]}}}, "distribution: values must lie in"),
    ({"units": {"resistance": {"form": "specific_kmh", "c0": {"values": [1.0]}}}}, "takes a0, a1, a2"),
])
def test_bad_per_unit_config_is_an_error_naming_the_field(plant: dict, message: str) -> None:
    data = {"name": "x", "duration_s": 1.0, "controller": {"law": "consensus"},
            "trains": {"count": 1, "units": 8, "unit_mass_kg": M, "unit_length_m": 25.0, "head_positions_m": [1000.0],
                       "speeds_mps": [0.0], "spacing_m": 3000.0, "emergency_gap_m": 1500.0},
            "reference": {"by": "time", "x0_m": 1000.0, "segments": [{"start": 0.0, "end": 10.0, "speed_mps": 1.0}]},
            "plant": plant}
    with pytest.raises(ValidationError, match=message):
        Scenario(**data)
