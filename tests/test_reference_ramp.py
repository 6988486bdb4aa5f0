"""Ramp reference segments (exact x_r, a_r on the wayside frame) and per-unit initial positions."""
from __future__ import annotations

import numpy as np
import pytest
from pydantic import ValidationError
from scipy.integrate import quad

from ecu_sim.codec import TrainDb
from hil.scenario.layout import TrainLayout
from hil.reference_profile import ReferenceProfile
from hil.runtime.assembly import assemble
from hil.scenario import load_scenario
from hil.scenario.model import ReferenceConfig, TrainsConfig

RAMPS = ReferenceConfig(by="time", x0_m=500.0, segments=[
    {"start": 0.0, "end": 100.0, "speed_mps": 0.0, "to_speed_mps": 50.0},
    {"start": 100.0, "end": 300.0, "speed_mps": 50.0},
    {"start": 300.0, "end": 350.0, "speed_kmh": 180.0, "to_speed_kmh": 0.0},
])


def test_ramp_gives_linear_speed_constant_accel_and_exact_position():
    ref = ReferenceProfile.from_config(RAMPS)
    x, v, a = ref.state(40.0)
    assert (v, a) == (pytest.approx(20.0), pytest.approx(0.5))
    assert x == pytest.approx(500.0 + 0.5 * 0.5 * 40.0**2, abs=1e-9)
    # x_r is the integral of v_r at every time, across ramps and the constant segment (independent quadrature)
    for t in (99.999, 100.0, 250.0, 320.0, 349.9, 400.0):
        integral = quad(lambda s: ref.state(s)[1], 0.0, t, points=[100.0, 300.0, 350.0], limit=200)[0]
        assert ref.state(t)[0] == pytest.approx(500.0 + integral, abs=1e-6)
    assert ref.state(325.0)[1:] == (pytest.approx(25.0), pytest.approx(-1.0))
    # after a final ramp the end speed holds with a_r = 0 (no ramping on to negative speeds)
    x1, v1, a1 = ref.state(350.0)
    x2, v2, a2 = ref.state(500.0)
    assert (v1, a1, v2, a2) == (pytest.approx(0.0, abs=1e-12), 0.0, pytest.approx(0.0, abs=1e-12), 0.0)
    assert x2 == pytest.approx(x1) and x1 == pytest.approx(500 + 2500 + 10_000 + 1250)
    assert ref.at(40.0) == ref.state(40.0)[:2]


def test_step_profiles_keep_their_representation_and_values():
    cfg = ReferenceConfig(by="time", x0_m=1000.0, segments=[
        {"start": 0.0, "end": 100.0, "speed_mps": 65.0},
        {"start": 100.0, "end": 200.0, "speed_mps": 73.0},
    ])
    ref = ReferenceProfile.from_config(cfg)
    assert ref.accels == ()  # no slope table: the historical arithmetic is used unchanged
    assert ref.state(150.0) == (1000.0 + 6500.0 + 73.0 * 50.0, 73.0, 0.0)


def test_ramp_rejected_on_position_profiles_and_with_both_units():
    with pytest.raises(ValidationError, match="needs by"):
        ReferenceConfig(by="position", x0_m=0.0, segments=[{"start": 0.0, "end": 10.0, "speed_mps": 1.0, "to_speed_mps": 2.0}])
    with pytest.raises(ValidationError, match="at most one of to_speed"):
        ReferenceConfig(by="time", x0_m=0.0, segments=[{"start": 0.0, "end": 10.0, "speed_mps": 1.0,
                                                        "to_speed_mps": 2.0, "to_speed_kmh": 7.2}])


def test_reference_aux_frame_carries_a_r():
    """The wayside's ReferenceAux encodes a_r (DBC: 0.001 m/s^2 steps); an ECU decodes it as ReferenceView.a."""
    from hil.plant.can_node import PlantCanNode

    layout = TrainLayout.from_config(load_scenario("seed000").trains)
    db = TrainDb.load()
    node = PlantCanNode(db, layout, None, ReferenceProfile.from_config(RAMPS), None)  # type: ignore[arg-type]  (no plant needed)
    (_, ref_data), (aux_id, aux_data) = node.reference_frames(40.0)
    assert db.by_id[aux_id].decode(aux_data)[0] == pytest.approx(0.5, abs=5e-4)
    (_, _), (_, aux_data) = node.reference_frames(320.0)
    assert db.by_id[aux_id].decode(aux_data)[0] == pytest.approx(-1.0, abs=5e-4)
    x_r, v_r = db.reference.decode(ref_data)
    assert v_r == pytest.approx(20.0, abs=5e-4) and x_r == pytest.approx(900.0, abs=1e-3)


TRAIN = dict(count=1, units=6, unit_mass_kg=8e4, unit_length_m=81.0, head_positions_m=[486.6],
             speeds_mps=[0.0], spacing_m=3000.0, emergency_gap_m=1500.0)
SEED001 = [486.6, 405.1, 324.1, 243.2, 162.0, 81.0]


def test_unit_positions_are_used_by_the_plant():
    sc = load_scenario("seed000")
    sc = sc.model_copy(update={"trains": TrainsConfig(**TRAIN, unit_positions_m=[SEED001])})
    parts = assemble(sc)
    assert parts.plant.x.tolist() == pytest.approx(SEED001)
    assert parts.plant.coupler_displacements() == pytest.approx([0.5, 0.0, -0.1, 0.2, 0.0], abs=1e-9)
    at_rest = assemble(sc.model_copy(update={"trains": TrainsConfig(**TRAIN)}))
    assert np.allclose(at_rest.plant.coupler_displacements(), 0.0)


@pytest.mark.parametrize("rows, message", [
    ([SEED001[:5]], r"unit_positions_m\[0\] has 5 values"),
    ([SEED001, SEED001], "has 2 lists"),
    ([[480.0] + SEED001[1:]], r"differs from head_positions_m\[0\]"),
    ([[486.6, 405.1, 410.0, 243.2, 162.0, 81.0]], r"unit_positions_m\[0\]\[2\] = 410.0 m is not behind"),
    ([[486.6, 405.1, float("nan"), 243.2, 162.0, 81.0]], "finite"),
])
def test_unit_positions_validation_names_the_field(rows, message):
    with pytest.raises(ValidationError, match=message):
        TrainsConfig(**TRAIN, unit_positions_m=rows)
