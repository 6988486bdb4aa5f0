"""The SocketCAN (vcan) option of the real-time rig: configuration only, checked against what the host has.

This machine has no AF_CAN, so the run test skips with that reason; where a host has vcan0..vcan2 up, it runs
seed000-consensus for 2 s on them. The error paths run everywhere."""
from __future__ import annotations

import sys
from pathlib import Path

import pytest

from hil.runtime.realtime.socketcan import SocketCanUnavailable, af_can_available, check_channels
from hil.scenario import ScenarioError, load_scenario

VCANS = ["vcan0", "vcan1", "vcan2"]


def _socketcan_scenario(channels: list[str]):
    return load_scenario("seed000-consensus", {"can.transport": "socketcan", "can.socketcan_channels": channels})


def test_socketcan_transport_needs_its_channels():
    with pytest.raises(ScenarioError, match="socketcan_channels"):
        load_scenario("seed000-consensus", {"can.transport": "socketcan"})
    with pytest.raises(SocketCanUnavailable, match="one per train"):
        check_channels(["vcan0"], 3)


@pytest.mark.skipif(af_can_available(), reason="this host has AF_CAN: the unavailable-host message cannot be shown")
def test_a_host_without_af_can_gets_a_clear_error_from_hil_run(tmp_path):
    import subprocess

    proc = subprocess.run([sys.executable, "-m", "hil", "run", "seed000-consensus", "--realtime", "--duration", "1",
                           "--set", "can.transport=socketcan", "--set", 'can.socketcan_channels=["vcan0","vcan1","vcan2"]',
                           "--out", str(tmp_path), "--quiet"], capture_output=True, text=True, timeout=60)
    assert proc.returncode == 2, proc.stderr
    assert "AF_CAN is unavailable" in proc.stderr and "Traceback" not in proc.stderr


def test_a_virtual_time_run_of_a_socketcan_scenario_says_it_runs_on_the_emulated_buses(tmp_path, capsys):
    from hil.cli import main

    assert main(["run", "seed000-consensus", "--duration", "0.3", "--set", "can.transport=socketcan", "--set",
                 'can.socketcan_channels=["vcan0","vcan1","vcan2"]', "--out", str(tmp_path), "--quiet"]) == 0
    assert ("hil: warning: can.transport = 'socketcan' is for real-time runs (--realtime); this run is in virtual "
            "time, on the rig's emulated buses") in capsys.readouterr().err


def _vcans_up() -> bool:
    try:
        check_channels(VCANS, 3)
    except SocketCanUnavailable:
        return False
    return True


@pytest.mark.skipif(not af_can_available(), reason="no SocketCAN on this host (AF_CAN unavailable: no vcan kernel module)")
@pytest.mark.skipif(af_can_available() and not _vcans_up(), reason="SocketCAN exists but vcan0..vcan2 are not up")
def test_realtime_rig_runs_on_vcan(tmp_path):
    from hil.runtime.realtime.orchestrator import run_realtime

    res = run_realtime(_socketcan_scenario(VCANS), Path(tmp_path), pace=0.5, duration_s=2.0, ecus_per_process=4)
    m = res.metrics
    assert not m["interrupted"] and m["sim_time_s"] == pytest.approx(2.0)
    assert not [e for e in res.log.events if e.level == "ERROR" and e.source != "safety"]
    assert m["e2e_latency_p50_s"] is not None


@pytest.mark.skipif(not af_can_available(), reason="no SocketCAN on this host (AF_CAN unavailable: no vcan kernel module)")
@pytest.mark.skipif(af_can_available() and not _vcans_up(), reason="SocketCAN exists but vcan0..vcan2 are not up")
def test_an_external_ecu_on_socketcan_takes_the_place_of_one_unit(tmp_path):
    """The device-under-test slot on a host interface: the reference external ECU on vcan1 drives train 2's unit 3."""
    import subprocess
    import threading

    from hil.runtime.realtime.orchestrator import run_realtime

    root = Path(__file__).resolve().parents[1]
    sc = load_scenario(root / "examples" / "cruise.toml", {"can.transport": "socketcan", "can.socketcan_channels": VCANS[:2],
                                                           "ecu.external": ["train2/unit3"]})
    ecu: list[subprocess.Popen] = []

    def start_ecu(channels) -> None:
        assert [c.channel for c in channels] == VCANS[:2] and channels[1].interface == "socketcan"
        ecu.append(subprocess.Popen([sys.executable, str(root / "examples" / "external_ecu.py"), "--interface",
                                     "socketcan", "--channel", "vcan1", "--unit", "3", "--duration", "8"]))

    res = run_realtime(sc, Path(tmp_path), duration_s=4.0, ecus_per_process=3, on_channels=start_ecu)
    ecu[0].wait(30)
    seen = res.metrics["external_units"]["train2/unit3"]
    assert seen["joined_s"] is not None and seen["commands"] > 300 and seen["missing"] == []
