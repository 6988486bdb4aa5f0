"""Metrics on synthetic run logs with hand-computed answers."""
from __future__ import annotations

import json
import math

import numpy as np
import pytest

from hil import cli
from hil.scenario.layout import TrainLayout
from hil.record.metrics import compute_metrics
from hil.record.runlog import BusLog, RunLog
from hil.scenario.model import TrainsConfig

BAND = (-0.1, 0.1)
SETTLE = 0.5 / 3.6  # default settle band, 0.1389 m/s


def layout() -> TrainLayout:
    """2 trains x 2 units of 25 m / 50 t, l_s = 100 m, l_e = 30 m."""
    cfg = TrainsConfig(count=2, units=2, unit_mass_kg=50_000.0, unit_length_m=25.0, head_positions_m=[0.0, -200.0],
                       speeds_mps=[10.0, 10.0], spacing_m=100.0, emergency_gap_m=30.0)
    return TrainLayout.from_config(cfg)


def make_log(t, v_r, err=None, pe=None, a=None, force=None) -> RunLog:
    """A RunLog whose units have speed error `err` and position error `pe` (both (k, 4)) around the reference."""
    L = layout()
    t = np.asarray(t, float)
    k, n = len(t), L.n_units
    v_r = np.broadcast_to(np.asarray(v_r, float), (k,))
    x_r = np.cumsum(np.r_[0.0, np.diff(t)] * v_r)
    z = np.zeros((k, n))
    err = z if err is None else np.asarray(err, float)
    pe = z if pe is None else np.asarray(pe, float)
    a = z if a is None else np.asarray(a, float)
    force = z if force is None else np.asarray(force, float)
    log = RunLog(L)
    for i in range(k):
        x = x_r[i] - L.offset_m + pe[i]
        log.add_sample(t[i], x_r[i], v_r[i], x, v_r[i] + err[i], a[i], force[i], force[i])
    return log


def test_step_response_settling_time_hand_computed():
    t = np.arange(0.0, 20.01, 0.5)
    err = np.zeros((len(t), 4))
    err[t < 3.0, 0] = 1.0  # unit 0 overshoots by 1 m/s until t = 3
    err[t >= 3.0, 0] = 0.05  # then stays inside the band
    err[t == 6.0, 3] = -0.3  # a late excursion of the last unit
    m = compute_metrics(make_log(t, 20.0, err=err), BAND)
    assert m["settling_time_s"] == 6.5
    assert m["settled"] is True
    assert m["settling_time_per_segment_s"] == [6.5]
    assert m["speed_overshoot_max_mps"] == pytest.approx(1.0)
    assert m["speed_error_max_after_settling_mps"] == pytest.approx(0.05)
    assert m["speed_error_max_abs_mps"] == pytest.approx(1.0)


def test_exponential_settling_matches_analytic_crossing():
    t = np.arange(0.0, 30.0, 0.5)
    e = -5.0 * np.exp(-t / 2.0)  # approaching from below: no overshoot
    m = compute_metrics(make_log(t, 30.0, err=np.repeat(e[:, None], 4, axis=1)), BAND)
    crossing = 2.0 * math.log(5.0 / SETTLE)  # 7.167 s
    assert m["settling_time_s"] == math.ceil(crossing / 0.5) * 0.5 == 7.5
    assert m["speed_overshoot_max_mps"] == 0.0
    assert m["speed_error_max_after_settling_mps"] == pytest.approx(5.0 * math.exp(-7.5 / 2.0))


def test_never_settling_is_none():
    t = np.arange(0.0, 10.0, 1.0)
    err = np.zeros((len(t), 4))
    err[-1, 2] = 0.2  # out of band at the very last sample
    m = compute_metrics(make_log(t, 20.0, err=err), BAND)
    assert m["settling_time_s"] is None
    assert m["settled"] is False
    assert m["speed_error_max_after_settling_mps"] is None
    assert m["settling_time_per_segment_s"] == [None]


