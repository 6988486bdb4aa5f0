"""CAN timing analysis of a train bus: the frame set, hand-checked C/WCRT/utilisation, measured beside bound, CLI."""
from __future__ import annotations

import argparse
import json
import re
import subprocess
import sys

import pytest

from ecu_sim.codec import TrainDb
from hil.can.analysis import (
    CanAnalysisError,
    TrainBusSetup,
    analyse,
    analyse_train_bus,
    format_table,
    forwarded_jitter,
    train_bus_messages,
    utilisation,
)
from hil.commands.can_analysis import add_can_analysis_parser
from hil.scenario import load_scenario

US = 1e-6
BUS1_IDS = ({0x080 + u for u in range(4)} | {0x0A0, 0x0A1} | {0x0C0 + u for u in range(4)}
            | {0x100 + u for u in range(4)} | {0x120 + u for u in range(4)} | {0x188, 0x189})


@pytest.fixture(scope="module")
def db() -> TrainDb:
    return TrainDb.load()


@pytest.fixture(scope="module")
def seed000():
    return load_scenario("seed000")


def by_name(timings):
    return {t.name: t for t in timings}


# --------------------------------------------------------------------------- the frame set


def test_frame_set_is_what_the_rig_puts_on_bus1(db, seed000):
    """The analysed set is the rig's wiring: the ids bus 1 carries in a short run, each at its cycle."""
    from hil.runtime.virtual import VirtualRig

    log = VirtualRig(seed000).run(1.0)
    frames = log.buses[0].frames.array
    mine = train_bus_messages(db, 4, 0.01, 0.01, 0.01, radio_ahead=False, radio_behind=True, radio_jitter_s=0.003)
    assert {m.can_id for m in mine} == set(frames[:, 1].astype(int)) == BUS1_IDS
    for m in mine:  # 100 frames of each id per simulated second
        assert abs((frames[:, 1] == m.can_id).sum() - 1.0 / m.period_s) <= 1, m.name


def test_radio_frames_follow_the_trains_position_and_forward_aux(db, seed000):
    ids = [{m.can_id for m in TrainBusSetup.from_scenario(seed000, k).messages(db, 0.0)} for k in range(3)]
    assert ids[0] == BUS1_IDS  # no train ahead of train 1
    assert ids[1] == BUS1_IDS | {0x180, 0x181}  # middle: both ways
    assert ids[2] == BUS1_IDS - {0x188, 0x189} | {0x180, 0x181}  # last: none behind
    no_aux = train_bus_messages(db, 2, forward_aux=False, radio_jitter_s=(0.001, 0.002))
    radio = {m.name: m.jitter_s for m in no_aux if m.can_id >= 0x180}
    assert radio == {"RadioAheadState": 0.001, "RadioBehindState": 0.002}
    # periods default to the DBC's GenMsgCycleTime (10 ms), and follow the arguments otherwise
    assert {m.period_s for m in no_aux} == {0.01}
    fast = {m.name: m.period_s for m in train_bus_messages(db, 1, cycle_s=0.005, sensor_period_s=0.02, reference_period_s=0.05)}
    assert fast["TractionCmd_U01"] == fast["AgentAux_U01"] == fast["RadioAheadState"] == 0.005
    assert fast["Sensor_U01"] == 0.02 and fast["Reference"] == fast["ReferenceAux"] == 0.05


def test_bad_unit_count_is_named(db):
    with pytest.raises(CanAnalysisError, match=r"units=17 .*1\.\.16"):
        train_bus_messages(db, 17)
    with pytest.raises(CanAnalysisError, match="bitrate"):
        TrainBusSetup(units=4, bitrate=300_000)


# --------------------------------------------------------------------------- hand-checked numbers


def test_seed000_bus1_lengths_and_utilisation(db, seed000):
    t = by_name(analyse_train_bus(db, TrainBusSetup.from_scenario(seed000, 0)))
    # Davis eq. 1: 34 + 8s + 13 + floor((34 + 8s - 1) / 4) bits, 2 us each at 500 kbit/s
    assert t["Sensor_U01"].bits == 135 and t["Sensor_U01"].c_s == pytest.approx(270 * US)
    assert t["AgentAux_U01"].bits == 125 and t["TractionCmd_U01"].bits == 105 and t["ReferenceAux"].bits == 95
    # per 10 ms: Reference 135 + ReferenceAux 95 + 4 x (135 + 105 + 135 + 125) + RadioBehind 135 + 125 = 2490 bits
    assert utilisation(t.values()) == pytest.approx(2490 * 2 * US / 0.01)  # 49.8 %


