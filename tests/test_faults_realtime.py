"""The fault schedule on the real-time rig: the packaged faults, moved early, in a 4 s run at pace 0.5.

An ECU process is killed and restarted, a babbling node and a corruption burst hit the bus servers, the radio
node blacks out a link: every fault is injected, logged and detected, corrupted frames equal rejected ones, and
no process or run directory is left behind (the ``rt`` fixture of test_realtime_rig)."""
from __future__ import annotations

import pytest

from hil.runtime.realtime.orchestrator import run_realtime
from hil.scenario import load_scenario
from hil.session import run_scenario
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
    assert can["corrupted"] == can["rejected"] > 0 and can["undetected"] == 0, can
    rig = [e.text for e in log.events if e.source == "rig"]
    assert any("train2/unit3 killed (SIGKILL)" in t for t in rig)
    assert any("restart asked" in t for t in rig)
    # the new process is a restart, as in virtual time: the ecu_failure verdict (--check fails on it) names it
    failure = res.metrics["safety"]["ecu_failure"]
    assert failure["violated"] and failure["violations"][0]["where"] == "rig", failure
    assert failure["violations"][0]["text"].startswith("ECU process train2/unit3 restarted with a reset controller")
    virtual = run_scenario(sc, tmp_path / "virtual", duration_s=4.0, record=False, progress=False).metrics
    assert virtual["safety"]["ecu_failure"]["count"] == failure["count"] == 1
    # the nodes whose error state the buses report go by virtual time's names: an ECU process's units by unit
    # (ECU_U01, ...; SENDER_NAME), not by the process's connection (ECU_T1_U01x4, ECU_T1_U01x4.1, ...)
    def error_nodes(metrics: dict) -> dict[str, set[str]]:
        return {bus: set(d["nodes"]) for bus, d in metrics["faults"]["can_errors"]["buses"].items()}

    assert error_nodes(res.metrics) == error_nodes(virtual) and "ECU_U02" in error_nodes(virtual)["bus1"]
    assert log.radio_stats["1>2"].get("fault", 0) > 0
    assert res.metrics["safety"]["collision"]["violated"] is False
    assert not res.metrics["interrupted"] and res.metrics["sim_time_s"] == pytest.approx(4.0)
    # the babbler is put on its bus at the wall clock's now, while the server's bus may still run events before
    # it: its frames wait from then on, never a negative wait (it wrapped to 1.8e10 s in a 45 s run)
    assert 0 < res.metrics["frame_latency_max_s"] < 4.0 and 0 < res.metrics["latency_to_period_max"] < 400


FAILS_ONCE = '''
from ecu_sim.controllers.consensus import OrdinaryConsensus

FAILED = []


class FailsOnce(OrdinaryConsensus):
    """Consensus that raises once per process, in its first cycle after t = 1 s."""

    def step(self, view):
        if view.t >= 1.0 and not FAILED:
            FAILED.append(view.t)
            raise RuntimeError("lookup table out of range")
        return super().step(view)
'''


def test_the_watchdog_restarts_a_crashed_process_and_a_controller_error_in_real_time(rt, tmp_path, monkeypatch):  # noqa: F811
    """One policy (hil.faults.watchdog) in both places: the orchestrator restarts a crash without a duration (a new
    process), the ECU process restarts the unit its controller stopped (in place)."""
    (tmp_path / "failsonce.py").write_text(FAILS_ONCE)
    monkeypatch.chdir(tmp_path)
    sc = load_scenario("faults", overrides={
        "faults": [{"kind": "ecu_crash", "train": 2, "unit": 3, "at_s": 0.5}],
        "ecu": {"restart_after_s": 0.4, "units": [{"unit": "train1/unit2", "law": "failsonce:FailsOnce"}]}})
    res = run_realtime(sc, tmp_path / "rt", pace=1.0, duration_s=3.0, ecus_per_process=4)
    rig = [e.text for e in res.log.events if e.source == "rig"]
    assert any("train2/unit3: restart asked (watchdog, after a crash)" in t for t in rig), rig
    ecu = [e for e in res.log.events if e.source == "train1/unit2/ecu"]
    restarted = [e.t for e in ecu if "restarted with a reset controller (watchdog, after a controller error)" in e.text]
    assert len(restarted) == 1 and 1.4 <= restarted[0] < 2.0, [(e.t, e.text) for e in ecu]  # 0.4 s after the error
    assert res.metrics["faults"]["injected"] == 1


def test_an_injected_hang_longer_than_the_hang_watch_is_left_to_the_fault_machinery(rt, tmp_path):  # noqa: F811
    """An ``ecu_hang`` (SIGSTOP) outlasting the orchestrator's hang watch (2 s of silence) is the fault's own: it
    continues at its end, no reset and no "hung" kill, while a process whose law never returns is killed
    (test_careless_use)."""
    sc = load_scenario("faults", overrides={"ecu": {"restart_after_s": None},  # no watchdog: the hang runs out
                                            "faults": [{"kind": "ecu_hang", "train": 1, "unit": 2, "at_s": 0.5,
                                                        "duration_s": 3.0}]})
    res = run_realtime(sc, tmp_path / "rt", pace=1.0, duration_s=4.5, ecus_per_process=4)
    rig = [(e.t, e.text) for e in res.log.events if e.source == "rig"]
    assert any("stopped (SIGSTOP): hang" in t for _, t in rig), rig
    resumed = [t for t, text in rig if "continued (SIGCONT): the hang is over" in text]
    assert len(resumed) == 1 and resumed[0] == pytest.approx(3.5, abs=0.2), rig
    assert not any("hung:" in t or "killed" in t for _, t in rig), rig
    assert res.metrics["faults"]["injected"] == 1