def test_segments_split_at_reference_changes():
    t = np.arange(0.0, 20.0, 1.0)
    v_r = np.where(t < 10.0, 20.0, 25.0)
    err = np.zeros((len(t), 4))
    err[t < 3.0] = 0.5  # segment 0 settles at 3 s
    err[(t >= 10.0) & (t < 14.0), 1] = -2.0  # segment 1 (from the change at 10 s) settles at 14 s, i.e. after 4 s
    log = make_log(t, v_r, err=err)
    log.reference_change_times = [0.0, 10.0]  # a change at t = 0 is the initial reference, not a segment
    m = compute_metrics(log, BAND)
    assert m["settling_time_per_segment_s"] == [3.0, 4.0]
    assert m["settling_time_s"] == 3.0
    assert m["speed_error_max_after_settling_mps"] == 0.0  # segment 1's error does not count
    assert m["speed_overshoot_max_mps"] == 0.5
    assert m["speed_error_max_abs_mps"] == 2.0


def test_coupler_and_gap_extremes_with_zero_order_hold():
    t = [0.0, 1.0, 3.0, 4.0, 10.0]
    pe = np.array([
        [0.0, 0.00, 0.0, 0.0],
        [0.25, 0.20, 0.0, 0.2],
        [0.15, 0.0, 50.0, 50.0],
        [0.12, 0.0, 80.0, 80.0],
        [0.0, 0.0, 10.0, 10.0],
    ])
    # couplers e = pe_front - pe_rear: train 1 [0, .05, .15, .12, 0]; train 2 [0, -.2, 0, 0, 0]
    # gap = l_s + pe[1] - pe[2] = [100, 100.2, 50, 20, 90]
    m = compute_metrics(make_log(t, 10.0, pe=pe), BAND)
    assert m["coupler_max_m"] == pytest.approx(0.15)
    assert m["coupler_min_m"] == pytest.approx(-0.2)
    assert m["coupler_max_abs_m"] == pytest.approx(0.2)
    assert m["coupler_out_of_band_s"] == pytest.approx(2.0 + 1.0 + 6.0)  # samples 1, 2, 3 hold 2, 1, 6 s
    assert m["gap_min_m"] == pytest.approx([20.0])
    assert m["gap_final_m"] == pytest.approx([90.0])
    assert m["gap_min_overall_m"] == pytest.approx(20.0)
    assert m["gap_margin_to_emergency_m"] == pytest.approx(-10.0)
    assert m["gap_below_emergency_s"] == pytest.approx(6.0)
    assert m["position_error_final_m"] == pytest.approx([0.0, 0.0, 10.0, 10.0])


def test_control_effort_and_jerk():
    t = np.linspace(0.0, 10.0, 101)
    force = np.zeros((len(t), 4))
    force[:, 1] = -50_000.0  # 1 m/s^2 braking on a 50 t unit for 10 s -> 10 m/s
    a = np.zeros((len(t), 4))
    a[:, 2] = 0.5 * t  # constant jerk 0.5 m/s^3 on one unit of four
    m = compute_metrics(make_log(t, 10.0, a=a, force=force), BAND)
    assert m["control_effort"] == pytest.approx(10.0 / 4)
    assert m["jerk_rms_mps3"] == pytest.approx(math.sqrt(0.25 / 4))


def _bus(name: str, lat: np.ndarray, loads: list[float]) -> BusLog:
    bus = BusLog(name, 500_000)
    for i, v in enumerate(lat):
        bus.frames.append(np.array([0.01 * i, 0x100, v, v / 2]))
    for i, v in enumerate(loads):
        bus.load.append(np.array([0.1 * (i + 1), v]))
    bus.frames_sent, bus.frames_dropped = len(lat) + 2, 2
    bus.dropped_by_node = {"Plant": 2}
    return bus


