"""The position-channel (mismatched) disturbance dx/dt = v + d2, and the unchanged default force channel."""
from __future__ import annotations

import numpy as np
import pytest

from hil.scenario.layout import TrainLayout
from hil.plant import Plant
from hil.scenario import ScenarioError, load_scenario
from hil.scenario.model import Disturbance, PlantConfig, TrackConfig, TrainsConfig

TRAINS = TrainsConfig(count=2, units=1, unit_mass_kg=400e3, unit_length_m=200.0, head_positions_m=[10000.0, 6000.0],
                      speeds_mps=[60.0, 60.0], spacing_m=3800.0, emergency_gap_m=1000.0)
FORCE = [{"kind": "random", "start_s": 0.0, "end_s": 30.0, "amplitude_n": 5e3, "correlation_s": 2.0},
         {"kind": "sine", "train": 2, "start_s": 1.0, "end_s": 20.0, "amplitude_n": 20e3, "frequency_hz": 0.1}]
POSITION = [{"kind": "step", "channel": "position", "train": 1, "start_s": 5.0, "end_s": 15.0, "amplitude_mps": 0.3},
            {"kind": "sine", "channel": "position", "train": 2, "start_s": 0.0, "end_s": 30.0, "amplitude_mps": 0.2,
             "frequency_hz": 0.05}]


def run(disturbances: list[dict], seconds: float = 30.0) -> tuple[np.ndarray, np.ndarray]:
    layout = TrainLayout.from_config(TRAINS)
    cfg = PlantConfig(step_s=0.01, disturbances=[Disturbance(**d) for d in disturbances], limits={"enabled": False})
    plant = Plant(cfg, TrackConfig(), layout, layout.initial_positions(TRAINS.head_positions_m), np.full(2, 60.0),
                  np.random.default_rng(5))
    xs, vs = [], []
    for _ in range(round(seconds / 0.01)):
        plant.command(0, 2e4, 0, plant.t)
        plant.command(1, 2e4, 0, plant.t)
        plant.step()
        xs.append(plant.x.copy())
        vs.append(plant.v.copy())
    return np.array(xs), np.array(vs)


def test_position_channel_moves_x_only_by_the_integral_of_d2():
    x0, v0 = run(FORCE)
    x1, v1 = run(FORCE + POSITION)
    assert np.array_equal(v0, v1)  # d2 never enters the speed (mismatched) and draws no random numbers
    t = np.arange(1, len(x0) + 1) * 0.01
    # train 1: +0.3 m/s over [5, 15) s -> +3 m from 15 s on (rectangle rule at the 10 ms step)
    assert x1[-1, 0] - x0[-1, 0] == pytest.approx(3.0, abs=1e-6)
    assert np.all(np.abs((x1 - x0)[t < 5.0, 0]) < 1e-9)
    # train 2: 0.2 sin(2 pi 0.05 t) over [0, 30): integral (0.2 / (2 pi 0.05)) (1 - cos(2 pi 0.05 t))
    expected = 0.2 / (2 * np.pi * 0.05) * (1 - np.cos(2 * np.pi * 0.05 * t))
    assert np.max(np.abs((x1 - x0)[:, 1] - expected)) < 2e-3


def test_default_channel_is_force_and_a_zero_position_disturbance_changes_nothing():
    d = Disturbance(kind="step", start_s=0.0, end_s=1.0, amplitude_n=1e3)
    assert d.channel == "force" and d.amplitude == 1e3
    x0, v0 = run(FORCE)
    zero = [dict(POSITION[0], amplitude_mps=0.0)]
    x1, v1 = run(FORCE + zero)
    assert np.array_equal(x0, x1) and np.array_equal(v0, v1)
    # the force channel is not the position channel: the same number as a force changes v
    _, v2 = run(FORCE + [{"kind": "step", "train": 1, "start_s": 5.0, "end_s": 15.0, "amplitude_n": 0.3}])
    assert not np.array_equal(v0, v2)


def test_channel_amplitudes_are_checked_with_named_fields():
    with pytest.raises(ValueError, match="needs amplitude_mps"):
        Disturbance(kind="step", channel="position", start_s=0.0, end_s=1.0)
    with pytest.raises(ValueError, match="amplitude_n does not apply"):
        Disturbance(kind="step", channel="position", start_s=0.0, end_s=1.0, amplitude_mps=0.1, amplitude_n=5.0)
    with pytest.raises(ValueError, match="needs amplitude_n"):
        Disturbance(kind="step", start_s=0.0, end_s=1.0)
    with pytest.raises(ScenarioError, match="plant.disturbances.3"):
        load_scenario("seed003-p1", {"plant.disturbances": [dict(d) for d in POSITION] + [dict(FORCE[0])]
                                     + [{"kind": "step", "channel": "speed", "start_s": 0.0, "end_s": 1.0}]})