def test_wcrt_of_highest_and_lowest_priority_frames(db, seed000):
    setup = TrainBusSetup.from_scenario(seed000, 0)
    t = by_name(analyse_train_bus(db, setup))
    # highest priority: its own C plus blocking by the longest lower-priority frame (8 bytes, 270 us)
    assert t["TractionCmd_U01"].wcrt_s == pytest.approx((210 + 270) * US)
    # forwarded to bus1: train 2's head AgentAux_U01 (0x120). On bus2 it waits for everything above it
    # (4 TractionCmd 840 + Reference 270 + Aux 190 + 4 Sensor 1080 + 4 AgentState 1080 = 3460 us) and one
    # 270 us lower-priority frame: R = 3460 + 270 + 250 = 3980 us; best case 103 bits = 206 us.
    ahead, behind = forwarded_jitter(db, setup)
    assert behind == pytest.approx((3980 - 206) * US)
    # lowest priority on bus1: no blocking, every other frame once: R = J + (4980 - 250) + 250 us
    assert t["RadioBehindAux"].wcrt_s == pytest.approx(behind + 4980 * US)
    assert all(x.schedulable for x in t.values())


def test_radio_jitter_of_the_scenario_adds_to_the_bound(db, seed000):
    base = TrainBusSetup.from_scenario(seed000, 0)
    jittery = TrainBusSetup.from_scenario(load_scenario("seed000", {"radio.jitter_s": 0.002}), 0)
    assert forwarded_jitter(db, jittery)[1] == pytest.approx(forwarded_jitter(db, base)[1] + 0.002)
    with pytest.raises(CanAnalysisError, match="jitter_distribution = 'normal' has no upper bound"):
        TrainBusSetup.from_scenario(load_scenario("seed000", {"radio.jitter_s": 0.01, "radio.jitter_distribution": "normal"}))


def test_overloaded_bus_reports_unbounded_frames(db):
    t = analyse_train_bus(db, TrainBusSetup(units=16, bitrate=125_000))
    # per 10 ms: 230 + 16 x 500 + both radio directions 520 = 8750 bits x 8 us = 70 ms
    assert utilisation(t) == pytest.approx(7.0)
    named = by_name(t)
    assert named["TractionCmd_U01"].schedulable and named["TractionCmd_U01"].wcrt_s == pytest.approx((840 + 1080) * US)
    assert named["RadioBehindAux"].wcrt_s == float("inf") and not named["RadioBehindAux"].schedulable
    assert "inf" in format_table(t)


# --------------------------------------------------------------------------- measured beside the bound


def test_measured_latencies_beside_bounds_and_flagged(db):
    msgs = train_bus_messages(db, 4, radio_ahead=False)
    t = by_name(analyse(msgs, 500_000, {0x080: 300 * US, 0x0C0: 3e-3}))
    assert t["TractionCmd_U01"].ratio == pytest.approx(300 / 480) and not t["TractionCmd_U01"].exceeds
    assert t["Sensor_U01"].exceeds and t["Sensor_U02"].measured_s is None and t["Sensor_U02"].ratio is None
    lines = format_table(list(t.values()), 500_000).splitlines()
    header, rows = lines[0], lines[1:19]
    assert "measured ms" in header and "meas/WCRT" in header
    flagged = [r.split()[0] for r in rows if "EXCEEDS BOUND" in r]
    assert flagged == ["Sensor_U01"]
    row = next(r for r in rows if r.startswith("TractionCmd_U01"))
    assert "0x080" in row and "0.480" in row and "0.300" in row and "0.625" in row
    assert len({r.index("0x") for r in rows}) == 1  # aligned columns
    assert "measured above bound: Sensor_U01 (0x0C0)" in lines


