"""The fault schedule on the real-time rig: the packaged faults, moved early, in a 4 s run at pace 0.5.

An ECU process is killed and restarted, a babbling node and a corruption burst hit the bus servers, the radio
node blacks out a link: every fault is injected, logged and detected, corrupted frames equal rejected ones, and
no process or run directory is left behind (the ``rt`` fixture of test_realtime_rig)."""
from __future__ import annotations

import pytest

from hil.runtime.realtime.orchestrator import run_realtime
from hil.scenario import load_scenario
from tests.test_realtime_rig import rt  # noqa: F401  (fixture)

PACE = 0.5


def early_faults():
    return [
        {"kind": "ecu_crash", "train": 2, "unit": 3, "at_s": 0.5, "duration_s": 0.5},
        {"kind": "bus_corruption", "train": 1, "at_s": 1.0, "duration_s": 0.1, "bits": 2},
        {"kind": "babbling_node", "train": 3, "at_s": 1.5, "duration_s": 0.5},
        {"kind": "radio_blackout", "pair": 1, "at_s": 2.5, "duration_s": 1.0},
    ]


def test_faults_in_real_time(rt, tmp_path):  # noqa: F811
    sc = load_scenario("faults", overrides={"faults": early_faults()})
    res = run_realtime(sc, tmp_path / "rt", pace=PACE, duration_s=4.0, ecus_per_process=4)
    f, log = res.metrics["faults"], res.log
    assert f["injected"] == 4 and f["detected"] == 4, f["faults"]
    rows = {r["kind"]: r for r in f["faults"]}
    assert rows["ecu_crash"]["detected_by"] in ("plant", "train2/unit2/ecu", "train2/unit4/ecu")
    assert rows["bus_corruption"]["detected_by"] == "bus1/can"
    assert "bus3/guardian" in rows["babbling_node"]["detectors"]
    can = f["can_errors"]
    assert can["corrupted"] == can["rejected"] > 0 and can["undetected"] == 0
    rig = [e.text for e in log.events if e.source == "rig"]
    assert any("train2/unit3 killed (SIGKILL)" in t for t in rig)
    assert any("restart asked" in t for t in rig)
    assert log.radio_stats["1>2"].get("fault", 0) > 0
    assert res.metrics["safety"]["collision"]["violated"] is False
    assert not res.metrics["interrupted"] and res.metrics["sim_time_s"] == pytest.approx(4.0)
