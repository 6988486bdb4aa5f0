"""The device-under-test slot: a real-time run with one external unit, driven by the reference external ECU in
examples/ (python-can, cantools and the DBC only), as a user would start the two; and a unit that never joins."""
from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from tests.rrd_reader import read_scalars, read_text_rows

ROOT = Path(__file__).resolve().parents[1]
CRUISE = ROOT / "examples" / "cruise.toml"
EXAMPLE = ROOT / "examples" / "external_ecu.py"
DURATION_S = 6.0
FAILSAFE_HOLD_S = 0.1  # plant.failsafe.hold_s (cruise.toml keeps the default): a unit silent longer is braked


def start_rig(tmp_path: Path, run: str, *extra: str, quiet: bool = True) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "hil", "run", str(CRUISE), "--realtime", "--run", run,
                             "--duration", str(DURATION_S), "--ecus-per-process", "3", *(("--quiet",) if quiet else ()),
                             "--out", str(tmp_path / "r"), *extra],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=tmp_path)


def start_example(tmp_path: Path, channel: str, *extra: str) -> subprocess.Popen:
    """The reference external ECU as unit 3 of ``channel``'s train."""
    return subprocess.Popen([sys.executable, str(EXAMPLE), "--channel", channel, "--unit", "3", *extra],
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, cwd=tmp_path)


def failsafe_events(events: dict, unit: str) -> list[float]:
    """When the plant's fail-safe took over ``unit`` ("train 2 unit 3 "): no command for longer than its hold."""
    return [te for rows in events.values() for te, text, _ in rows
            if text.startswith(unit) and "no command for" in text and "fail-safe" in text]


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
    ecu = start_example(tmp_path, channels["bus2"], *dbc)
    out, err = rig.communicate(timeout=180)
    ecu_out = ecu.communicate(timeout=30)[0]
    assert rig.returncode == 0, err
    assert ecu.returncode == 0 and "dropped 0 with a bad E2E CRC" in ecu_out, ecu_out
    metrics = json.loads((tmp_path / "r" / "metrics.json").read_text())
    seen = metrics["external_units"]["train2/unit3"]
    # The rig's clock waited for its connection: it answers the first Sensor frames, before the plant's fail-safe
    # hold (0.1 s) runs out; from then on, no gap and one command per Sensor frame.
    joined = seen["joined_s"]
    assert joined < FAILSAFE_HOLD_S and seen["missing"] == []
    assert seen["commands"] >= 0.95 * (DURATION_S - joined) / 0.01
    assert abs(seen["period_p50_ms"] - 10.0) < 1.0 and 9.5 < seen["period_mean_ms"] < 10.5  # as seen on the bus
    assert seen["period_max_ms"] >= seen["period_p99_ms"] >= seen["period_p50_ms"] and seen["jitter_std_ms"] > 0
    # the plant applied its commands (no fail-safe on that unit once it joined) and the unit tracked the reference
    events = read_text_rows(tmp_path / "r" / "run.rrd", "/events")
    texts = [text for rows in events.values() for _, text, _ in rows]
    assert any(t.startswith("train2/unit3 (external) joined: first valid TractionCmd at t = ") for t in texts), texts
    assert failsafe_events(events, "train 2 unit 3 ") == []
    signals = read_scalars(tmp_path / "r" / "run.rrd")
    t, traction = signals["/trains/2/units/3/traction_kn"]
    assert np.all(traction[(t > joined + 0.1) & (t < joined + 1.0)] > 10.0)  # 5 km/h slow at the start: the PI law pulls
    t, err_kmh = signals["/trains/2/units/3/speed_error_kmh"]
    assert err_kmh[0] < -4.0 and abs(err_kmh[-1]) < 1.0  # from 5 km/h slow to within 1 km/h in 6 s
    assert metrics["e2e_latency_p99_s"] is not None


@pytest.mark.slow  # about 15 s
def test_the_clock_waits_for_a_device_started_after_the_rig_is_ready(tmp_path):
    """Simulated t = 0 waits for a client on the external unit's bus: a device started a second after the rig said
    it was ready and waiting joins at the first Sensor frames, and the plant's fail-safe never takes its unit."""
    run = f"late{os.getpid()}"
    rig = start_rig(tmp_path, run, "--external", "train2/unit3", quiet=False)
    for line in rig.stderr:
        if "simulated t = 0 waits up to" in line:
            assert "for a client on bus2 (the external unit(s))" in line, line
            break
    else:
        raise AssertionError(f"the rig never said it waits for the external unit: {rig.communicate(timeout=60)}")
    time.sleep(1.0)
    started = time.time()
    ecu = start_example(tmp_path, f"{run}/bus2")
    out, err = rig.communicate(timeout=180)
    ecu_out = ecu.communicate(timeout=30)[0]
    assert rig.returncode == 0, err
    assert ecu.returncode == 0, ecu_out
    t0 = json.loads((tmp_path / "r" / "nodes" / "run.json").read_text())["t0"]
    assert t0 > started  # the clock started after the device
    seen = json.loads((tmp_path / "r" / "metrics.json").read_text())["external_units"]["train2/unit3"]
    assert seen["joined_s"] < FAILSAFE_HOLD_S and seen["missing"] == []
    assert failsafe_events(read_text_rows(tmp_path / "r" / "run.rrd", "/events"), "train 2 unit 3 ") == []


@pytest.mark.slow  # about 8 s
def test_an_external_unit_that_never_joins_stops_the_run_with_its_name(tmp_path):
    rig = start_rig(tmp_path, f"nojoin{os.getpid()}", "--external", "train1/unit2", "--set", "ecu.join_timeout_s=1.0")
    out, err = rig.communicate(timeout=180)
    assert rig.returncode == 1, err
    assert "hil: error: external unit train1/unit2 sent no valid TractionCmd within ecu.join_timeout_s = 1 s of " \
           "the rig being ready" in err
    metrics = json.loads((tmp_path / "r" / "metrics.json").read_text())
    assert metrics["error"].startswith("ExternalUnitMissing: external unit train1/unit2")
    assert metrics["sim_time_s"] < DURATION_S and metrics["interrupted"] is True
    assert metrics["external_units"]["train1/unit2"]["commands"] == 0
