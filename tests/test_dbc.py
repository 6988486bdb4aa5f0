"""The committed DBC: cantools reads it cleanly, and it has the frames, layouts and resolution we specified."""
from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import cantools
import pytest

DBC = Path(__file__).resolve().parents[1] / "dbc" / "train.dbc"
UNITS = range(1, 17)

# Hand-written spec: name -> (frame id, DLC, sender, E2E data ID).
EXPECTED: dict[str, tuple[int, int, str, int]] = {
    **{f"TractionCmd_U{u:02d}": (0x080 + u - 1, 5, f"ECU_U{u:02d}", 1) for u in UNITS},
    "Reference": (0x0A0, 8, "Wayside", 2),
    "ReferenceAux": (0x0A1, 4, "Wayside", 3),
    **{f"Sensor_U{u:02d}": (0x0C0 + u - 1, 8, "Plant", 4) for u in UNITS},
    **{f"AgentState_U{u:02d}": (0x100 + u - 1, 8, f"ECU_U{u:02d}", 5) for u in UNITS},
    **{f"AgentAux_U{u:02d}": (0x120 + u - 1, 7, f"ECU_U{u:02d}", 6) for u in UNITS},
    "RadioAheadState": (0x180, 8, "RadioGW", 5),
    "RadioAheadAux": (0x181, 7, "RadioGW", 6),
    "RadioBehindState": (0x188, 8, "RadioGW", 5),
    "RadioBehindAux": (0x189, 7, "RadioGW", 6),
}

# Payload layouts: signal -> (start bit, length, signed, scale).
STATE = {"Position": (12, 30, False, 0.001), "Speed": (42, 19, True, 0.0005)}
AUX = {"Accel": (12, 20, True, 0.001), "Force": (32, 20, True, 10)}
LAYOUT = {
    "TractionCmd": {"Mode": (12, 2, False, 1), "Force": (14, 20, True, 10)},
    "Reference": STATE,
    "ReferenceAux": {"Accel": (12, 20, True, 0.001)},
    "Sensor": STATE,
    "AgentState": STATE,
    "AgentAux": AUX,
    "RadioAheadState": STATE,
    "RadioBehindState": STATE,
    "RadioAheadAux": AUX,
    "RadioBehindAux": AUX,
}


@pytest.fixture(scope="module")
def db() -> cantools.database.can.Database:
    return cantools.database.load_file(DBC, strict=True)


def family(name: str) -> str:
    return name.split("_U")[0]


def test_cantools_dump_reads_it_cleanly() -> None:
    cmd = [sys.executable, "-m", "cantools", "dump", str(DBC)]
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=60)
    assert proc.returncode == 0, proc.stderr
    assert proc.stderr == ""
    assert "Name:           AgentAux_U16" in proc.stdout


def test_nodes(db) -> None:
    assert [n.name for n in db.nodes] == ["Plant", "Wayside", "RadioGW", *[f"ECU_U{u:02d}" for u in UNITS]]


def test_messages_ids_dlc_senders_data_ids(db) -> None:
    assert {m.name for m in db.messages} == set(EXPECTED)
    for m in db.messages:
        frame_id, dlc, sender, data_id = EXPECTED[m.name]
        assert (m.frame_id, m.length, m.senders) == (frame_id, dlc, [sender]), m.name
        assert not m.is_extended_frame and not m.is_fd and m.frame_id < 0x800
        assert m.dbc.attributes["E2EDataID"].value == data_id, m.name
        assert m.cycle_time == 10 and m.send_type == "Cyclic", m.name
        assert m.comment, f"{m.name} has no comment"


def test_radio_frames_carry_the_data_id_of_the_frame_they_forward(db) -> None:
    did = {m.name: m.dbc.attributes["E2EDataID"].value for m in db.messages}
    assert did["RadioAheadState"] == did["RadioBehindState"] == did["AgentState_U01"]
    assert did["RadioAheadAux"] == did["RadioBehindAux"] == did["AgentAux_U01"]