def test_bus_statistics_match_numpy():
    rng = np.random.default_rng(7)
    lat1, lat2 = rng.gamma(2.0, 1e-4, 500), rng.gamma(3.0, 2e-4, 300)
    log = make_log([0.0, 1.0], 10.0)
    log.buses = [_bus("bus1", lat1, [0.2, 0.4]), _bus("bus2", lat2, [0.9, 0.1, 0.5])]
    log.frames_lost = 3
    m = compute_metrics(log, BAND)
    both = np.concatenate([lat1, lat2])
    assert m["frame_latency_p50_s"] == pytest.approx(np.percentile(both, 50))
    assert m["frame_latency_p99_s"] == pytest.approx(np.percentile(both, 99))
    assert m["frame_latency_max_s"] == pytest.approx(both.max())
    assert m["frames_sent"] == 502 + 302
    assert m["frames_dropped"] == 4
    assert m["frames_lost"] == 3
    assert m["bus_load_max"] == pytest.approx(0.9)
    assert m["bus_load_mean"] == pytest.approx(2.1 / 5)
    b2 = m["per_bus"]["bus2"]
    assert b2["latency_p99_s"] == pytest.approx(np.percentile(lat2, 99))
    assert b2["latency_max_s"] == pytest.approx(lat2.max())
    assert (b2["load_max"], b2["load_mean"], b2["frames_sent"], b2["frames_dropped"]) == pytest.approx((0.9, 0.5, 302, 2))
    assert b2["frames_dropped_by_node"] == {"Plant": 2}
    # the run's summary names them
    assert cli._drop_lines(m["per_bus"]) == [f"{'frames dropped, by node':38s} bus1/Plant 2, bus2/Plant 2"]
    assert cli._drop_lines({"bus1": {"frames_dropped_by_node": {}}}) == [] and cli._drop_lines(None) == []


def test_no_frames_gives_none():
    log = make_log([0.0, 1.0], 10.0)
    log.buses = [BusLog("bus1", 500_000)]
    m = compute_metrics(log, BAND)
    assert m["frame_latency_p50_s"] is None and m["frame_latency_p99_s"] is None and m["frame_latency_max_s"] is None
    assert m["bus_load_max"] is None and m["frames_sent"] == 0
    assert m["per_bus"]["bus1"]["latency_p99_s"] is None


def test_counters_events_and_realtime_factor_are_copied():
    log = make_log([0.0, 1.0], 10.0)
    log.event(0.5, "WARN", "train1/unit2/ecu", "timeout")
    log.event(0.6, "WARN", "bus1", "overflow")
    log.event(0.7, "ERROR", "plant", "emergency brake")
    log.codec_saturations = {"State.Speed": 4}
    log.radio_stats = {"radio1-2": {"sent": 10, "lost": 1}}
    log.e2e = {"train1/unit1": {"ok": 100, "crc": 2}}
    log.sim_time_s, log.wall_time_s = 60.0, 20.0
    m = compute_metrics(log, BAND)
    log.codec_saturations["State.Speed"] = 99
    log.radio_stats["radio1-2"]["lost"] = 99
    assert m["events_by_level"] == {"INFO": 0, "WARN": 2, "ERROR": 1}
    assert m["codec_saturations"] == {"State.Speed": 4}
    assert m["radio"] == {"radio1-2": {"sent": 10, "lost": 1}}
    assert m["e2e"] == {"train1/unit1": {"ok": 100, "crc": 2}}
    assert m["interrupted"] is False
    assert m["realtime_factor"] == pytest.approx(3.0)


