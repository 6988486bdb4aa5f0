"""Rerun inspection: a produced .rrd read back with rerun's own Python API (rerun.chunk.RrdReader, no viewer, no
network) has the expected entity paths, the track view's data, per-frame rows, the wall-clock timeline and the
default blueprint for its kind of run; `hil view` prints how to open it where no viewer can start."""
from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from hil.scenario.layout import TrainLayout
from hil.record import paths
from hil.record.rerun_writer import write_runlog
from hil.record.series import margin_colors
from hil.scenario import load_scenario
from hil.scenario.model import TrainsConfig
from hil.session import run_scenario
from hil.viewer import find_recordings, viewer_command, viewer_env, why_no_viewer
from tests.rrd_reader import entity_columns, read_blueprint, read_component, read_scalars, read_text_rows

CRUISE = Path(__file__).resolve().parents[1] / "examples" / "cruise.toml"


@pytest.fixture(scope="module")
def recorded(tmp_path_factory):
    """2 s of the example scenario (2 trains x 3 units, consensus law) with per-frame rows switched on."""
    sc = load_scenario(CRUISE, {"recording.frames": True})
    out = tmp_path_factory.mktemp("frames")
    result = run_scenario(sc, out, duration_s=2.0)
    return out / "run.rrd", result.log, sc


def test_entity_paths_of_signals_track_frames_and_events(recorded):
    rrd, log, _ = recorded
    cols = entity_columns(rrd)
    for i in (1, 2):
        for j in (1, 2, 3):
            for s in ("speed_kmh", "speed_error_kmh", "position_error_m", "traction_kn", "applied_kn"):
                assert "Scalars:scalars" in cols[f"/trains/{i}/units/{j}/{s}"]
        assert "Scalars:scalars" in cols[f"/trains/{i}/couplers/2/displacement_m"]
    assert "Scalars:scalars" in cols["/trains/2/gap_ahead_m"]
    assert {"Boxes2D:centers", "Boxes2D:half_sizes", "sim_time"} <= cols[paths.TRACK_UNITS]
    assert {"LineStrips2D:strips", "LineStrips2D:colors", "LineStrips2D:labels"} <= cols[paths.TRACK_GAPS]
    assert "Points2D:positions" in cols[paths.TRACK_SLOTS]
    assert "TextLog:text" in cols["/buses/bus1/frames/080_TractionCmd_U01"]
    assert "TextLog:text" in cols["/buses/bus2/frames/180_RadioAheadState"]  # forwarded by the radio to train 2
    assert "/buses/bus1/frames/180_RadioAheadState" not in cols  # nobody sends it on the first train's bus
    assert not any(c == "wall_time" for e in cols.values() for c in e)  # virtual time: sim_time only


def test_track_view_data_is_every_unit_along_the_line_and_the_gap_coloured_by_margin(recorded):
    rrd, log, sc = recorded
    t, centers = read_component(rrd, paths.TRACK_UNITS, "Boxes2D:centers")
    np.testing.assert_allclose(t, log.t, atol=1e-9)
    x = np.array([[c[0] for c in row] for row in centers])
    # rerun stores 2D positions as float32: box centre = front end - half the 80 m unit, rounded to float32
    np.testing.assert_array_equal(x, (log.x - 40.0).astype(np.float32))
    _, strips = read_component(rrd, paths.TRACK_GAPS, "LineStrips2D:strips")
    _, colors = read_component(rrd, paths.TRACK_GAPS, "LineStrips2D:colors")
    front_behind = np.array([row[0][0][0] for row in strips])
    rear_ahead = np.array([row[0][1][0] for row in strips])
    np.testing.assert_array_equal(front_behind, log.x[:, 3].astype(np.float32))  # train 2's head
    np.testing.assert_array_equal(rear_ahead, (log.x[:, 2] - 80.0).astype(np.float32))  # train 1's rear end
    _, labels = read_component(rrd, paths.TRACK_GAPS, "LineStrips2D:labels")
    assert [row[0] for row in labels] == [f"{g:.0f} m" for g in log.gaps[:, 0]]
    margin = (log.gaps[:, 0] - sc.trains.emergency_gap_m) / (sc.trains.spacing_m - sc.trains.emergency_gap_m)
    rgba = margin_colors(margin)
    packed = (rgba[:, 0].astype(np.int64) << 24) | (rgba[:, 1].astype(np.int64) << 16) | (rgba[:, 2].astype(np.int64) << 8) | 255
    assert [row[0] for row in colors] == packed.tolist()


def test_margin_colours_go_from_green_at_l_s_to_red_at_l_e():
    green, amber, red, below = margin_colors(np.array([1.2, 0.5, 0.0, -0.3]))
    assert green[1] > 150 and green[0] < 60  # at or above l_s
    assert amber[0] > 200 and amber[1] > 150  # half way
    assert tuple(red[:3]) == tuple(below[:3]) == (200, 0, 0)


