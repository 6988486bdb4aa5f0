"""The device-under-test slot: a real-time run with one external unit, driven by the reference external ECU in
examples/ (python-can, cantools and the DBC only), as a user would start the two; and a unit that never joins."""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from tests.rrd_reader import read_scalars, read_text_rows

ROOT = Path(__file__).resolve().parents[1]
CRUISE = ROOT / "examples" / "cruise.toml"
EXAMPLE = ROOT / "examples" / "external_ecu.py"
DURATION_S = 6.0
JOIN_BY_S = 1.0  # the external unit's first command, simulated s (it starts beside the rig's nodes)


def start_rig(tmp_path: Path, run: str, *extra: str) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "hil.cli", "run", str(CRUISE), "--realtime", "--run", run,
                             "--duration", str(DURATION_S), "--ecus-per-process", "3", "--quiet",
                             "--out", str(tmp_path / "r"), *extra],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=tmp_path)


def read_channels(rig: subprocess.Popen, n: int) -> dict[str, str]:
    """The ``channel bus=... channel=...`` lines the rig prints on stdout before its nodes start."""
    found = {}
    for line in rig.stdout:
        if line.startswith("channel "):
            fields = dict(kv.split("=", 1) for kv in line.split()[1:])
            assert fields["interface"] == "trainhil"
            found[fields["bus"]] = fields["channel"]
            if len(found) == n:
                return found
    raise AssertionError(f"the rig printed no channels; stderr: {rig.stderr.read()}")


PACKED_FD = ("--set", "can.fd=true", "--set", "can.data_bitrate=2000000", "--set", "can.dbc=train_fd.dbc")


@pytest.mark.slow  # about 15 s: node start-up, 6 s of real time, the merge
@pytest.mark.parametrize("bus", ["classical", "packed CAN FD"])
def test_an_external_python_can_ecu_takes_the_place_of_one_unit(tmp_path, bus):
    """Also on a packed CAN FD bus (train_fd.dbc): the example unpacks what it receives and sends its container."""
    run = f"dut{os.getpid()}"
    packed = bus == "packed CAN FD"
    rig = start_rig(tmp_path, run, "--external", "train2/unit3", *(PACKED_FD if packed else ()))
    channels = read_channels(rig, 2)
    assert channels == {"bus1": f"{run}/bus1", "bus2": f"{run}/bus2"}
    dbc = ("--dbc", str(ROOT / "dbc" / "train_fd.dbc")) if packed else ()
    ecu = subprocess.Popen([sys.executable, str(EXAMPLE), "--channel", channels["bus2"], "--unit", "3", *dbc],
                           stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, cwd=tmp_path)
    out, err = rig.communicate(timeout=180)
    ecu_out = ecu.communicate(timeout=30)[0]
    assert rig.returncode == 0, err
    assert ecu.returncode == 0 and "dropped 0 with a bad E2E CRC" in ecu_out, ecu_out
    metrics = json.loads((tmp_path / "r" / "metrics.json").read_text())
    seen = metrics["external_units"]["train2/unit3"]
    # It starts as the rig starts its nodes: on an idle machine it is on the bus before t = 0, on a loaded one its
    # imports can take it a little past; from then on, no gap and one command per Sensor frame.
    joined = seen["joined_s"]
    assert joined < JOIN_BY_S and seen["missing"] == []
    assert seen["commands"] >= 0.95 * (DURATION_S - joined) / 0.01
    assert abs(seen["period_p50_ms"] - 10.0) < 1.0 and 9.5 < seen["period_mean_ms"] < 10.5  # as seen on the bus
    assert seen["period_max_ms"] >= seen["period_p99_ms"] >= seen["period_p50_ms"] and seen["jitter_std_ms"] > 0
    # the plant applied its commands (no fail-safe on that unit once it joined) and the unit tracked the reference
    events = read_text_rows(tmp_path / "r" / "run.rrd", "/events")
    texts = [text for rows in events.values() for _, text, _ in rows]
    assert any(t.startswith("train2/unit3 (external) joined: first valid TractionCmd at t = ") for t in texts), texts
    failsafe = [te for rows in events.values() for te, text, _ in rows
                if text.startswith("train 2 unit 3 ") and "no command for" in text and "fail-safe" in text]
    assert all(te < joined for te in failsafe), (joined, failsafe)  # (only while it was still starting)
    signals = read_scalars(tmp_path / "r" / "run.rrd")
    t, traction = signals["/trains/2/units/3/traction_kn"]
    assert np.all(traction[(t > joined + 0.1) & (t < joined + 1.0)] > 10.0)  # 5 km/h slow at the start: the PI law pulls
    t, err_kmh = signals["/trains/2/units/3/speed_error_kmh"]
    assert err_kmh[0] < -4.0 and abs(err_kmh[-1]) < 1.0  # from 5 km/h slow to within 1 km/h in 6 s
    assert metrics["e2e_latency_p99_s"] is not None


@pytest.mark.slow  # about 8 s
def test_an_external_unit_that_never_joins_stops_the_run_with_its_name(tmp_path):
    rig = start_rig(tmp_path, f"nojoin{os.getpid()}", "--external", "train1/unit2", "--set", "ecu.join_timeout_s=1.0")
    out, err = rig.communicate(timeout=180)
    assert rig.returncode == 1, err
    assert "hil: error: external unit train1/unit2 sent no valid TractionCmd within ecu.join_timeout_s = 1 s of " \
           "the start" in err
    metrics = json.loads((tmp_path / "r" / "metrics.json").read_text())
    assert metrics["error"].startswith("ExternalUnitMissing: external unit train1/unit2")
    assert metrics["sim_time_s"] < DURATION_S and metrics["interrupted"] is True
    assert metrics["external_units"]["train1/unit2"]["commands"] == 0
