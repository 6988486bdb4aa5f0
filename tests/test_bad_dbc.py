"""DBC files that do not match what the firmware needs: each is a DbcMismatchError naming the file, message and signal.

Every case edits a copy of dbc/train.dbc in one way (the edit must hit: the test checks the text changed) and
loads it with ``TrainDb.load``: missing messages, wrong signal sizes and scalings, wrong or duplicated IDs,
frames that are not classical CAN, unparseable files. ``tests/test_codec.py`` covers the E2E header cases.
"""
from __future__ import annotations

import re
from pathlib import Path

import pytest

from ecu_sim.codec import DbcMismatchError, TrainDb, default_dbc_path

DBC = default_dbc_path().read_text()


def drop_message(text: str, frame_id: int) -> str:
    """Remove a message, its signals and every line that refers to its ID."""
    text = re.sub(rf"BO_ {frame_id} [^\n]*\n(?: SG_[^\n]*\n)+", "", text)
    return "\n".join(line for line in text.split("\n") if not re.search(rf"(?:BO_|SG_|VAL_) {frame_id}\b", line))


def move_message(text: str, frame_id: int, new_id: int) -> str:
    """Give message ``frame_id`` the ID ``new_id`` everywhere (definition, comments, attributes)."""
    return re.sub(rf"\b(BO_|SG_|VAL_) {frame_id}\b", rf"\g<1> {new_id}", text)


def drop_all(text: str, frame_ids) -> str:
    for frame_id in frame_ids:
        text = drop_message(text, frame_id)
    return text


CASES = [
    # (id, edit, expected regex after the file name)
    ("missing-sensor-unit-5", lambda t: drop_message(t, 0x0C4), r"missing message\(s\) Sensor_U05"),
    ("missing-reference", lambda t: drop_message(t, 0x0A0), r"missing message\(s\) Reference\b"),
    ("missing-every-traction-cmd", lambda t: drop_all(t, range(0x080, 0x090)), r"missing message\(s\) TractionCmd_U01"),
    ("unknown-message", lambda t: t.replace("BO_ 128 TractionCmd_U01:", "BO_ 128 TractionCommand_U01:", 1)
     .replace("TractionCmd_U01", "TractionCommand_U01"), r"TractionCommand_U01|TractionCmd_U01"),
    ("force-4-bits", lambda t: t.replace(" SG_ Force : 14|20@1- (10,0) [-5242880|5242870]", " SG_ Force : 14|4@1- (10,0) [-80|70]", 1),
     r"message TractionCmd_U01: signal Force \(4 bits, scale 10\) carries \[-80, 70\].*needs at least \[-500000, 500000\]"),
    ("force-narrowed-by-limits", lambda t: t.replace("(10,0) [-5242880|5242870]", "(10,0) [-1000|1000]", 1),
     r"message TractionCmd_U01: signal Force .*carries \[-1000, 1000\]"),
    ("mode-1-bit", lambda t: t.replace(" SG_ Mode : 12|2@1+ (1,0) [0|2]", " SG_ Mode : 12|1@1+ (1,0) [0|1]", 1),
     r"message TractionCmd_U01: signal Mode \(1 bits.*needs at least \[0, 2\]"),
    ("position-in-metres", lambda t: re.sub(r"SG_ Position : 12\|30@1\+ \(0\.001,0\) \[0\|1073741\.823\]",
                                            "SG_ Position : 12|30@1+ (1,0) [0|1073741823]", t, count=1),
     r"signal Position .*in steps of 1; the firmware needs .* in steps of 0.001"),
    ("speed-unsigned", lambda t: re.sub(r"SG_ Speed : 42\|19@1- \(0\.0005,0\) \[[^\]]*\]", "SG_ Speed : 42|19@1+ (0.0005,0) [0|262.143]",
                                        t, count=1), r"signal Speed .*carries \[0, 262.143\]"),
    ("signal-overruns-dlc", lambda t: t.replace(" SG_ Force : 14|20@1-", " SG_ Force : 14|30@1-", 1),
     r"cantools cannot load it.*Force does not fit"),
    ("signals-overlap", lambda t: t.replace(" SG_ Mode : 12|2@1+", " SG_ Mode : 12|3@1+", 1), r"overlapping"),
    ("float-signal", lambda t: t.replace(" SG_ Speed : 42|19@1-", " SG_ Speed : 32|32@1-", 1) + "\nSIG_VALTYPE_ 160 Speed : 1;\n",
     r"(Speed must be a plain Intel integer signal|cantools cannot load it)"),
    ("duplicate-id", lambda t: move_message(t, 0x0A1, 0x0A0), r"messages Reference and ReferenceAux share the frame ID 0x0A0"),
    ("id-beyond-11-bits", lambda t: move_message(t, 0x0A0, 0x800), r"(more than 11 bits|11-bit ID)"),
    ("extended-frame", lambda t: move_message(t, 0x0A0, 0x800000A0), r"message Reference: must be a classical CAN frame"),
    ("dlc-9", lambda t: t.replace("BO_ 128 TractionCmd_U01: 5", "BO_ 128 TractionCmd_U01: 9", 1),
     r"message TractionCmd_U01: must be a classical CAN frame with an 11-bit ID and DLC <= 8"),
    ("dlc-too-short", lambda t: t.replace("BO_ 128 TractionCmd_U01: 5", "BO_ 128 TractionCmd_U01: 2", 1), r"does not fit"),
    ("data-id-beyond-a-byte", lambda t: t.replace('BA_ "E2EDataID" BO_ 160 2;', 'BA_ "E2EDataID" BO_ 160 300;'),
     r"message Reference: E2EDataID 300 is not in 0..255"),
    ("garbage", lambda t: "this is not a DBC\n", r"cantools cannot load it"),
    ("empty", lambda t: "", r"cantools cannot load it"),
    ("truncated", lambda t: t[: len(t) // 3], r"(cantools cannot load it|missing message)"),
]


@pytest.mark.parametrize(("edit", "expected"), [c[1:] for c in CASES], ids=[c[0] for c in CASES])
def test_mismatched_dbc_is_refused_naming_file_and_message(tmp_path: Path, edit, expected: str) -> None:
    broken = edit(DBC)
    assert broken != DBC, "the edit did not hit"
    path = tmp_path / "broken.dbc"
    path.write_text(broken)
    with pytest.raises(DbcMismatchError) as err:
        TrainDb.load(path)
    msg = str(err.value)
    assert msg.startswith(f"DBC {path}"), msg
    assert re.search(expected, msg, re.S), msg


@pytest.mark.parametrize("name", ["train.txt", "train", "train.dbc.bak"])
def test_a_dbc_whose_suffix_cantools_does_not_read_is_refused_naming_the_file(tmp_path: Path, name: str) -> None:
    """cantools reads a database's format from its file name: the train DBC under another suffix (or none) is a
    DbcMismatchError naming the file and the suffixes it takes, not cantools' bare ValueError."""
    path = tmp_path / name
    path.write_text(DBC)
    with pytest.raises(DbcMismatchError, match=rf"^DBC {re.escape(str(path))}: .*one of \.dbc, .*this one has"):
        TrainDb.load(path)


def test_the_committed_dbc_meets_every_need() -> None:
    db = TrainDb.load()
    assert db.max_units == 16 and len(db.by_id) == len(db.by_name)
