"""CAN FD on the bus: the scenario fields, both bus models timing FD frames alike, error frames at both rates,
and the response-time analysis bounding what an FD run measures."""
from __future__ import annotations

import json
import random

import numpy as np
import pytest

from tests.oracle.bus_model import CanBusModel
from tests.oracle.bus_errors import ERROR_TAIL_BITS, BusErrors
from hil.can.frame import (
    FD_LENGTHS,
    FD_TAIL_BITS,
    best_case_fd_frame_bits,
    fd_frame_bits,
    fd_pad,
    frame_bits,
    worst_case_fd_frame_bits,
)
from hil.record.metrics import run_metrics
from hil.runtime.virtual import VirtualRig
from hil.scenario import ScenarioError, load_scenario
from tests.oracle.python_rig import rig_on

FD_5M = {"can.fd": True, "can.data_bitrate": 5_000_000}


@pytest.mark.parametrize("overrides, message", [
    ({"can.data_bitrate": 2_000_000}, "data_bitrate is a CAN FD setting: set fd = true"),
    ({"can.fd": True, "can.bitrate": 1_000_000, "can.data_bitrate": 500_000}, "below the nominal bitrate 1000000"),
    ({"can.fd": True, "can.data_bitrate": 3_000_000}, "no whole-nanosecond bit time"),
    ({"can.fd": True, "can.data_bitrate": 20_000_000}, "can.data_bitrate"),
])
def test_bad_fd_settings_are_named(overrides, message):
    with pytest.raises(ScenarioError, match=message):
        load_scenario("seed000", overrides)


def test_fd_payloads_are_padded_to_the_next_dlc_length():
    assert [len(fd_pad(bytes(n))) for n in (0, 8, 9, 13, 17, 21, 25, 33, 49, 64)] == [0, 8, 12, 16, 20, 24, 32, 48, 64, 64]
    with pytest.raises(ValueError, match="65 data bytes exceed"):
        fd_pad(bytes(65))


def test_the_worst_and_best_case_bounds_hold_every_fd_frame():
    """The analysis's lengths bound the exact count of every frame tried, patterns that stuff most included."""
    rng = random.Random(3)
    for extended in (False, True):
        for length in FD_LENGTHS:
            (wn, wd), (bn, bd) = worst_case_fd_frame_bits(length, extended), best_case_fd_frame_bits(length, extended)
            for k in range(400):
                can_id = 0 if k % 5 == 0 else rng.randrange(1 << (29 if extended else 11))
                data = bytes(rng.choice((0x00, 0xFF, 0x0F, 0x78, 0x3C, rng.randrange(256))) for _ in range(length))
                n, d = fd_frame_bits(can_id, data, extended)
                assert bn <= n <= wn and bd <= d <= wd and bn + bd <= n + d <= wn + wd, (extended, length, can_id, data)


def _frames(rig: VirtualRig) -> list[list[tuple]]:
    rows: list[list[tuple]] = [[] for _ in rig.buses]
    for i, bus in enumerate(rig.buses):
        bus.frame_listeners.append(lambda tx, out=rows[i]: out.append((tx.frame_id, bytes(tx.data), tx.t_start, tx.t_end)))
    return rows


def test_engine_and_python_model_time_fd_frames_alike():
    """The same FD schedule from both bus models, every frame timed at two rates (seed000 at 500k/2M, 3 s)."""
    sc = load_scenario("seed000", {"can.fd": True, "can.data_bitrate": 2_000_000})
    runs = []
    for network in ("python", "engine"):
        rig = rig_on(network, sc)
        rows = _frames(rig)
        runs.append((rows, rig.run(3.0)))
    (py, py_log), (en, en_log) = runs
    assert sum(map(len, en)) > 10_000 and py == en
    assert np.array_equal(py_log.signals.array, en_log.signals.array)
    frame_id, data, start, end = en[0][0]
    nominal, fast = fd_frame_bits(frame_id, data)
    assert end - start == nominal * 2000 + fast * 500  # 500 kbit/s arbitration, 2 Mbit/s data


def test_fd_with_brs_unloads_the_bus_and_the_control_result_stays():
    """seed000 over CAN FD at 500k/5M: a smaller bus load and latency than classical CAN, the same physics within
    what the shorter delays change."""
    classical, fd = (VirtualRig(load_scenario("seed000", o)).run(5.0) for o in ({}, FD_5M))
    load = [max(b.load.array[:, 1]) for b in (classical.buses[0], fd.buses[0])]
    assert load[1] < 0.6 * load[0]
    speed = [log.signals.array for log in (classical, fd)]
    assert np.allclose(speed[0], speed[1], atol=0.5)  # positions, speeds, forces: same run within 0.5


def _fd_bus(data_bitrate: int = 4_000_000) -> CanBusModel:
    return CanBusModel("b", 1_000_000, fd=True, data_bitrate=data_bitrate)