def test_e2e_header_on_every_message(db) -> None:
    for m in db.messages:
        crc, counter = m.get_signal_by_name("CRC"), m.get_signal_by_name("AliveCounter")
        assert (crc.start, crc.length, crc.is_signed, crc.byte_order) == (0, 8, False, "little_endian"), m.name
        assert (counter.start, counter.length, counter.is_signed, counter.byte_order) == (8, 4, False, "little_endian")
        assert crc.comment and counter.comment


def test_payload_layouts(db) -> None:
    for m in db.messages:
        payload = {s.name: s for s in m.signals if s.name not in ("CRC", "AliveCounter")}
        expected = LAYOUT[family(m.name)]
        assert set(payload) == set(expected), m.name
        for name, (start, length, signed, scale) in expected.items():
            s = payload[name]
            got = (s.start, s.length, s.is_signed, s.scale, s.offset)
            assert got == (start, length, signed, scale, 0), f"{m.name}.{name}"
            assert s.byte_order == "little_endian" and not s.is_float
            assert start + length <= 8 * m.length, f"{m.name}.{name} overruns the DLC"
        # No two signals share a bit.
        bits = [b for s in m.signals for b in range(s.start, s.start + s.length)]
        assert len(bits) == len(set(bits)), m.name


def test_units_and_ranges(db) -> None:
    ref = db.get_message_by_name("Reference")
    assert ref.get_signal_by_name("Position").unit == "m" and ref.get_signal_by_name("Speed").unit == "m/s"
    assert (ref.get_signal_by_name("Position").minimum, ref.get_signal_by_name("Position").maximum) == (0, 1073741.823)
    force = db.get_message_by_name("TractionCmd_U07").get_signal_by_name("Force")
    assert (force.unit, force.minimum, force.maximum) == ("N", -5242880, 5242870)
    assert db.get_message_by_name("ReferenceAux").get_signal_by_name("Accel").unit == "m/s^2"


def test_mode_choices_and_comments(db) -> None:
    for u in UNITS:
        m = db.get_message_by_name(f"TractionCmd_U{u:02d}")
        mode = m.get_signal_by_name("Mode")
        assert {k: str(v) for k, v in mode.choices.items()} == {0: "Normal", 1: "Service", 2: "Emergency"}
        assert mode.comment and m.get_signal_by_name("Force").comment
        assert m.receivers == {"Plant"}


def test_sensor_goes_to_its_own_ecu(db) -> None:
    for u in UNITS:
        assert db.get_message_by_name(f"Sensor_U{u:02d}").receivers == {f"ECU_U{u:02d}"}


def representable(signal) -> tuple[float, float]:
    """Physical range the bits can carry."""
    if signal.is_signed:
        lo, hi = -(1 << (signal.length - 1)), (1 << (signal.length - 1)) - 1
    else:
        lo, hi = 0, (1 << signal.length) - 1
    return lo * signal.scale + signal.offset, hi * signal.scale + signal.offset


@pytest.mark.parametrize("fam", ["Reference", "Sensor_U01", "AgentState_U16", "RadioAheadState", "RadioBehindState"])
def test_state_resolution_requirements(db, fam) -> None:
    m = db.get_message_by_name(fam)
    pos, speed = m.get_signal_by_name("Position"), m.get_signal_by_name("Speed")
    assert pos.scale <= 0.001 and representable(pos)[1] - representable(pos)[0] >= 1_000_000.0
    assert pos.maximum >= 1_000_000.0
    lo, hi = representable(speed)
    assert speed.scale <= 0.0005 and hi >= 110.0 and lo <= -110.0


@pytest.mark.parametrize("name", ["TractionCmd_U01", "AgentAux_U09", "RadioAheadAux", "RadioBehindAux"])
def test_force_resolution_requirements(db, name) -> None:
    force = db.get_message_by_name(name).get_signal_by_name("Force")
    lo, hi = representable(force)
    assert force.scale <= 10 and hi >= 500_000.0 and lo <= -500_000.0