def test_json_round_trip_with_nonfinite_and_empty_logs():
    t = np.arange(0.0, 5.0, 1.0)
    err = np.zeros((len(t), 4))
    err[2, 1] = np.nan  # a plant that went non-finite
    for log in (make_log(t, 10.0, err=err), RunLog(layout())):
        m = compute_metrics(log, BAND)
        text = json.dumps(m, allow_nan=False)
        assert json.loads(text) == m
    empty = compute_metrics(RunLog(layout()), BAND)
    assert empty["settling_time_s"] is None and empty["coupler_max_m"] is None
    assert empty["gap_min_m"] == [None] and empty["realtime_factor"] is None and empty["control_effort"] is None


def test_bad_arguments_name_the_field():
    log = make_log([0.0, 1.0], 10.0)
    with pytest.raises(ValueError, match="coupler_band"):
        compute_metrics(log, (0.1, -0.1))
    with pytest.raises(ValueError, match="coupler_band"):
        compute_metrics(log, (0.1,))
    with pytest.raises(ValueError, match="settle_band_mps"):
        compute_metrics(log, BAND, settle_band_mps=0.0)


# --------------------------------------------------------------------------- safety verdict, string stability, deadlines


def test_safety_verdicts_flag_band_gap_and_collision_at_any_sample():
    t = [0.0, 1.0, 2.0]
    calm = compute_metrics(make_log(t, 10.0), BAND)
    assert (calm["unsafe"], calm["collision"]) == (False, False)
    pe = np.zeros((3, 4))
    pe[2, 0] = 0.11  # coupler of train 1 stretched 0.11 m at the last sample only (it holds 0 s)
    m = compute_metrics(make_log(t, 10.0, pe=pe), BAND)
    assert m["coupler_out_of_band_s"] == 0.0 and (m["unsafe"], m["collision"]) == (True, False)
    pe = np.zeros((3, 4))
    pe[1, 2:] = 75.0  # gap = 100 - 75 = 25 m < l_e = 30 m, still positive
    m = compute_metrics(make_log(t, 10.0, pe=pe), BAND)
    assert (m["unsafe"], m["collision"]) == (True, False)
    pe[1, 2:] = 100.5  # gap = -0.5 m: the trains overlap
    m = compute_metrics(make_log(t, 10.0, pe=pe), BAND)
    assert (m["unsafe"], m["collision"]) == (True, True)
    empty = compute_metrics(RunLog(layout()), BAND)
    assert (empty["unsafe"], empty["collision"], empty["string_stability_ratio"]) == (None, None, None)


def three_single_unit_trains(gap_errors: np.ndarray) -> RunLog:
    """3 trains x 1 unit of 25 m, l_s = 100 m; gap_errors (k, 2) = gap - l_s of each pair."""
    cfg = TrainsConfig(count=3, units=1, unit_mass_kg=50_000.0, unit_length_m=25.0, head_positions_m=[0.0, -125.0, -250.0],
                       speeds_mps=[10.0] * 3, spacing_m=100.0, emergency_gap_m=30.0)
    log = RunLog(TrainLayout.from_config(cfg))
    z = np.zeros(3)
    for i, (d1, d2) in enumerate(gap_errors):
        x = np.array([0.0, -125.0 - d1, -250.0 - d1 - d2])
        log.add_sample(float(i), 0.0, 10.0, x, z + 10.0, z, z, z)
    return log


def test_string_stability_ratio_is_last_pair_peak_over_first_pair_peak():
    log = three_single_unit_trains(np.array([[0.0, 0.0], [-4.0, 2.0], [3.0, -6.0], [1.0, 5.0]]))
    m = compute_metrics(log, BAND)
    assert m["gap_min_m"] == pytest.approx([96.0, 94.0])
    assert m["string_stability_ratio"] == pytest.approx(6.0 / 4.0)
    flat_first = three_single_unit_trains(np.array([[0.0, 0.0], [0.0, 2.0]]))
    assert compute_metrics(flat_first, BAND)["string_stability_ratio"] is None  # 2 / 0: undefined
    assert compute_metrics(make_log([0.0, 1.0], 10.0), BAND)["string_stability_ratio"] is None  # one pair only