def test_a_destroyed_fd_frame_holds_the_bus_for_its_bits_at_both_rates_and_its_error_frame_at_the_nominal():
    bus = _fd_bus()
    errors = BusErrors(bus, rng=np.random.default_rng(0))
    sender = bus.attach("tx")
    bus.attach("rx", lambda *a: None)
    bus.enqueue(sender, 0x10, bytes(range(20)), 0)  # padded to 20 (a DLC length)
    tx = bus.arbitrate(0)
    assert tx is not None and len(tx.data) == 20
    errors._fail(tx, "crc", 40)  # detected at bit 40 (inside the data phase): bits 0..40 counted
    nominal, _ = fd_frame_bits(0x10, tx.data)
    arbitration = nominal - FD_TAIL_BITS
    assert tx.t_end == arbitration * 1000 + (41 - arbitration) * 250 + ERROR_TAIL_BITS * 1000
    bus.complete()
    assert errors.counters_of(sender).tec == 8 and errors.stats["retransmissions"] == 1  # confinement as classical


def test_a_corrupted_fd_frame_is_rejected_after_its_ack_delimiter():
    bus = _fd_bus()
    errors = BusErrors(bus, rng=np.random.default_rng(0))
    sender = bus.attach("tx")
    bus.enqueue(sender, 0x10, bytes(8), 0)
    tx = bus.arbitrate(0)
    errors._corrupt(tx, 3)
    nominal, fast = fd_frame_bits(0x10, bytes(8))
    assert tx.error == "crc" and errors.stats["rejected"] == 1 and errors.stats["undetected"] == 0
    assert tx.t_end == (nominal - 10) * 1000 + fast * 250 + ERROR_TAIL_BITS * 1000  # up to the ACK delimiter


def test_a_classical_bus_is_unchanged():
    bus = CanBusModel("b", 500_000)
    node = bus.attach("tx")
    bus.enqueue(node, 0x10, bytes(5), 0)
    assert bus.arbitrate(0).t_end == frame_bits(0x10, bytes(5)) * 2000


def test_can_analysis_of_the_packaged_fd_scenario_bounds_its_run(tmp_path, capsys):
    """`hil can-analysis --scenario seed001-fd --measured RUN` after a run of it: every frame under its bound."""
    from hil.commands.can_analysis import main as can_analysis

    sc = load_scenario("seed001-fd")
    assert sc.can.fd and sc.can.data_rate == 5_000_000
    metrics = run_metrics(VirtualRig(sc).run(3.0), sc, "virtual", sc.seed)  # with its provenance
    (tmp_path / "metrics.json").write_text(json.dumps(metrics))
    assert can_analysis(["--scenario", "seed001-fd", "--measured", str(tmp_path)]) == 0
    out = capsys.readouterr().out
    assert "1000 kbit/s CAN FD, data phase 5 Mbit/s" in out and "unschedulable frames: none" in out
    assert "measured above bound: none" in out
    measured = [line for line in out.splitlines() if line.startswith(("Sensor_", "AgentState_", "TractionCmd_"))]
    assert len(measured) == 18 and all(line.split()[11] != "-" for line in measured)  # every frame was measured


@pytest.mark.parametrize("fmt", ["asc", "blf"])
def test_fd_frames_go_into_the_can_logs_in_their_fd_form(tmp_path, fmt):
    """`hil run seed001-fd --can-log FMT`: python-can reads back FD frames with BRS, cantools decodes them."""
    import subprocess
    import sys

    import can
    import cantools

    from ecu_sim.codec import default_dbc_path

    out = tmp_path / "r"
    proc = subprocess.run([sys.executable, "-m", "hil", "run", "seed001-fd", "--duration", "0.5", "--out", str(out),
                           "--no-record", "--quiet", "--can-log", fmt], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    reader = can.ASCReader if fmt == "asc" else can.BLFReader
    msgs = list(reader(out / f"bus1.{fmt}"))
    assert len(msgs) > 1000 and all(m.is_fd and m.bitrate_switch for m in msgs)
    db = cantools.database.load_file(default_dbc_path())
    sensor = next(m for m in msgs if m.arbitration_id == 0x0C0)
    assert db.decode_message(0x0C0, bytes(sensor.data))["Position"] > 400  # car 1 starts at 486.6 m


@pytest.mark.parametrize("dbc", ["train.dbc", "train_fd.dbc"])
def test_the_faults_scenario_on_fd_buses_confines_errors_as_on_classical_ones(tmp_path, dbc):
    """The faults scenario's first 16 s (a crash, a babbling node, corruption) over CAN FD 500k/5M, its frames as
    they are or packed (train_fd.dbc): every fault injected and detected, corrupted FD frames rejected (none
    undetected), senders driven bus-off and back, as over classical CAN."""
    from hil.session import run_scenario

    res = run_scenario(load_scenario("faults", {**FD_5M, "can.dbc": dbc}), tmp_path, duration_s=16.0, record=False)
    f = res.metrics["faults"]
    assert f["injected"] == f["detected"] == 3
    errors = f["can_errors"]
    assert errors["corrupted"] == errors["rejected"] > 0 and errors["undetected"] == 0
    bus1 = errors["buses"]["bus1"]
    assert errors["error_frames"] == errors["corrupted"] and bus1["retransmissions"] > 0 and bus1["by_error"] == {
        "crc": errors["corrupted"]}  # an FD frame's corruption is found by its CRC
    assert any(node["bus_off"] > 0 and node["state"] == "error_active" for node in bus1["nodes"].values())  # recovered