def test_every_frame_is_a_text_row_with_id_decoded_signals_and_latency(recorded):
    rrd, log, _ = recorded
    rows = read_text_rows(rrd, "/buses/")
    total = sum(len(r) for r in rows.values())
    assert total == sum(b.frames_sent for b in log.buses)  # every frame once
    t, text, level = rows["/buses/bus2/frames/0C0_Sensor_U01"][0]
    assert text.startswith("0x0C0 Sensor_U01 Position=") and " m Speed=" in text and "latency" in text
    assert level == "DEBUG"
    pos = float(text.split("Position=")[1].split()[0])
    assert abs(pos - 7745.0) < 0.01  # train 2's head at t = 0, as encoded (1 mm resolution)
    sensor_t = log.buses[1].frames.array
    first = sensor_t[sensor_t[:, 1] == 0x0C0][0]
    assert t == pytest.approx(first[0]) and f"latency {first[2] * 1e3:.3f} ms" in text


def test_blueprint_for_this_kind_of_run(recorded):
    rrd, _, _ = recorded
    bp = read_blueprint(rrd)
    assert bp["application_id"] == "trainhil"
    views = {(cls, name, origin) for cls, name, origin in bp["views"]}
    assert ("2D", "Track: units, gaps (green at l_s, red at l_e), slots", "/track") in views
    assert ("TextLog", "Event log", "/events") in views and ("TextLog", "Frames on bus2", "/buses/bus2/frames") in views
    assert {"Overview", "Speeds (km/h)", "Speed errors (km/h)", "Couplers", "Gaps", "Traction (kN)", "CAN buses",
            "Frames"} <= bp["containers"]
    assert "Timing (real time)" not in bp["containers"]
    assert {"/trains/2/gap_ahead_m", "/limits/spacing_m", "/limits/emergency_gap_m", "/trains/2/units/3/speed_kmh",
            "/reference/speed_kmh", "/buses/bus1/frame_latency_ms", "/trains/2/couplers/2/displacement_m"} <= bp["queries"]
    assert bp["timelines"] == {"sim_time"}


def test_single_unit_single_train_blueprint_has_no_couplers_gaps_or_frames(tmp_path):
    cfg = TrainsConfig(count=1, units=1, unit_mass_kg=1e5, unit_length_m=200.0, head_positions_m=[0.0],
                       speeds_mps=[10.0], spacing_m=100.0, emergency_gap_m=30.0)
    from hil.record.rerun_writer import RerunWriter

    with RerunWriter(tmp_path / "one.rrd", TrainLayout.from_config(cfg), "one", (-0.1, 0.1), 100.0, 30.0):
        pass
    containers = read_blueprint(tmp_path / "one.rrd")["containers"]
    assert "Overview" in containers and not {"Couplers", "Gaps", "Frames", "Timing (real time)"} & containers


def test_real_time_recording_has_a_wall_clock_timeline_and_a_timing_tab(recorded, tmp_path):
    _, log, sc = recorded
    t0, pace = 1_700_000_000.25, 2.0
    timing = {"/timing/e2e_latency_ms": (np.array([0.5, 1.0]), np.array([3.0, 4.0]))}
    rrd = write_runlog(tmp_path / "rt.rrd", log, sc, wall_clock=(t0, pace), realtime=True, extra_series=timing)
    t_sim, v = read_component(rrd, "/trains/1/units/1/speed_kmh", "Scalars:scalars")
    t_wall, _ = read_component(rrd, "/trains/1/units/1/speed_kmh", "Scalars:scalars", timeline="wall_time")
    np.testing.assert_allclose(t_wall * 1e-9, t0 + t_sim / pace, atol=1e-6)  # wall = T0 + sim / pace
    assert read_scalars(rrd)["/timing/e2e_latency_ms"][1].tolist() == [3.0, 4.0]
    assert "Timing (real time)" in read_blueprint(rrd)["containers"]


def test_hil_view_prints_how_to_open_where_no_viewer_can_start(recorded, tmp_path):
    rrd, _, _ = recorded
    env = {k: v for k, v in __import__("os").environ.items() if k not in ("DISPLAY", "WAYLAND_DISPLAY")}
    proc = subprocess.run([sys.executable, "-m", "hil", "view", str(rrd.parent)], capture_output=True, text=True,
                          env=env, timeout=60)
    assert proc.returncode == 0, proc.stderr
    assert "not starting a viewer here: there is no display" in proc.stdout
    assert str(rrd) in proc.stdout and "--bind 127.0.0.1" in proc.stdout and "CI=1" in proc.stdout
    proc = subprocess.run([sys.executable, "-m", "hil", "view", str(tmp_path / "nothing")], capture_output=True,
                          text=True, timeout=60)
    assert proc.returncode == 2 and "no such run directory" in proc.stderr


