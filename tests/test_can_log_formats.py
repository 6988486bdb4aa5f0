"""CAN logs in ASC, BLF and MF4, in both runtimes: python-can reads each back with the same frames,
cantools decodes the BLF with the DBC, and bus N is channel N in the ASC/BLF files (channel N-1 read back by
python-can) in the rig's logs and in python -m can.logger's."""
from __future__ import annotations

import subprocess
import sys
import time
from pathlib import Path

import can
import cantools
import pytest

from hil.record.canlog import CanLogUnavailable, log_format
from hil.scenario import load_scenario
from hil.session import run_scenario

ROOT = Path(__file__).resolve().parents[1]
CRUISE = ROOT / "examples" / "cruise.toml"
READERS = {"asc": can.ASCReader, "blf": can.BLFReader, "mf4": can.MF4Reader}


def frames(path: Path) -> list[tuple[float, int, bytes, object]]:
    return [(round(m.timestamp, 6), m.arbitration_id, bytes(m.data), m.channel) for m in READERS[path.suffix[1:]](path)
            if not m.is_error_frame]


@pytest.fixture(scope="module")
def logs(tmp_path_factory):
    """0.5 s of the cruise scenario (2 buses) in virtual time, logged in each format."""
    sc = load_scenario(CRUISE)
    out = {}
    for fmt in ("asc", "blf", "mf4"):
        d = tmp_path_factory.mktemp(fmt)
        run_scenario(sc, d, duration_s=0.5, can_log=fmt, record=False)
        out[fmt] = d
    return out


def test_every_format_reads_back_with_the_same_frames(logs):
    asc = frames(logs["asc"] / "bus2.asc")
    assert len(asc) > 500 and {c for *_, c in asc} == {1}  # bus2: channel index 1
    for fmt in ("blf", "mf4"):
        other = frames(logs[fmt] / f"bus2.{fmt}")
        assert [f[1:3] for f in other] == [f[1:3] for f in asc], fmt
        assert [f[0] for f in other] == pytest.approx([f[0] for f in asc], abs=2e-6), fmt
        assert {c for *_, c in other} == {1}, fmt


def test_the_hil_command_writes_mf4_though_it_starts_without_asammdf(logs, tmp_path):
    """``hil`` imports python-can with its MF4 support deferred (hil/deferred_mf4.py); ``--can-log mf4`` loads it,
    and the log has the frames of the same run made in this process, where python-can was imported as usual."""
    pytest.importorskip("asammdf")
    proc = subprocess.run([sys.executable, "-m", "hil", "run", str(CRUISE), "--duration", "0.5", "--can-log", "mf4",
                           "--no-record", "--quiet", "--out", str(tmp_path)], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    assert frames(tmp_path / "bus2.mf4") == frames(logs["mf4"] / "bus2.mf4")


def test_cantools_decodes_the_blf_log_with_the_dbc(logs):
    db = cantools.database.load_file(ROOT / "dbc" / "train.dbc")
    decoded = [db.decode_message(m.arbitration_id, m.data) for m in can.BLFReader(logs["blf"] / "bus1.blf")
               if m.arbitration_id == db.get_message_by_name("Sensor_U01").frame_id]
    assert len(decoded) == 50 and all(200 / 3.6 - 2 < d["Speed"] < 200 / 3.6 + 1 for d in decoded)


def test_bus_n_is_channel_n_in_the_asc_file(logs):
    text = (logs["asc"] / "bus2.asc").read_text()
    rows = [line.split() for line in text.splitlines() if " Rx " in line]  # "<time> <channel> <id> Rx d <dlc> ..."
    assert len(rows) > 500 and {r[1] for r in rows} == {"2"}


def test_unknown_or_unavailable_formats_are_named():
    with pytest.raises(CanLogUnavailable, match="choose one of asc, blf, mf4"):
        log_format("pcap")
    assert log_format(True) == "asc" and log_format(None) is None


@pytest.mark.slow  # about 12 s: a 2 s real-time run in BLF, and can.logger beside it
def test_real_time_logs_agree_with_can_logger_on_channel_numbers(tmp_path):
    rig = subprocess.Popen([sys.executable, "-m", "hil", "run", str(CRUISE), "--realtime", "--duration", "2",
                            "--ecus-per-process", "3", "--quiet", "--no-record", "--can-log", "blf", "--run",
                            f"logs{id(tmp_path) % 10**6}", "--out", str(tmp_path / "r")],
                           stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    channel = None
    for line in rig.stdout:
        if line.startswith("channel bus=bus1 "):
            channel = line.split("channel=")[-1].strip()
            break
    logger = subprocess.Popen([sys.executable, "-m", "can.logger", "-i", "trainhil", "-c", channel,
                               "-f", str(tmp_path / "logger.asc")], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    rig.communicate(timeout=120)
    time.sleep(0.5)
    logger.terminate()
    logger.wait(10)
    assert rig.returncode == 0
    ours = {m.channel for m in can.BLFReader(tmp_path / "r" / "bus1.blf")}
    theirs = {m.channel for m in can.ASCReader(tmp_path / "logger.asc")}
    assert ours == theirs == {0}  # bus1: channel 1 in both files, 0 read back
