"""The rerun writer: incremental writes, then read the .rrd back with rerun.chunk.RrdReader (no CLI, no network)."""
from __future__ import annotations

import subprocess
import sys
import textwrap
from collections import defaultdict
from pathlib import Path

import numpy as np
import pytest
import rerun as rr
from rerun.chunk import RrdReader

from tests.rrd_reader import read_scalars

from hil.scenario.layout import TrainLayout
from hil.record.blueprint import default_blueprint
from hil.record.rerun_writer import RerunWriter, event_path
from hil.record.runlog import BusLog, RunLog
from hil.scenario.model import TrainsConfig

K = 20  # samples
DT = 0.1


def layout() -> TrainLayout:
    """2 trains x 2 units of 25 m, l_s = 100 m, l_e = 30 m."""
    cfg = TrainsConfig(count=2, units=2, unit_mass_kg=50_000.0, unit_length_m=25.0, head_positions_m=[0.0, -200.0],
                       speeds_mps=[10.0, 10.0], spacing_m=100.0, emergency_gap_m=30.0)
    return TrainLayout.from_config(cfg)


def make_log() -> RunLog:
    """Signals with distinct values per unit and sample, two buses, three events."""
    L = layout()
    log = RunLog(L)
    rng = np.random.default_rng(3)
    x0 = L.initial_positions([0.0, -200.0])
    for k in range(K):
        t = k * DT
        v = 10.0 + 0.01 * k + np.arange(L.n_units)
        x = x0 + 10.0 * t + rng.normal(0.0, 0.05, L.n_units)
        f = 1000.0 * (k + 10.0 * np.arange(L.n_units))
        log.add_sample(t, 10.0 * t, 10.0, x, v, np.zeros(L.n_units), f, 0.5 * f)
    for b in range(2):
        bus = BusLog(f"bus{b + 1}", 500_000)
        for i in range(30):
            bus.frames.append(np.array([0.05 * i, 0x100 + i, 1e-4 * (i + 1) + b, 0.0]))
        for i in range(10):
            bus.load.append(np.array([0.2 * (i + 1), 0.1 * b + 0.01 * i]))
        log.buses.append(bus)
    log.event(0.3, "WARN", "train1/unit2/ecu", "inter-train frame timeout")
    log.event(1.2, "ERROR", "plant", "emergency brake")
    log.event(1.5, "INFO", "radio1-2", "link restored")
    return log


def write_in_two_increments(path: Path, log: RunLog) -> None:
    w = RerunWriter(path, log.layout, "two-trains", (-0.1, 0.1), 100.0, 30.0)
    offsets = [(0, 0)] * len(log.buses)
    w.write_signals(log, 0, 12)
    offsets = [w.write_bus(b, *o) for b, o in zip(log.buses, offsets)]
    w.write_events(log.events[:1])
    w.flush()
    w.write_signals(log, 12, K)
    offsets = [w.write_bus(b, *o) for b, o in zip(log.buses, offsets)]
    assert offsets == [(10, 30), (10, 30)]
    w.write_events(log.events[1:])
    w.close()
    w.close()  # idempotent


@pytest.fixture(scope="module")
def written(tmp_path_factory) -> tuple[Path, RunLog]:
    path = tmp_path_factory.mktemp("rrd") / "sub" / "run.rrd"
    log = make_log()
    write_in_two_increments(path, log)
    return path, log


def test_entity_tree_and_every_sample_once(written):
    path, log = written
    data = read_scalars(path)
    expected = {"/reference/speed_kmh", "/reference/position_km", "/trains/2/gap_ahead_m",
                "/trains/1/couplers/1/displacement_m", "/trains/2/couplers/1/displacement_m",
                "/buses/bus1/load", "/buses/bus2/frame_latency_ms",
                "/limits/coupler_min_m", "/limits/coupler_max_m", "/limits/spacing_m", "/limits/emergency_gap_m"}
    for i in (1, 2):
        for j in (1, 2):
            expected |= {f"/trains/{i}/units/{j}/{s}" for s in
                         ("speed_kmh", "speed_error_kmh", "position_error_m", "traction_kn", "applied_kn")}
    assert expected <= set(data)
    assert "/trains/1/gap_ahead_m" not in data  # the lead train has nobody ahead
    t, _ = data["/trains/1/units/1/speed_kmh"]
    np.testing.assert_allclose(t, log.t, atol=1e-9)  # both increments, no duplicates, on sim_time


def test_values_read_back_equal_what_was_written(written):
    path, log = written
    data = read_scalars(path)
    assert data["/trains/2/units/2/speed_kmh"][1][-1] == pytest.approx(log.v[-1, 3] * 3.6)
    np.testing.assert_allclose(data["/trains/2/units/1/speed_error_kmh"][1], log.speed_error[:, 2] * 3.6)
    np.testing.assert_allclose(data["/trains/1/units/2/position_error_m"][1], log.position_error[:, 1], atol=1e-9)
    np.testing.assert_allclose(data["/trains/2/units/1/traction_kn"][1], log.force_cmd[:, 2] / 1000)
    np.testing.assert_allclose(data["/trains/2/units/1/applied_kn"][1], log.force_applied[:, 2] / 1000)
    # cross-check against RunLog's own coupler/gap views (an independent implementation)
    np.testing.assert_allclose(data["/trains/2/couplers/1/displacement_m"][1], log.couplers[:, 1], atol=1e-9)
    np.testing.assert_allclose(data["/trains/2/gap_ahead_m"][1], log.gaps[:, 0], atol=1e-9)
    np.testing.assert_allclose(data["/reference/position_km"][1], log.x_ref / 1000)


