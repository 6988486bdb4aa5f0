"""Compiled codecs: agree with cantools bit for bit, quantise within half an LSB, saturate, reject bad input."""
from __future__ import annotations

import math
import random
import re
import warnings
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
import pytest
from crccheck.crc import Crc8SaeJ1850

import ecu_sim.codec as codec_mod
from ecu_sim.codec import DbcMismatchError, MessageCodec, TrainDb, default_dbc_path

REPO_DBC = Path(__file__).resolve().parents[1] / "dbc" / "train.dbc"


@pytest.fixture(scope="module")
def db() -> TrainDb:
    return TrainDb.load()


@pytest.fixture()
def fresh_db() -> TrainDb:
    """A private instance for tests that count saturations."""
    return TrainDb.load()


def random_values(codec: MessageCodec, rng: random.Random) -> list[float]:
    """Random physical values inside each signal's range (Mode as a whole number)."""
    return [float(rng.randint(0, 2)) if name == "Mode" else rng.uniform(lo, hi)
            for name, (lo, hi) in zip(codec.signals, codec.limits)]


def scale_of(db: TrainDb, codec: MessageCodec, signal: str) -> float:
    return db.database.get_message_by_name(codec.name).get_signal_by_name(signal).scale


def test_default_path_is_the_repo_dbc() -> None:
    assert default_dbc_path() == REPO_DBC


def test_default_path_falls_back_to_the_installed_copy(tmp_path, monkeypatch) -> None:
    monkeypatch.setattr(codec_mod, "__file__", str(tmp_path / "site" / "ecu_sim" / "codec.py"))
    monkeypatch.setattr(codec_mod.sys, "prefix", str(tmp_path / "venv"))
    with pytest.raises(FileNotFoundError) as err:
        default_dbc_path()
    assert str(tmp_path / "site" / "dbc" / "train.dbc") in str(err.value)
    assert str(tmp_path / "venv" / "share" / "trainhil" / "dbc" / "train.dbc") in str(err.value)
    installed = tmp_path / "venv" / "share" / "trainhil" / "dbc" / "train.dbc"
    installed.parent.mkdir(parents=True)
    installed.write_bytes(REPO_DBC.read_bytes())
    assert default_dbc_path() == installed


def test_lookup_helpers(db) -> None:
    assert db.max_units == 16 and len(db.by_name) == 70 and len(db.by_id) == 70
    assert (db.traction_cmd(0).name, db.traction_cmd(0).frame_id) == ("TractionCmd_U01", 0x080)
    assert db.traction_cmd(15).frame_id == 0x08F
    assert (db.sensor(15).name, db.sensor(15).frame_id) == ("Sensor_U16", 0x0CF)
    assert db.agent_state(3).frame_id == 0x103 and db.agent_aux(15).frame_id == 0x12F
    assert (db.reference.frame_id, db.reference_aux.frame_id) == (0x0A0, 0x0A1)
    assert (db.radio_ahead_state.frame_id, db.radio_ahead_aux.frame_id) == (0x180, 0x181)
    assert (db.radio_behind_state.frame_id, db.radio_behind_aux.frame_id) == (0x188, 0x189)
    assert db.by_id[0x124] is db.agent_aux(4)
    c = db.agent_aux(4)
    assert (c.dlc, c.cycle_time_s, c.data_id, c.signals, c.units) == (7, 0.01, 6, ("Accel", "Force"), ("m/s^2", "N"))
    assert db.traction_cmd(0).signals == ("Mode", "Force") and c.index("Force") == 1
    with pytest.raises(KeyError, match="AgentAux_U05.*Speed"):
        c.index("Speed")


def test_unknown_ids_and_units(db) -> None:
    with pytest.raises(KeyError, match="0x7FF"):
        db.by_id[0x7FF]
    assert db.by_id.get(0x7FF) is None
    with pytest.raises(IndexError, match="16"):
        db.sensor(16)
    with pytest.raises(IndexError, match="-1"):
        db.agent_state(-1)