def test_table_without_measurements_has_no_measured_columns(db):
    out = format_table(analyse(train_bus_messages(db, 1), 1_000_000), 1_000_000)
    assert "measured" not in out and "bus utilisation at 1000 kbit/s" in out


# --------------------------------------------------------------------------- the CLI


def cli(argv, capsys) -> tuple[int, str, str]:
    parser = argparse.ArgumentParser(prog="hil")
    add_can_analysis_parser(parser.add_subparsers(dest="command", required=True))
    args = parser.parse_args(["can-analysis", *argv])
    code = args.func(args)
    out, err = capsys.readouterr()
    return code, out, err


def printed_ids(out: str) -> set[int]:
    return {int(m, 16) for m in re.findall(r"^\S+\s+0x([0-9A-F]{3})\s", out, re.MULTILINE)}


def test_cli_prints_every_frame_of_the_scenarios_bus(capsys):
    code, out, _ = cli(["--scenario", "seed000", "--bus", "bus1"], capsys)
    assert code == 0
    assert printed_ids(out) == BUS1_IDS
    assert "bus utilisation at 500 kbit/s: 49.80 %" in out
    code, out, _ = cli(["--scenario", "seed000", "--bus", "bus2", "--bitrate", "1000000"], capsys)
    assert code == 0 and printed_ids(out) == BUS1_IDS | {0x180, 0x181} and "27.50 %" in out


def test_cli_without_scenario_uses_the_dbc(capsys):
    code, out, _ = cli(["--bitrate", "500000", "--units", "8"], capsys)
    assert code == 0
    assert {0x087, 0x0C7, 0x107, 0x127, 0x180, 0x181, 0x188, 0x189} <= printed_ids(out)
    assert 0x088 not in printed_ids(out) and len(printed_ids(out)) == 2 + 4 * 8 + 4


@pytest.mark.parametrize("argv, message", [
    (["--units", "4"], "--bitrate is required without --scenario"),
    (["--scenario", "seed000", "--bus", "bus4"], "bus1..bus3"),
    (["--scenario", "no-such-scenario"], "unknown scenario"),
    (["--bitrate", "500000", "--bus", "front"], "--bus 'front'"),
])
def test_cli_user_errors_exit_2(argv, message, capsys):
    code, out, err = cli(argv, capsys)
    assert code == 2 and message in err and out == ""


def test_cli_measured_without_the_key_names_the_file(tmp_path, capsys):
    (tmp_path / "metrics.json").write_text(json.dumps({"per_bus": {"bus1": {"latency_max_s": 0.002}}}))
    code, _, err = cli(["--scenario", "seed000", "--measured", str(tmp_path)], capsys)
    assert code == 2
    assert str(tmp_path / "metrics.json") in err and "latency_max_by_id" in err and "written before" in err
    code, _, err = cli(["--scenario", "seed000", "--measured", str(tmp_path / "nowhere")], capsys)
    assert code == 2 and str(tmp_path / "nowhere" / "metrics.json") in err


def test_cli_measured_from_a_real_run_stays_under_the_bounds(tmp_path, capsys):
    from hil.record.metrics import run_metrics
    from hil.runtime.virtual import VirtualRig

    sc = load_scenario("seed000")
    log = VirtualRig(sc).run(2.0)
    metrics = run_metrics(log, sc, "virtual", sc.seed)
    (tmp_path / "metrics.json").write_text(json.dumps(metrics))
    code, out, _ = cli(["--scenario", "seed000", "--bus", "bus2", "--measured", str(tmp_path)], capsys)
    assert code == 0
    assert "measured above bound: none" in out and "EXCEEDS" not in out
    measured_rows = [r for r in out.splitlines() if re.match(r"^\S+\s+0x", r) and r.split()[11] != "-"]
    assert {int(r.split()[1], 16) for r in measured_rows} == BUS1_IDS | {0x180, 0x181}


def test_python_dash_m_entry_point():
    proc = subprocess.run([sys.executable, "-m", "hil.commands.can_analysis", "--bitrate", "250000", "--units", "2"],
                          capture_output=True, text=True, timeout=60)
    assert proc.returncode == 0, proc.stderr
    assert "Sensor_U02" in proc.stdout and "Sensor_U03" not in proc.stdout
