"""CAN FD frame packing (dbc/train_fd.dbc): each sender's frames of one instant go as one container frame, every
receiver gets them back as the frames they were, and the run, the analysis, the logs and real time agree."""
from __future__ import annotations

import importlib.util
import json
import subprocess
import sys
from collections import Counter
from pathlib import Path

import cantools
import numpy as np
import pytest

from ecu_sim.codec import DbcMismatchError, TrainDb, default_dbc_path
from hil.record.metrics import run_metrics
from hil.runtime.train_db import load_train_db
from hil.runtime.virtual import VirtualRig
from hil.scenario import ScenarioError, load_scenario
from tests.oracle.python_rig import rig_on

FD_DBC = default_dbc_path("train_fd.dbc")
PACKED = {"can.fd": True, "can.data_bitrate": 2_000_000, "can.dbc": "train_fd.dbc"}


@pytest.fixture(scope="module")
def fd_db() -> TrainDb:
    return TrainDb.load(FD_DBC)


def test_train_fd_dbc_is_what_make_train_fd_writes():
    """The checked-in FD DBC is dbc/make_train_fd.py's output from dbc/train.dbc (the one source stays train.dbc)."""
    spec = importlib.util.spec_from_file_location("make_train_fd", FD_DBC.parent / "make_train_fd.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)  # type: ignore[union-attr]
    assert module.build() == FD_DBC.read_text()


def test_the_fd_dbc_holds_each_senders_frames_in_one_container(fd_db):
    unit = fd_db.container_by_id[0x060]
    assert (unit.name, unit.length) == ("UnitFD_U01", 20)
    assert [(p.name, p.offset, p.length) for p in unit.parts] == [
        ("TractionCmd_U01", 0, 5), ("AgentState_U01", 5, 8), ("AgentAux_U01", 13, 7)]
    assert fd_db.container_by_id[0x0B8].length == 64 and len(fd_db.container_by_id[0x0B8].parts) == 8
    assert [p.name for p in fd_db.container_by_id[0x0A8].parts] == ["Reference", "ReferenceAux"]
    six = {c.name: c for c in fd_db.containers_for(6)}
    assert six["SensorFD_A"].length == 64 and "SensorFD_B" not in six  # its DBC length, slots 7-8 zero and "UnitFD_U07" not in six
    assert TrainDb.load().containers == () and TrainDb.load().packing() is None


def test_cantools_decodes_a_packed_frame_as_its_parts(fd_db):
    """A container built by the engine's packing decodes, with the FD DBC in cantools, to its parts' values."""
    cmd, state, aux = fd_db.traction_cmd(2), fd_db.agent_state(2), fd_db.agent_aux(2)
    frames = [(cmd.frame_id, cmd.encode((0, -1230.0), 7)), (state.frame_id, state.encode((1234.567, 55.5), 7)),
              (aux.frame_id, aux.encode((0.25, 4560.0), 7))]
    [(frame_id, data)] = fd_db.packing(4).pack(frames)
    assert frame_id == 0x062 and len(data) == 20
    decoded = cantools.database.load_file(FD_DBC).decode_message(frame_id, data)
    assert decoded["AgentState_U03_Position"] == pytest.approx(1234.567) and decoded["TractionCmd_U03_Force"] == -1230
    assert decoded["AgentAux_U03_Accel"] == pytest.approx(0.25) and decoded["AgentState_U03_AliveCounter"] == 7
    assert fd_db.packing(4).unpack(frame_id, data) == frames


@pytest.mark.parametrize("edit, message", [
    (lambda t: t.replace('"TractionCmd_U01 AgentState_U01 AgentAux_U01"', '"TractionCmd_U01 AgentState_U99"', 1),
     "names AgentState_U99, which is not a message"),
    (lambda t: t.replace("BO_ 96 UnitFD_U01: 20 ECU_U01", "BO_ 96 UnitFD_U01: 24 ECU_U01", 1), "its length must be 20, not 24"),
    (lambda t: t.replace(" SG_ AgentState_U01_Speed : 82|19@1-", " SG_ AgentState_U01_Speed : 83|19@1-", 1),
     "its parts' signals at their byte offsets"),
    (lambda t: t.replace('BA_ "VFrameFormat" BO_ 96 14;', "", 1), "must be a CAN FD frame"),
])
def test_a_container_that_does_not_match_its_parts_is_refused_by_name(tmp_path, edit, message):
    path = tmp_path / "bad.dbc"
    path.write_text(edit(FD_DBC.read_text()))
    with pytest.raises(DbcMismatchError, match="container UnitFD_U01") as err:
        TrainDb.load(path)
    assert message in str(err.value)


def _ids_on_the_bus(rig: VirtualRig, bus: int = 0) -> Counter:
    seen: Counter = Counter()
    rig.buses[bus].frame_listeners.append(lambda tx: seen.update([tx.frame_id]))
    return seen


def test_a_packed_run_sends_one_frame_per_sender_and_cycle_and_its_parts_arrive_intact():
    """seed000 (3 trains x 4 units, 10 ms) over FD 500k/2M with train_fd.dbc, 3 s: on bus1 each ECU's container
    every cycle (a lone TractionCmd only while its first sensor sample is not in), the plant's one sensor
    container, the wayside's one reference container; no receiver saw a bad or missing frame; the physics is the
    unpacked FD run's within what the shorter latencies change."""
    sc = load_scenario("seed000", PACKED)
    rig = VirtualRig(sc)
    seen = _ids_on_the_bus(rig)
    log = rig.run(3.0)
    cycles = 300
    assert all(seen[0x060 + u] >= cycles - 1 for u in range(4)) and seen[0x0B8] == cycles
    assert seen[0x0A8] == round(3.0 / sc.reference.period_s)
    assert sum(seen[0x080 + u] for u in range(4)) <= 4  # lone commands: at most the first cycle of each
    assert not any(seen[i] for i in (0x0C0, 0x100, 0x120, 0x0A0, 0x0A1))  # no part travels alone once packed
    plain = VirtualRig(load_scenario("seed000", {k: v for k, v in PACKED.items() if k != "can.dbc"}))
    unpacked = plain.run(3.0)
    verdicts = [ecu.e2e_summary() for ecu in rig.ecus]
    assert verdicts == [ecu.e2e_summary() for ecu in plain.ecus]  # every stream arrived as often, and as good
    assert all(set(v) == {"OK", "INITIAL"} for v in verdicts)
    assert np.allclose(log.signals.array, unpacked.signals.array, atol=0.5)
    packed_load, load = (max(b.load.array[:, 1]) for b in (log.buses[0], unpacked.buses[0]))
    assert packed_load < 0.75 * load


def test_the_engine_and_the_python_bus_model_pack_alike():
    """The same packed frame schedule, E2E verdicts and signals from both bus models (seed000 on FD 500k/2M, 3 s)."""
    sc = load_scenario("seed000", PACKED)
    runs = []
    for network in ("python", "engine"):
        rig = rig_on(network, sc)
        rows: list[list] = [[] for _ in rig.buses]
        for bus, out in zip(rig.buses, rows):
            bus.frame_listeners.append(lambda tx, out=out: out.append((tx.frame_id, bytes(tx.data), tx.t_start, tx.t_end)))
        log = rig.run(3.0)
        runs.append((rows, log.signals.array, [e.e2e_summary() for e in rig.ecus]))
    (py_rows, py_signals, py_e2e), (en_rows, en_signals, en_e2e) = runs
    assert sum(map(len, en_rows)) > 7000 and py_rows == en_rows and py_e2e == en_e2e  # bus by bus, frame by frame
    assert np.array_equal(py_signals, en_signals)
    assert Counter(r[0] for r in en_rows[0])[0x060] == 300  # UnitFD_U01 every cycle: packed in both


def test_a_packed_dbc_needs_an_fd_bus(tmp_path):
    with pytest.raises(ScenarioError, match=r"can.dbc = 'train_fd.dbc' packs frames into CAN FD containers.*set can.fd = true"):
        VirtualRig(load_scenario("seed000", {"can.dbc": "train_fd.dbc"}))
    with pytest.raises(ScenarioError, match=r"set can.fd = true"):
        load_train_db(load_scenario("seed001", {"can.dbc": "train_fd.dbc"}))
    with pytest.raises(ScenarioError, match=r"can.dbc.*no DBC 'nope.dbc'"):
        load_scenario("seed000", {"can.dbc": "nope.dbc"})
    out = tmp_path / "r"
    proc = subprocess.run([sys.executable, "-m", "hil", "run", "seed000", "--set", "can.dbc=train_fd.dbc", "--duration",
                           "1", "--no-record", "--quiet", "--out", str(out)], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2 and "set can.fd = true" in proc.stderr and "Traceback" not in proc.stderr
    assert not out.exists() or not any(out.iterdir())  # refused before anything was written: no stub in the way


def test_can_analysis_of_the_packed_scenario_bounds_its_run(tmp_path, capsys):
    """`hil can-analysis --scenario seed001-fd-packed --measured RUN`: seed 001's own 1 ms exchange, eight frames per
    period on FD 1M/5M, each under its worst-case bound in the run."""
    from hil.commands.can_analysis import main as can_analysis

    sc = load_scenario("seed001-fd-packed")
    assert sc.ecu.cycle_s == 0.001 and sc.can.dbc == "train_fd.dbc"
    metrics = run_metrics(VirtualRig(sc).run(2.0), sc, "virtual", sc.seed)
    (tmp_path / "metrics.json").write_text(json.dumps(metrics))
    assert can_analysis(["--scenario", "seed001-fd-packed", "--measured", str(tmp_path)]) == 0
    out = capsys.readouterr().out
    assert "train_fd.dbc" in out and "unschedulable frames: none" in out and "measured above bound: none" in out
    rows = [line.split() for line in out.splitlines() if line.startswith(("UnitFD_", "SensorFD_", "ReferenceFD"))]
    assert len(rows) == 8 and all(row[11] != "-" for row in rows)  # every container was measured
    assert can_analysis([str(FD_DBC), "--bitrate", "1000000"]) == 2  # containers on classical CAN: said, not raised
    assert "packs frames into CAN FD containers: analyse it on a CAN FD bus" in capsys.readouterr().err


def strictly_decoded(log_file: Path, dbc: Path) -> Counter:
    """Decode every frame of a CAN log strictly (no truncated or excess bytes) with ``dbc``: frames per ID."""
    import can

    db = cantools.database.load_file(dbc)
    seen: Counter = Counter()
    for m in can.LogReader(log_file):
        message = db.get_message_by_frame_id(m.arbitration_id)
        assert len(m.data) == message.length, (message.name, len(m.data), message.length)
        message.decode(bytes(m.data), allow_truncated=False, allow_excess=False)
        seen[m.arbitration_id] += 1
    return seen


def test_packed_frames_go_into_the_can_log_and_decode_with_the_fd_dbc(tmp_path):
    """Every frame on the wire decodes strictly with the run's DBC: a sensor container of a 6-unit train keeps its
    64 bytes (slots 7 and 8 zero); it used to go with 48, which CANoe and strict cantools refuse."""
    import can

    out = tmp_path / "r"
    proc = subprocess.run([sys.executable, "-m", "hil", "run", "seed001-fd-packed", "--duration", "0.2", "--out",
                           str(out), "--no-record", "--quiet", "--can-log", "asc"], capture_output=True, text=True,
                          timeout=120)
    assert proc.returncode == 0, proc.stderr
    assert sum(strictly_decoded(out / "bus1.asc", FD_DBC).values()) > 1000
    sensors = [m for m in can.ASCReader(out / "bus1.asc") if m.arbitration_id == 0x0B8]
    assert len(sensors) == 200 and all(m.is_fd and m.bitrate_switch and m.dlc == 64 for m in sensors)
    decoded = cantools.database.load_file(FD_DBC).decode_message(0x0B8, bytes(sensors[0].data))
    assert decoded["Sensor_U01_Position"] > 400 and decoded["Sensor_U07_Position"] == 0


def test_a_packed_fd_run_in_real_time(rt, tmp_path):
    """The real-time nodes pack and unpack as the virtual rig does: one frame per sender and cycle, nothing lost."""
    from hil.runtime.realtime.orchestrator import run_realtime

    sc = load_scenario("seed000", PACKED)
    res = run_realtime(sc, tmp_path / "rt", pace=1.0, duration_s=1.0, ecus_per_process=6, can_log=True)
    assert res.metrics["frames_lost"] == 0
    assert not any(v.get("CRC_ERROR") or v.get("WRONG_LENGTH") or v.get("UNKNOWN_ID") for v in res.metrics["e2e"].values())
    import can

    ids = strictly_decoded(tmp_path / "rt" / "bus1.asc", FD_DBC)
    assert ids[0x0B8] >= 95 and all(ids[0x060 + u] >= 90 for u in range(4))
    assert not any(ids[i] for i in (0x0C0, 0x100, 0x120))


def test_the_firmware_test_kit_sees_a_packed_message_inside_its_container():
    """hil.testing's frame-period check counts a message that travelled in a container (the run's own DBC), and
    names the containers too."""
    from hil.testing import HilAssertionError, Rig, assert_frame_period

    run = Rig("seed000", set=PACKED).run(0.5)
    assert not len(run.frame_times(0x081, "bus1"))  # TractionCmd_U02 never travelled alone ...
    assert_frame_period(run, "TractionCmd_U*", max_gap_ms=12.0, after=0.02)  # ... but arrived every cycle
    assert_frame_period(run, "UnitFD_U02", max_gap_ms=12.0, after=0.02)
    with pytest.raises(HilAssertionError, match=r"SensorFD_A \(0x0B8\)"):
        assert_frame_period(run, "SensorFD_A", max_gap_ms=5.0)


def test_the_kn_pid_at_1_4_ms_holds_over_packed_fd_when_each_ecu_runs_right_after_its_sample():
    """seed004-kn-pid-fd-packed (3 s): with the reference at the ECU period and every ECU 0.2 ms after the sample, no
    force saturates and the speed error is the ideal loop's within 50 %; with the rig's default phase (0.6-1.3 ms
    after the sample) cars 5 and 7, near their sampled loop's margin, saturate at the Force signal's limit."""
    from hil.runtime.ideal import IdealLoop

    sc = load_scenario("seed004-kn-pid-fd-packed")
    on_time = VirtualRig(sc).run(3.0)
    late = VirtualRig(load_scenario("seed004-kn-pid-fd-packed", {"ecu.phase_s": 0.002, "ecu.stagger_s": 0.0001})).run(3.0)
    ideal = IdealLoop(sc).run(3.0)

    def worst_speed_error(log) -> float:
        return float(np.abs(log.speed_error[log.t > 1.0]).max())

    assert not on_time.codec_saturations and worst_speed_error(on_time) < 1.5 * worst_speed_error(ideal)
    assert {"TractionCmd_U05.Force", "TractionCmd_U07.Force"} <= set(late.codec_saturations)
    assert worst_speed_error(late) > 10 * worst_speed_error(ideal)