def test_hil_view_finds_recordings_and_would_start_the_viewer_local_only(recorded, tmp_path):
    rrd, _, _ = recorded
    assert find_recordings(rrd.parent) == [rrd] and find_recordings(rrd) == [rrd]
    nested = tmp_path / "failed" / "test_a" / "cruise"
    nested.mkdir(parents=True)
    (nested / "run.rrd").write_bytes(rrd.read_bytes())
    assert find_recordings(tmp_path / "failed") == [nested / "run.rrd"]
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(FileNotFoundError, match="no .rrd"):
        find_recordings(empty)
    assert why_no_viewer({"DISPLAY": ":0"}, "linux", "/usr/bin/rerun") is None
    assert "no display" in why_no_viewer({}, "linux", "/usr/bin/rerun")
    assert "not installed" in why_no_viewer({"DISPLAY": ":0"}, "linux", None)
    assert viewer_command("/usr/bin/rerun", [rrd]) == ["/usr/bin/rerun", "--bind", "127.0.0.1", str(rrd)]
    env = viewer_env({"FORCE_RERUN_ANALYTICS": "1", "HOME": "/h"})
    assert env == {"HOME": "/h", "CI": "1"}  # rerun's analytics pipeline stays off


def test_frame_rows_flag_crc_errors_and_frames_not_in_the_dbc():
    from ecu_sim.codec import TrainDb
    from hil.record.frames import FrameRecorder

    db = TrainDb.load()
    rec = FrameRecorder([], db)
    cmd = db.traction_cmd(0)
    good = cmd.encode((0, 12350.0), 3)  # Force in steps of 10 N
    text, level = rec.format(cmd.frame_id, good, 250_000)
    assert (text, level) == ("0x080 TractionCmd_U01 Mode=0 Force=12350 N | alive 3 | latency 0.250 ms", "DEBUG")
    bad = bytes([good[0] ^ 0xFF]) + good[1:]
    text, level = rec.format(cmd.frame_id, bad, 250_000)
    assert text.endswith("| alive 3 | CRC ERROR | latency 0.250 ms") and level == "WARN"
    assert rec.format(0x7F0, b"\x01\x02", 0) == ("0x7F0 (not in the DBC) data 01 02 | latency 0.000 ms", "WARN")


def test_hil_view_skips_what_is_no_recording_and_says_a_cut_one(recorded, tmp_path, capsys):
    """Garbage, empty and truncated .rrd files used to be listed alike, exit 0."""
    from hil.cli import main

    rrd, _, _ = recorded
    runs = tmp_path / "runs"
    for name, data in (("good", rrd.read_bytes()), ("cut", rrd.read_bytes()[: rrd.stat().st_size // 2]),
                       ("garbage", b"hello world" * 40), ("empty", b"")):
        (runs / name).mkdir(parents=True)
        (runs / name / "run.rrd").write_bytes(data)
    assert main(["view", "--print", str(runs)]) == 0
    out, err = capsys.readouterr()
    assert str(runs / "good" / "run.rrd") in out and str(runs / "cut" / "run.rrd") in out
    assert "garbage" not in out and "empty/run.rrd" not in out
    assert f"skipping {runs / 'garbage' / 'run.rrd'}: not a rerun recording (no RRF2 header)" in err
    assert f"skipping {runs / 'empty' / 'run.rrd'}: empty" in err
    assert f"{runs / 'cut' / 'run.rrd'} is cut short: " in err
    assert main(["view", "--print", str(runs / "garbage")]) == 2
    assert "no readable recording among 1 .rrd file" in capsys.readouterr().err


def test_hil_view_says_when_the_viewer_died_at_once(recorded, tmp_path, monkeypatch, capsys):
    from hil import viewer
    from hil.cli import main

    rrd, _, _ = recorded
    fake = tmp_path / "rerun"
    fake.write_text("#!/bin/sh\necho 'no GPU adapter found' >&2\nexit 1\n")
    fake.chmod(0o755)
    monkeypatch.setattr(viewer, "rerun_executable", lambda: str(fake))
    monkeypatch.setenv("DISPLAY", ":0")
    assert main(["view", str(rrd)]) == 1
    err = capsys.readouterr().err
    assert "hil view: the rerun viewer exited at once (code 1): no GPU adapter found" in err


def test_load_run_reads_a_cut_recording_up_to_its_last_complete_message(recorded, tmp_path):
    """It used to raise at once: rerun's reader refuses a file whose last message is cut."""
    from hil.record import load_run

    rrd, _, _ = recorded
    whole = load_run(rrd)
    cut = tmp_path / "run.rrd"
    cut.write_bytes(rrd.read_bytes()[: rrd.stat().st_size * 2 // 3])
    part = load_run(cut)
    assert part.cut_short and not whole.cut_short and 0 < len(part.series) <= len(whole.series)
    entity = next(iter(part.series))
    t = part[entity].t
    assert np.array_equal(t, whole[entity].t[: len(t)])
    (tmp_path / "junk.rrd").write_bytes(b"\x00" * 100)
    with pytest.raises(ValueError, match="junk.rrd: not a rerun recording"):
        load_run(tmp_path / "junk.rrd")