def test_hand_computed_frame(db) -> None:
    # AgentState_U01: Position 1.000 m -> raw 1000 at bit 12; Speed -0.0005 m/s -> raw -1 = 0x7FFFF (19 bits) at bit 42.
    codec = db.agent_state(0)
    frame = codec.encode([1.0, -0.0005], counter=3)
    word = (3 << 8) | (1000 << 12) | (0x7FFFF << 42)
    body = word.to_bytes(8, "little")[1:]
    assert frame[1:] == body
    assert frame[0] == Crc8SaeJ1850.calc(bytes([5]) + body)
    assert codec.decode(frame) == (1.0, -0.0005)
    assert codec.counter_of(frame) == 3 and codec.crc_ok(frame)


def test_encode_and_decode_agree_with_cantools_for_every_message(db) -> None:
    rng = random.Random(7)
    for codec in db.by_name.values():
        message = db.database.get_message_by_name(codec.name)
        for k in range(30):
            values = random_values(codec, rng)
            counter = k % 16
            frame = codec.encode(values, counter)
            assert len(frame) == codec.dlc
            ref = message.encode({"CRC": frame[0], "AliveCounter": counter, **dict(zip(codec.signals, values))},
                                 scaling=True, strict=True)
            assert frame == ref, f"{codec.name} {values}"
            assert frame[0] == Crc8SaeJ1850.calc(bytes([codec.data_id]) + frame[1:])
            decoded = message.decode(frame, decode_choices=False)
            assert codec.decode(frame) == tuple(decoded[s] for s in codec.signals)
            assert codec.counter_of(frame) == counter and codec.crc_ok(frame)


def test_quantisation_error_is_at_most_half_an_lsb(db) -> None:
    rng = random.Random(3)
    for codec in (db.reference, db.reference_aux, db.sensor(2), db.agent_aux(7), db.traction_cmd(9)):
        lsb = [scale_of(db, codec, s) for s in codec.signals]
        for _ in range(500):
            values = random_values(codec, rng)
            decoded = codec.decode(codec.encode(values, 0))
            for v, d, q in zip(values, decoded, lsb):
                assert abs(d - v) <= q / 2 * (1 + 1e-9) + 1e-12 * abs(v)


def test_saturation_at_both_ends_is_counted_and_never_wraps(fresh_db) -> None:
    state = fresh_db.agent_state(1)
    assert state.decode(state.encode([2e6, 200.0], 0)) == (1073741.823, 262143 * 0.0005)
    assert state.decode(state.encode([-5.0, -200.0], 1)) == (0.0, -131.072)
    assert state.decode(state.encode([math.inf, -math.inf], 2)) == (1073741.823, -131.072)
    assert state.saturations == {"Position": 3, "Speed": 3}
    cmd = fresh_db.traction_cmd(0)
    assert cmd.decode(cmd.encode([3, 6e6], 0)) == (2.0, 5242870.0)  # Mode 3 is outside the DBC range [0, 2]
    assert cmd.decode(cmd.encode([-1, -6e6], 1)) == (0.0, -5242880.0)
    assert fresh_db.total_saturations() == {
        "AgentState_U02.Position": 3, "AgentState_U02.Speed": 3, "TractionCmd_U01.Mode": 2, "TractionCmd_U01.Force": 2,
    }
    fresh_db.reset_saturations()
    assert fresh_db.total_saturations() == {}


def test_within_half_lsb_of_the_extreme_is_quantisation_not_saturation(fresh_db) -> None:
    aux = fresh_db.reference_aux
    assert aux.decode(aux.encode([524.2874], 0)) == (524.287,)
    assert aux.decode(aux.encode([-524.2884], 0)) == (-524.288,)
    assert aux.saturations == {"Accel": 0}
    assert aux.decode(aux.encode([524.2886], 0)) == (524.287,)
    assert aux.saturations == {"Accel": 1}


def test_nan_raises_naming_message_and_signal(db) -> None:
    with pytest.raises(ValueError, match=r"AgentAux_U03\.Force.*NaN"):
        db.agent_aux(2).encode([0.1, float("nan")], 0)


def test_bad_arguments_raise(db) -> None:
    codec = db.sensor(0)
    frame = codec.encode([10.0, 1.0], 0)
    for bad in (frame[:7], frame + b"\x00"):
        for method in (codec.decode, codec.counter_of, codec.crc_ok):
            with pytest.raises(ValueError, match="Sensor_U01.*DLC is 8"):
                method(bad)
    with pytest.raises(ValueError, match="Sensor_U01.*counter 16"):
        codec.encode([10.0, 1.0], 16)
    with pytest.raises(ValueError, match="Sensor_U01.*got 1"):
        codec.encode([10.0], 0)