def test_buses_and_limits(written):
    path, log = written
    data = read_scalars(path)
    t, lat = data["/buses/bus2/frame_latency_ms"]
    np.testing.assert_allclose(t, log.buses[1].frames.array[:, 0], atol=1e-9)
    np.testing.assert_allclose(lat, log.buses[1].frames.array[:, 2] * 1000)
    np.testing.assert_allclose(data["/buses/bus1/load"][1], log.buses[0].load.array[:, 1])
    for entity, value in (("/limits/coupler_min_m", -0.1), ("/limits/coupler_max_m", 0.1),
                          ("/limits/spacing_m", 100.0), ("/limits/emergency_gap_m", 30.0)):
        t, v = data[entity]
        assert np.all(v == value)
        assert t.min() == pytest.approx(0.0) and t.max() == pytest.approx(log.t[-1])


def test_events_are_text_logs_with_levels(written):
    path, _ = written
    rows = {}
    for ch in RrdReader(path).stream():
        rb = ch.to_record_batch()
        if "TextLog:text" in rb.schema.names:
            t = rb.column("sim_time").cast("int64").to_numpy() * 1e-9
            for ti, text, level in zip(t, rb.column("TextLog:text").to_pylist(), rb.column("TextLog:level").to_pylist()):
                rows[ch.entity_path] = (round(ti, 9), text[0], level[0])
    assert rows == {
        "/events/train1/unit2/ecu": (0.3, "inter-train frame timeout", "WARN"),
        "/events/plant": (1.2, "emergency brake", "ERROR"),
        "/events/radio1-2": (1.5, "link restored", "INFO"),
    }


def test_recording_identity_and_blueprint_in_same_file(written):
    path, _ = written
    reader = RrdReader(path)
    [rec] = reader.recordings()
    [blue] = reader.blueprints()  # 0.41 stores the blueprint as a second store in the same .rrd
    assert rec.application_id == blue.application_id == "trainhil"
    reader.store()  # the footer was written on close: random access works
    names = []
    for ch in reader.stream():
        rb = ch.to_record_batch()
        if "RecordingInfo:name" in rb.schema.names:
            names += [n[0] for n in rb.column("RecordingInfo:name").to_pylist()]
    assert names == ["two-trains"]
    views, queries = set(), []
    for ch in reader.stream(store=blue):
        rb = ch.to_record_batch()
        if "ViewBlueprint:display_name" in rb.schema.names:
            views |= {n[0] for n in rb.column("ViewBlueprint:display_name").to_pylist()}
        if "ViewContents:query" in rb.schema.names:
            queries += [q for row in rb.column("ViewContents:query").to_pylist() for q in row]
    assert {"Speeds (km/h): train 1", "Couplers: train 2", "Gaps to the train ahead (m)", "Bus load",
            "Frame latency (ms)", "Events"} <= views
    assert {"/trains/2/units/2/speed_kmh", "/reference/speed_kmh", "/limits/emergency_gap_m",
            "/limits/coupler_max_m", "/buses/bus2/load"} <= set(queries)


def test_writer_leaves_global_recording_alone(tmp_path):
    before = rr.get_global_data_recording()
    with RerunWriter(tmp_path / "a.rrd", layout(), "a", (-0.1, 0.1), 100.0, 30.0):
        assert rr.get_global_data_recording() is before


def test_bad_calls(tmp_path):
    log = make_log()
    w = RerunWriter(tmp_path / "b.rrd", log.layout, "b", (-0.1, 0.1), 100.0, 30.0)
    with pytest.raises(ValueError, match=r"rows \[5, 99\)"):
        w.write_signals(log, 5, 99)
    w.write_signals(log, 3, 3)  # empty range: nothing to do
    w.close()
    with pytest.raises(RuntimeError, match="closed"):
        w.write_signals(log, 0, 1)


def test_event_path_escapes_parts():
    assert event_path("train1/unit2/ecu") == "/events/train1/unit2/ecu"
    assert event_path("odd name") == "/events/odd\\ name"
    assert event_path("") == "/events/unknown"


def test_flushed_data_survives_a_hard_kill(tmp_path):
    """What was flushed stays readable (streaming read, no footer) if the process dies before close()."""
    path = tmp_path / "killed.rrd"
    script = textwrap.dedent(f"""
        import os, sys
        sys.path.insert(0, {str(Path(__file__).resolve().parents[1])!r})
        from pathlib import Path
        from tests.test_rerun_writer import make_log
        from hil.record.rerun_writer import RerunWriter
        log = make_log()
        w = RerunWriter(Path({str(path)!r}), log.layout, "k", (-0.1, 0.1), 100.0, 30.0)
        w.write_signals(log, 0, 7)
        w.flush()
        os._exit(1)
    """)
    subprocess.run([sys.executable, "-c", script], check=False, timeout=60)
    with pytest.warns(Warning, match="no footer"):
        t, v = read_scalars(path)["/trains/1/units/1/speed_kmh"]
    np.testing.assert_allclose(t, np.arange(7) * DT, atol=1e-9)
    assert v[-1] == pytest.approx((10.0 + 0.06) * 3.6)


def test_blueprint_for_single_unit_trains_has_no_couplers():
    cfg = TrainsConfig(count=1, units=1, unit_mass_kg=1e5, unit_length_m=200.0, head_positions_m=[0.0],
                       speeds_mps=[0.0], spacing_m=100.0, emergency_gap_m=30.0)
    default_blueprint(TrainLayout.from_config(cfg))  # builds without coupler or gap entities
