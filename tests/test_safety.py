"""The safety supervisor (hil/record/safety.py) on synthetic run logs: each verdict, its interval, worst value and
cause, and the block metrics.json carries."""
from __future__ import annotations

import numpy as np
import pytest

from hil.scenario.layout import TrainLayout
from hil.record.metrics import compute_metrics
from hil.record.runlog import RunLog
from hil.record.safety import KMH, check_safety, ebi_margin, explain, safety_report
from hil.scenario.model import TrainsConfig

BAND = (-0.1, 0.1)
L_E = 1500.0


def layout() -> TrainLayout:
    return TrainLayout.from_config(TrainsConfig(count=2, units=2, unit_mass_kg=80e3, unit_length_m=80.0,
                                                head_positions_m=[10_000.0, 6_840.0], speeds_mps=[80.0, 80.0],
                                                spacing_m=3000.0, emergency_gap_m=L_E))


def synthetic(gap_of_t, coupler_of_t=lambda t: 0.0, v_extra_of_t=lambda t: 0.0, v_ref: float = 80.0,
              t_end: float = 100.0) -> RunLog:
    """Train 1 at v_ref; train 2's head placed to give gap_of_t(t); coupler 1 of train 1 displaced by coupler_of_t;
    train 2 unit 2 faster by v_extra_of_t."""
    L = layout()
    log = RunLog(L)
    zeros = np.zeros(L.n_units)
    for t in np.arange(0.0, t_end + 1e-9, 0.1):
        head1 = 10_000.0 + v_ref * t
        x = np.array([head1, head1 - 80.0 - coupler_of_t(t), 0.0, 0.0])
        rear1 = x[1] - 80.0
        x[2] = rear1 - gap_of_t(t)
        x[3] = x[2] - 80.0
        v = np.full(4, v_ref)
        v[3] += v_extra_of_t(t)
        log.add_sample(float(t), head1, v_ref, x, v, zeros, zeros, zeros)
    log.sim_time_s = t_end
    return log


def test_ebi_margin_follows_the_etcs_defaults():
    v = np.array([50, 110, 160, 210, 350]) * KMH
    assert np.allclose(ebi_margin(v) / KMH, [7.5, 7.5, 11.25, 15.0, 15.0])


def test_gap_below_le_and_collision_intervals_with_their_worst_values():
    def gap(t):  # 3000 m, dips to 1200 m around t = 30 s, then to -5 m at t = 70 s
        return 3000.0 - 1800.0 * max(0.0, 1 - abs(t - 30) / 10) - 3005.0 * max(0.0, 1 - abs(t - 70) / 5)

    log = synthetic(gap)
    vs = check_safety(log, BAND)
    below = [v for v in vs if v.verdict == "gap_below_le"]
    assert [v.where for v in below] == ["train 1-2", "train 1-2"]
    first = below[0]
    # gap < 1500 where 1800 (1 - |t-30|/10) > 1500: |t - 30| < 1.667 s
    assert first.start_s == pytest.approx(28.4) and first.end_s == pytest.approx(31.7)
    assert first.worst == pytest.approx(1200.0) and first.worst_at_s == pytest.approx(30.0)
    crash = [v for v in vs if v.verdict == "collision"]
    assert len(crash) == 1 and crash[0].worst == pytest.approx(-5.0) and crash[0].worst_at_s == pytest.approx(70.0)
    assert crash[0].start_s > below[1].start_s and crash[0].end_s < below[1].end_s
    assert not [v for v in vs if v.verdict in ("coupler_out_of_band", "overspeed")]


def test_coupler_band_and_overspeed():
    log = synthetic(lambda t: 3000.0, coupler_of_t=lambda t: 0.15 if 10 <= t < 12 else (-0.12 if 50 <= t < 51 else 0.0),
                    v_extra_of_t=lambda t: 5.0 if 20 <= t < 25 else (3.0 if 40 <= t < 45 else 0.0))
    vs = check_safety(log, BAND)
    band = [v for v in vs if v.verdict == "coupler_out_of_band"]
    assert [(v.where, round(v.start_s, 1), round(v.end_s, 1), round(v.worst, 2)) for v in band] == \
        [("train 1 coupler 1-2", 10.0, 12.0, 0.15), ("train 1 coupler 1-2", 50.0, 51.0, 0.12)]
    over = [v for v in vs if v.verdict == "overspeed"]
    # at 80 m/s (288 km/h) the margin is 15 km/h = 4.17 m/s: 5 m/s over is overspeed, 3 m/s is not
    assert [(v.where, round(v.start_s, 1), round(v.end_s, 1)) for v in over] == [("train 2 unit 2", 20.0, 25.0)]
    assert over[0].worst == pytest.approx(5.0 - 15 * KMH)
    line = [v for v in check_safety(log, BAND, line_limit_mps=82.0) if v.verdict == "overspeed"]
    assert {round(v.start_s, 1) for v in line} == {20.0, 40.0}


def test_causes_come_from_fault_events_then_errors_then_none():
    log = synthetic(lambda t: 3000.0 - 1800.0 * max(0.0, 1 - abs(t - 30) / 10), t_end=60.0)
    vs = check_safety(log, BAND)
    assert "no injected fault" in explain(vs, log.events, 2)[0].cause
    log.event(25.0, "ERROR", "train2/unit1/ecu", "lost contact with the train ahead: emergency brake")
    assert explain(check_safety(log, BAND), log.events, 2)[0].cause.startswith("after train2/unit1/ecu at t = 25.00 s")
    log.event(10.0, "WARN", "faults", "#3 radio_blackout on radio 1-2: injected at t = 10 s, for 20 s")
    log.event(30.0, "INFO", "faults", "#3 radio_blackout on radio 1-2: over after 20.000 s")
    log.event(5.0, "WARN", "faults", "#0 babbling_node on bus3: injected at t = 5 s")  # a train with no pair here
    cause = explain(check_safety(log, BAND), log.events, 2)[0].cause
    assert cause == "injected #3 radio_blackout on radio 1-2 (active)"


def test_metrics_carry_the_verdicts():
    log = synthetic(lambda t: 3000.0 - 1800.0 * max(0.0, 1 - abs(t - 30) / 10), t_end=60.0)
    m = compute_metrics(log, BAND)
    s = m["safety"]
    assert s["safe"] is False and s["gap_below_le"]["violated"] and s["gap_below_le"]["count"] == 1
    assert s["gap_below_le"]["first_s"] == pytest.approx(28.4)
    assert s["collision"]["violated"] is False and s["overspeed"]["count"] == 0
    assert s["gap_below_le"]["violations"][0]["cause"]
    assert m["unsafe"] is True  # the existing verdict agrees
    clean = safety_report(synthetic(lambda t: 3000.0, t_end=5.0), BAND)
    assert clean["safe"] is True and all(not clean[k]["violated"] for k in ("gap_below_le", "collision"))