def test_numpy_inputs_encode_like_floats(db) -> None:
    codec = db.agent_aux(0)
    assert codec.encode(np.array([0.25, -1234.0]), np.int64(4)) == codec.encode([0.25, -1234.0], 4)


def test_crc_detects_every_single_bit_flip_in_every_message(db) -> None:
    rng = random.Random(11)
    for codec in db.by_name.values():
        frame = codec.encode(random_values(codec, rng), rng.randrange(16))
        for bit in range(8 * codec.dlc):
            flipped = bytearray(frame)
            flipped[bit // 8] ^= 1 << (bit % 8)
            assert not codec.crc_ok(flipped), f"{codec.name} bit {bit}"


def test_e2e_through_the_radio_gateway(db) -> None:
    state = db.agent_state(3).encode([4321.5, 80.0], 9)
    aux = db.agent_aux(3).encode([-0.2, 15000.0], 9)
    assert db.radio_ahead_state.crc_ok(state) and db.radio_behind_state.crc_ok(state)
    assert db.radio_ahead_aux.crc_ok(aux) and db.radio_behind_aux.crc_ok(aux)
    assert db.radio_ahead_state.decode(state) == (4321.5, 80.0)
    assert not db.sensor(3).crc_ok(state)  # same layout, other data ID: a mis-routed frame is caught


# --- DBC mismatch: corrupted copies of the committed DBC ----------------------------------------

def corrupt(text: str, kind: str) -> str:
    """Break the DBC in one way; the edit must hit (the test asserts it changed the text)."""
    header = "BO_ 292 AgentAux_U05: 7 ECU_U05\n"  # 0x124
    if kind == "no_crc":
        return re.sub(re.escape(header) + r" SG_ CRC [^\n]*\n", header, text)
    if kind == "counter_3_bits":
        return re.sub(r"(BO_ 292 AgentAux_U05:[^\n]*\n[^\n]*\n SG_ AliveCounter : 8\|)4", r"\g<1>3", text)
    if kind == "no_data_id":
        return text.replace('BA_ "E2EDataID" BO_ 292 6;\n', "")
    if kind == "renamed_signal":
        return re.sub(r"(BO_ 292 AgentAux_U05:[^\n]*(?:\n SG_[^\n]*)*?\n SG_ )Force ", r"\1Thrust ", text).replace(
            "CM_ SG_ 292 Force ", "CM_ SG_ 292 Thrust ")
    if kind == "missing_message":
        text = re.sub(re.escape(header) + r"(?: SG_[^\n]*\n)+", "", text)
        return "\n".join(line for line in text.split("\n") if " 292 " not in line)
    raise AssertionError(kind)


@pytest.mark.parametrize(("kind", "message"), [
    ("no_crc", "message AgentAux_U05: E2E signal CRC is missing"),
    ("counter_3_bits", "message AgentAux_U05: AliveCounter must be unsigned Intel at bit 8, 4 bits"),
    ("no_data_id", "message AgentAux_U05: no E2EDataID"),
    ("renamed_signal", "message AgentAux_U05: payload signals"),
    ("missing_message", "missing message.*AgentAux_U05"),
])
def test_dbc_mismatch_is_a_clear_error(tmp_path, kind, message) -> None:
    text = REPO_DBC.read_text()
    broken = corrupt(text, kind)
    assert broken != text
    path = tmp_path / "broken.dbc"
    path.write_text(broken)
    with pytest.raises(ValueError, match=re.escape(str(path)) + ".*" + message):
        TrainDb.load(path)
    with pytest.raises(DbcMismatchError):
        TrainDb.load(path)


def test_missing_file_names_it(tmp_path) -> None:
    with pytest.raises(FileNotFoundError, match="nope.dbc"):
        TrainDb.load(tmp_path / "nope.dbc")


@pytest.fixture()
def parses(monkeypatch) -> list[tuple]:
    """cantools' parses of a DBC from now on (their arguments), with nothing parsed yet in this process."""
    seen: list[tuple] = []
    parse = codec_mod.cantools.database.load_string
    monkeypatch.setattr(codec_mod, "_PARSED", {})
    monkeypatch.setattr(codec_mod.cantools.database, "load_string", lambda *a, **k: seen.append(a) or parse(*a, **k))
    return seen


def test_a_dbc_is_parsed_once_per_content_and_each_load_counts_its_own_saturations(tmp_path, parses) -> None:
    path, copy = tmp_path / "train.dbc", tmp_path / "copy" / "train.dbc"
    path.write_text(REPO_DBC.read_text())
    copy.parent.mkdir()
    copy.write_text(REPO_DBC.read_text())
    first, second = TrainDb.load(path), TrainDb.load(copy)
    assert len(parses) == 1 and second.database is first.database and second.path == copy
    first.traction_cmd(0).encode((0, 1e12), 1)  # saturates the force in the first load's codec only
    assert first.total_saturations() == {"TractionCmd_U01.Force": 1} and second.total_saturations() == {}
    path.write_text(REPO_DBC.read_text().replace('CM_ BO_ ', 'CM_ BO_  ', 1))  # the same model, other bytes
    third = TrainDb.load(path)
    assert len(parses) == 2 and third.database is not first.database
    path.write_text(corrupt(REPO_DBC.read_text(), "no_crc"))  # and an edit the cached model must not hide
    with pytest.raises(DbcMismatchError, match="E2E signal CRC is missing"):
        TrainDb.load(path)


def test_a_dbc_saved_anew_during_a_load_is_loaded_as_read_and_parsed_again_at_the_next(tmp_path, monkeypatch,
                                                                                       parses) -> None:
    good = REPO_DBC.read_text()
    path = tmp_path / "train.dbc"
    path.write_text(good)
    read_bytes = Path.read_bytes

    def read_then_saved_anew(self: Path) -> bytes:
        content = read_bytes(self)
        if self == path:
            path.write_text(corrupt(good, "no_crc"))  # between the read of the content and its parse
        return content

    monkeypatch.setattr(Path, "read_bytes", read_then_saved_anew)
    assert TrainDb.load(path).max_units > 0  # the content it read, not the file's new one
    monkeypatch.setattr(Path, "read_bytes", read_bytes)
    with pytest.raises(DbcMismatchError, match="E2E signal CRC is missing"):
        TrainDb.load(path)  # the new content is parsed, not the first one's model taken for it
    assert len(parses) == 2


def test_a_dbc_is_read_as_cantools_reads_the_file(tmp_path, parses) -> None:
    """cp1252 text and CRLF line ends, as cantools' ``load_file`` opens a .dbc."""
    path = tmp_path / "train.dbc"
    text = REPO_DBC.read_text().replace("Wayside/ATO node", "Wayside/ATO node \u00e9", 1)
    path.write_bytes(text.replace("\n", "\r\n").encode("cp1252"))
    assert TrainDb.load(path).database.get_node_by_name("Wayside").comment.startswith("Wayside/ATO node \u00e9:")


def test_a_dbc_load_never_goes_through_cantools_disk_cache(tmp_path, monkeypatch, parses) -> None:
    """``CANTOOLS_CACHE_DIR`` turns on cantools' pickled cache, which whoever can write to that folder could fill."""
    cache = tmp_path / "cache"
    monkeypatch.setenv("CANTOOLS_CACHE_DIR", str(cache))
    path = tmp_path / "train.dbc"
    path.write_text(REPO_DBC.read_text())
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # cantools warns that the cache needs diskcache, where it is not installed
        TrainDb.load(path)
    assert len(parses) == 1 and not cache.exists()


def test_threads_loading_one_dbc_at_once_share_one_parse(tmp_path, parses) -> None:
    path = tmp_path / "train.dbc"
    path.write_text(REPO_DBC.read_text())
    with ThreadPoolExecutor(8) as pool:  # a sweep's threads, each building its rig
        loaded = list(pool.map(lambda _: TrainDb.load(path), range(8)))
    assert len(parses) == 1 and all(db.database is loaded[0].database for db in loaded)
    assert len({id(db.by_name["TractionCmd_U01"]) for db in loaded}) == 8  # each load's own codecs
