"""hil/compare/multi_train.py: seed 002's Table 4 metrics and seed 003's tracking errors on synthetic runs."""
from __future__ import annotations

import numpy as np
import pytest

from hil.compare.multi_train import seed002_metrics, seed003_metrics, settle_time, spacing_overshoot
from hil.scenario.layout import TrainLayout
from hil.record.runlog import RunLog
from hil.scenario.model import TrainsConfig

TRAINS = TrainsConfig(count=3, units=1, unit_mass_kg=400e3, unit_length_m=200.0, head_positions_m=[20000.0, 12600.0, 5200.0],
                      speeds_mps=[65.0, 65.0, 65.0], spacing_m=7200.0, emergency_gap_m=2000.0)


def synthetic(t: np.ndarray, d: np.ndarray, v: np.ndarray, v_r: np.ndarray, force: np.ndarray, changes: list[float]) -> RunLog:
    """A RunLog with head-to-head distances d (k, 2), speeds v (k, 3), reference v_r (k,) and commands (k, 3)."""
    log = RunLog(TrainLayout.from_config(TRAINS))
    log.reference_change_times = changes
    for k in range(len(t)):
        x = np.array([50000.0, 50000.0 - d[k, 0], 50000.0 - d[k, 0] - d[k, 1]]) + 65.0 * t[k]
        log.add_sample(t[k], 50000.0 + 65.0 * t[k], v_r[k], x, v[k], np.zeros(3), force[k], force[k])
    return log


def test_settle_time_and_overshoot():
    t = np.arange(10.0)
    assert settle_time(t, np.array([0, 0, 1, 0, 1, 1, 1, 1, 1, 1], dtype=bool), 0.0) == 4.0
    assert settle_time(t, np.array([1] * 9 + [0], dtype=bool), 0.0) is None
    d_r = np.array([7400.0, 7400.0])
    # pair 1 closes from 7500 to 7400 without passing it: no overshoot; pair 2 passes d_r by 50 m
    d = np.array([[7500.0, 7300.0], [7450.0, 7420.0], [7400.0, 7450.0], [7400.0, 7400.0]])
    assert spacing_overshoot(d, d_r).tolist() == [0.0, 50.0]
    # a gap that first grows away from d_r overshoots by the growth
    assert spacing_overshoot(np.array([[7500.0], [7600.0], [7400.0]]), d_r[:1]).tolist() == [100.0]


def test_seed002_metrics_on_a_synthetic_run():
    t = np.arange(0.0, 300.0, 1.0)
    v_r = np.where(t < 200.0, 65.0, 73.0)
    v = np.repeat(v_r[:, None], 3, axis=1) + np.where(t < 50.0, -5.0, 0.0)[:, None]
    v[(t >= 200.0) & (t < 230.0)] -= 8.0  # re-converges 30 s after the step
    d = np.column_stack([np.where(t < 50.0, 7600.0, 7500.0), np.full(len(t), 7300.0)])
    force = np.zeros((len(t), 3))
    force[0, 2] = 400e3 * 2.5
    m = seed002_metrics(synthetic(t, d, v, v_r, force, [200.0]))
    assert m["convergence_time_s"] == 50.0 and m["reconvergence_s"] == [30.0]
    assert m["max_spacing_overshoot_km"] == pytest.approx(0.0)  # 7600 -> 7500 and 7300 never pass d_r = 7400
    assert m["spacing_band_km"] == pytest.approx([7.3, 7.5])
    assert m["mean_steady_error_km"] == pytest.approx([0.1, -0.1])
    assert m["peak_accel_demand_mps2"] == pytest.approx(2.5)


def test_seed003_metrics_window_and_speed_limit():
    t = np.arange(0.0, 100.0, 1.0)
    v_r = np.full(len(t), 80.0)
    v = np.full((len(t), 3), 80.0)
    v[10, 1] = 84.0  # above an 83.33 m/s limit for one 1 s sample
    d = np.full((len(t), 2), 7400.0)
    log = synthetic(t, d, v, v_r, np.zeros((len(t), 3)), [])
    m = seed003_metrics(log, 50.0, 300 / 3.6)
    assert m["speed_limit_exceeded"] and m["time_above_limit_s"] == 1.0 and m["speed_max_mps"] == 84.0
    assert max(m["v_err_max_mps"]) == 0.0  # the excursion lies before the window