def _frames_bus(name: str, rows: list[tuple[float, int, float]]) -> BusLog:
    """A bus whose frames were enqueued at `release` with `latency`, appended in order of end of transmission."""
    bus = BusLog(name, 500_000)
    for release, fid, lat in sorted(rows, key=lambda r: r[0] + r[2]):
        bus.frames.append(np.array([release + lat, fid, lat, 0.0]))
    return bus


def test_deadline_misses_and_max_latency_per_id():
    rows = [(0.00, 0x100, 0.001), (0.01, 0x100, 0.012), (0.02, 0x100, 0.002), (0.03, 0x100, 0.0105),  # period 10 ms
            (0.000, 0x0C0, 0.001), (0.005, 0x0C0, 0.006), (0.010, 0x0C0, 0.0049),  # period 5 ms
            (0.004, 0x7FF, 1.0)]  # a single frame: no period, so never a miss, but its latency counts in the max
    # a radio-forwarded ID with jitter and two lost frames: intervals 9, 11, 10, 30 ms -> median period 10.5 ms
    radio = [(0.0, 0x180, 0.001), (0.009, 0x180, 0.0104), (0.020, 0x180, 0.0106), (0.030, 0x180, 0.001), (0.060, 0x180, 0.002)]
    ext = [(0.0, 0x18FF0001, 0.0005), (0.1, 0x18FF0001, 0.0007)]
    log = make_log([0.0, 1.0], 10.0)
    log.buses = [_frames_bus("bus1", rows), _frames_bus("bus2", radio + ext)]
    m = compute_metrics(log, BAND)
    b1, b2 = m["per_bus"]["bus1"], m["per_bus"]["bus2"]
    assert b1["latency_max_by_id"] == pytest.approx({"0x0C0": 0.006, "0x100": 0.012, "0x7FF": 1.0})
    assert b1["deadline_misses"] == 3  # 12 > 10 ms, 10.5 > 10 ms, 6 > 5 ms
    assert b1["latency_to_period_max"] == pytest.approx(1.2)
    assert b2["latency_max_by_id"] == pytest.approx({"0x180": 0.0106, "0x18FF0001": 0.0007})
    assert b2["deadline_misses"] == 1  # only 10.6 ms exceeds the median period of 10.5 ms
    assert b2["latency_to_period_max"] == pytest.approx(0.0106 / 0.0105)
    assert m["deadline_misses"] == 4 and m["latency_to_period_max"] == pytest.approx(1.2)
    assert m["frame_latency_max_s"] == pytest.approx(1.0)  # the existing keys are unchanged


def test_no_frames_no_deadline_misses():
    log = make_log([0.0, 1.0], 10.0)
    log.buses = [BusLog("bus1", 500_000)]
    m = compute_metrics(log, BAND)
    b = m["per_bus"]["bus1"]
    assert (b["latency_max_by_id"], b["deadline_misses"], b["latency_to_period_max"]) == ({}, 0, None)
    assert (m["deadline_misses"], m["latency_to_period_max"]) == (0, None)
    assert json.loads(json.dumps(m, allow_nan=False)) == m


def test_samples_skipped_or_repeated_at_the_readers_are_reported_apart_from_lost_frames():
    """E2E LOST and REPEATED counted by the ECUs' mailboxes are reader-side sampling, not bus loss."""
    log = make_log([0.0, 1.0], 80.0)
    log.e2e = {"train1/unit1/ecu": {"OK": 90, "OK_SOME_LOST": 3, "LOST": 4, "REPEATED": 2},
               "train1/unit2/ecu": {"OK": 99, "LOST": 1}}
    m = compute_metrics(log, BAND)
    assert (m["reader_samples_skipped"], m["reader_samples_repeated"], m["frames_lost"]) == (5, 2, 0)
    assert m["e2e"]["train1/unit1/ecu"]["LOST"] == 4  # the per-ECU verdicts stay as they were
