"""Fault schedules (hil/faults) in virtual time: each fault does what it says, is logged, and is detected by the
monitor that should see it; the packaged faults scenario end to end. Runs are a few simulated seconds of a small
group (2 trains x 2 units, consensus law) so each test stays well under 20 s."""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from ecu_sim.diagnostics import SensorPlausibility
from hil.runtime.virtual import VirtualRig
from hil.scenario import ScenarioError, load_scenario
from hil.scenario.loader import read_scenario_data, resolve, scenario_from_dict

FAULTS = "faults"


def small(faults: list[dict], duration: float = 6.0, **ecu) -> "Scenario":  # noqa: F821
    """2 trains x 2 units of seed000-consensus, started near their slots, with ``faults``."""
    data = read_scenario_data(resolve("seed000-consensus"))
    data.update(name="small-faults", duration_s=duration, faults=faults)
    data["trains"].update(count=2, units=2, head_positions_m=[109000.0, 105840.0], speeds_kmh=[316.0, 316.0])
    data.setdefault("ecu", {}).update(ecu)
    return scenario_from_dict(data, "small")


def run(sc, duration: float | None = None):
    rig = VirtualRig(sc)
    log = rig.run(duration)
    return rig, log


def events(log, source: str | None = None, text: str = "") -> list:
    """Events of ``source`` whose text starts with ``text``."""
    return [e for e in log.events if (source is None or e.source == source) and e.text.startswith(text)]


def report(log, k: int = 0) -> dict:
    return log.fault_report["faults"][k]


# --------------------------------------------------------------------------- schema


@pytest.mark.parametrize("fault, message", [
    ({"kind": "ecu_crash", "train": 2, "unit": 1}, "exactly one of at_s or at_position_m"),
    ({"kind": "ecu_crash", "train": 3, "unit": 1, "at_s": 1.0}, "faults.0.train = 3"),
    ({"kind": "ecu_crash", "train": 1, "unit": 5, "at_s": 1.0}, "faults.0.unit = 5"),
    ({"kind": "radio_blackout", "pair": 2, "at_s": 1.0}, "faults.0.pair = 2"),
    ({"kind": "bus_corruption", "train": 1, "at_s": 1.0, "probability": 0}, "faults.0.bus_corruption.probability"),
    ({"kind": "sensor_noise", "train": 1, "unit": 1, "at_s": 1.0}, "position_noise_m or speed_noise_mps"),
    ({"kind": "babbling_node", "train": 1, "at_s": 1.0, "frame_id": 0x800}, "faults.0.babbling_node.frame_id"),
    ({"kind": "ecu_explode", "train": 1, "unit": 1, "at_s": 1.0}, "kind must be one of"),
    ({"kind": "ecu_hang", "train": 1, "unit": 1, "at_s": 1.0, "colour": "red"}, "faults.0.ecu_hang.colour"),
])
def test_bad_faults_are_named_errors(fault, message):
    with pytest.raises(ScenarioError, match=message.replace(".", r"\.").replace("(", r"\(")):
        small([fault])


def test_the_packaged_scenario_loads_with_its_four_faults():
    sc = load_scenario(FAULTS)
    assert [f.kind for f in sc.faults] == ["ecu_crash", "babbling_node", "bus_corruption", "radio_blackout"]
    assert sc.ecu.restart_after_s == 1.0


# --------------------------------------------------------------------------- ECUs


def cmd_times(rig, train: int, unit: int) -> np.ndarray:
    """End times of the unit's TractionCmd frames on its bus."""
    frames = rig.log.buses[train - 1].frames.array
    return frames[frames[:, 1] == 0x080 + unit - 1, 0]


def test_crash_and_restart():
    rig, log = run(small([{"kind": "ecu_crash", "train": 2, "unit": 2, "at_s": 2.0, "duration_s": 1.0}]))
    t = cmd_times(rig, 2, 2)
    assert not np.any((t > 2.001) & (t < 3.0))  # silent while down (a frame on the wire at 2.0 may complete)
    assert np.sum(t > 3.0) > 250  # and back after the restart
    assert events(log, "plant", "train 2 unit 2 (#3): no command")
    assert events(log, "train2/unit1/ecu", "neighbour train2/unit2 stale")
    assert events(log, "train2/unit2/ecu", "restarted with a reset controller")
    r = report(log)
    assert r["detected"] and 2.0 < r["detected_s"] < 2.2 and r["end_s"] == pytest.approx(3.0)
    assert log.fault_report["ecu_restarts"] == 1


def test_a_crash_without_duration_is_restarted_by_the_watchdog():
    rig, log = run(small([{"kind": "ecu_crash", "train": 1, "unit": 2, "at_s": 1.0}], restart_after_s=0.5), 3.0)
    t = cmd_times(rig, 1, 2)
    assert not np.any((t > 1.001) & (t < 1.5)) and np.any(t > 1.5)
    assert events(log, "train1/unit2/ecu", "restarted with a reset controller (watchdog")
    rig, log = run(small([{"kind": "ecu_crash", "train": 1, "unit": 2, "at_s": 1.0}]), 3.0)  # no policy: stays down
    assert not np.any(cmd_times(rig, 1, 2) > 1.001)


def test_a_hung_ecu_stays_connected_and_resumes_without_reset():
    rig, log = run(small([{"kind": "ecu_hang", "train": 1, "unit": 1, "at_s": 1.0, "duration_s": 0.5}]), 3.0)
    ecu = rig.ecus[0]
    t = cmd_times(rig, 1, 1)
    assert not np.any((t > 1.001) & (t < 1.5)) and np.any(t > 1.5)
    assert rig.buses[0].attached(rig._ecu_nodes[0])  # never left the bus
    assert events(log, "train1/unit1/ecu", "resumed after the hang")
    assert not events(log, "train1/unit1/ecu", "restarted")
    # it kept receiving while hung: on resuming it met a counter jump, not a fresh stream (50 samples alias to a
    # jump of 2 in the 4-bit alive counter: classified as 1 lost frame per stream, not as a wrong sequence)
    e2e = ecu.e2e_summary()
    assert e2e.get("INITIAL") == len(ecu.slots) and e2e.get("LOST", 0) + e2e.get("WRONG_SEQUENCE", 0) >= 1
    assert report(log)["detected"]


def test_a_watchdog_shorter_than_the_hang_resets_the_ecu():
    rig, log = run(small([{"kind": "ecu_hang", "train": 1, "unit": 1, "at_s": 1.0, "duration_s": 2.0}],
                         restart_after_s=0.3), 3.0)
    assert events(log, "train1/unit1/ecu", "restarted with a reset controller (watchdog, after a hang)")
    assert np.any((cmd_times(rig, 1, 1) > 1.3) & (cmd_times(rig, 1, 1) < 2.0))


def test_a_controller_error_is_restarted_by_the_watchdog():
    sc = small([], restart_after_s=0.2)
    rig = VirtualRig(sc)
    ctrl = rig.ecus[1].controller
    step = ctrl.step

    def failing(view):
        if 1.0 <= view.t < 1.05:
            raise RuntimeError("injected")
        return step(view)

    ctrl.step = failing
    log = rig.run(2.0)
    assert events(log, "train1/unit2/ecu", "controller")
    restarted = events(log, "train1/unit2/ecu", "restarted")
    assert len(restarted) == 1 and restarted[0].t == pytest.approx(1.2, abs=0.02)


# --------------------------------------------------------------------------- sensors


def test_stuck_sensor_is_detected_by_the_firmware_which_brakes():
    rig, log = run(small([{"kind": "sensor_stuck", "train": 2, "unit": 1, "at_s": 2.0, "duration_s": 1.0}]), 5.0)
    found = events(log, "train2/unit1/ecu", "own sensor implausible (stuck")
    assert len(found) == 1 and 2.0 < found[0].t < 2.05
    assert report(log)["detected_by"] == "train2/unit1/ecu"
    state = rig.log.buses[1].frames.array
    own = state[state[:, 1] == 0x100, 0]  # its AgentState: withheld while the sensor is judged implausible
    assert not np.any((own > found[0].t + 0.011) & (own < 3.0))
    cleared = events(log, "train2/unit1/ecu", "cleared: own sensor implausible")
    assert cleared and 3.9 < cleared[0].t < 4.2  # 100 plausible samples after the fault ends


def test_noisy_sensor_detected_when_gross_and_not_when_small():
    _, log = run(small([{"kind": "sensor_noise", "train": 1, "unit": 2, "at_s": 1.0, "duration_s": 1.0,
                         "position_noise_m": 2.0}]), 2.5)
    assert events(log, "train1/unit2/ecu", "own sensor implausible (inconsistent")
    assert report(log)["detected"]
    _, log = run(small([{"kind": "sensor_noise", "train": 1, "unit": 2, "at_s": 1.0, "duration_s": 1.0,
                         "position_noise_m": 0.01}]), 2.5)
    assert not report(log)["detected"]  # 1 cm of noise is plausible: reported as undetected, honestly


def test_sensor_plausibility_on_synthetic_samples():
    dt = 0.01
    p = SensorPlausibility(dt)
    t = np.arange(600) * dt
    x = 100 + 80 * t + 3 * np.sin(7 * t)  # jerk up to 1000 m/s^3
    v = 80 + 21 * np.cos(7 * t)
    assert all(p.update(k % 16, round(xi, 3), round(vi, 4)) is None for k, (xi, vi) in enumerate(zip(x, v)))
    states = [p.update((600 + k) % 16, round(x[-1], 3), round(v[-1], 4)) for k in range(4)]  # frozen
    assert states[:1] == [None] and states[1] == "stuck"
    still = SensorPlausibility(dt)
    assert all(still.update(k % 16, 5.0, 0.0) is None for k in range(50))  # a standing train may repeat


# --------------------------------------------------------------------------- actuators


def test_traction_loss_and_degradation_are_found_by_the_force_balance():
    sc = small([{"kind": "traction_loss", "train": 1, "unit": 2, "at_s": 2.0, "duration_s": 6.0},
                {"kind": "actuator_degradation", "train": 2, "unit": 1, "health": 0.4, "at_s": 2.0, "duration_s": 6.0}],
               11.0)
    rig, log = run(sc)
    during = (log.t > 2.1) & (log.t < 8.0)
    assert np.all(log.force_applied[during, 1] == 0.0) and np.any(log.force_cmd[during, 1] != 0.0)
    assert np.allclose(log.force_applied[during, 2], 0.4 * log.force_cmd[during, 2], rtol=0, atol=1.0)
    ratios = {u: np.array(rig.ecus[u].monitors[0].ratios) for u in range(4)}
    in_fault = {u: r[(r[:, 0] > 4.0) & (r[:, 0] < 8.0), 1] for u, r in ratios.items()}
    assert np.all(np.abs(in_fault[1]) < 0.05) and np.all(np.abs(in_fault[2] - 0.4) < 0.05)
    assert np.all(np.abs(in_fault[0] - 1.0) < 0.05) and np.all(np.abs(in_fault[3] - 1.0) < 0.05)
    for k, source in ((0, "train1/unit2/ecu"), (1, "train2/unit1/ecu")):
        r = report(log, k)
        assert r["detected_by"] == source and 2.0 < r["detection_latency_s"] <= 6.1
    assert events(log, "train1/unit2/ecu", "cleared: traction implausible")
    assert not events(log, "train1/unit1/ecu", "traction") and not events(log, "train2/unit2/ecu", "traction")


# --------------------------------------------------------------------------- radio


def test_radio_blackout_by_time_triggers_the_contact_loss_rule():
    _, log = run(small([{"kind": "radio_blackout", "pair": 1, "at_s": 1.0, "duration_s": 3.0}]), 5.0)
    lost = events(log, "train2/unit1/ecu", "lost contact with the train ahead")
    assert lost and lost[0].t == pytest.approx(1.0 + 2.0, abs=0.05)  # radio_contact_timeout_s = 2
    assert events(log, "plant", "train 2: emergency brake on the train line")
    assert log.radio_stats["1>2"]["fault"] > 0 and log.radio_stats["2>1"]["fault"] > 0
    r = report(log)
    assert r["detected"] and r["detected_s"] < 1.2  # the stale radio neighbour, before the contact timeout


def test_radio_latency_and_burst_loss():
    rig = VirtualRig(small([{"kind": "radio_latency", "at_s": 1.0, "duration_s": 1.0, "latency_s": 0.25},
                            {"kind": "radio_burst_loss", "at_s": 3.0, "duration_s": 1.0, "probability": 1.0}]))
    log = rig.run(4.5)
    frames = log.buses[1].frames.array
    ahead = frames[frames[:, 1] == 0x180, 0]
    gaps = np.diff(ahead)
    assert np.max(gaps[(ahead[1:] > 1.0) & (ahead[1:] < 1.5)]) == pytest.approx(0.26, abs=0.015)  # the jump
    assert not np.any((ahead > 3.01) & (ahead < 4.0))
    assert log.fault_report["faults"][0]["detected"]  # 250 ms > neighbour_timeout_s: the data is stale
    assert log.fault_report["faults"][1]["detected"]


# --------------------------------------------------------------------------- buses


def test_babbling_node_in_the_rig_is_caught_by_the_guardian():
    _, log = run(small([{"kind": "babbling_node", "train": 1, "at_s": 1.0, "duration_s": 0.5}]), 2.5)
    g = events(log, "bus1/guardian", "babbling node: ID 0x000")
    assert len(g) == 1 and g[0].t == pytest.approx(1.1)
    assert not events(log, "bus2/guardian")  # the other bus is quiet, and no burst after the babble reads as one
    assert report(log)["detectors"]["bus1/guardian"] == pytest.approx(0.1)


def test_bus_corruption_in_the_rig_rejected_frames_equal_corrupted_ones():
    _, log = run(small([{"kind": "bus_corruption", "train": 2, "at_s": 1.0, "duration_s": 1.0, "probability": 0.05,
                         "bits": 3}]), 2.5)
    can = log.fault_report["can_errors"]
    assert can["corrupted"] > 20 and can["corrupted"] == can["rejected"] and can["undetected"] == 0
    assert can["buses"]["bus1"]["corrupted"] == 0
    assert report(log)["detected_by"] == "bus2/can"


def test_frame_drop_shows_as_lost_frames_at_the_receivers():
    _, log = run(small([{"kind": "frame_drop", "train": 1, "at_s": 1.0, "duration_s": 1.0, "probability": 0.2,
                         "frame_ids": [0x0C1]}]), 2.5)
    assert log.buses[0].frames_dropped > 10
    assert log.buses[0].dropped_by_node == {"Plant": log.buses[0].frames_dropped}  # the sender of 0x0C1 (Sensor)
    assert log.e2e["train1/unit2/ecu"].get("LOST", 0) > 0
    assert "train1/unit2/ecu" in report(log)["detectors"]


def test_a_position_trigger_fires_when_the_head_passes():
    sc = small([{"kind": "radio_blackout", "pair": 1, "at_position_m": 109000.0 + 88.0 * 1.5, "duration_s": 0.5}], 3.0)
    rig, log = run(sc)
    start = report(log)["start_s"]
    head = log.x[:, 0]
    t_pass = log.t[np.argmax(head >= 109000.0 + 88.0 * 1.5)]
    assert abs(start - t_pass) <= 0.1 + 1e-9  # checked every sensor period, recorded every 0.1 s


def test_runs_without_faults_are_untouched():
    sc = small([])
    rig, log = run(sc, 1.0)
    assert rig.faults is None and rig.net.bus_errors(0) is None and log.fault_report is None  # no error model


# --------------------------------------------------------------------------- the packaged scenario


def test_the_faults_scenario_short_run(tmp_path: Path):
    from hil.session import run_scenario
    from tests.rrd_reader import read_text_rows

    res = run_scenario(load_scenario(FAULTS), tmp_path, duration_s=18.5)  # the tunnel starts at ~17.3 s
    f = res.metrics["faults"]
    assert f["injected"] == f["detected"] == 4
    assert f["can_errors"]["corrupted"] == f["can_errors"]["rejected"] > 0
    rows = read_text_rows(tmp_path / "run.rrd", "/")
    faults_rows = [text for ent, rs in rows.items() if ent.endswith("faults") for _, text, _ in rs]
    for k in range(4):
        assert any(r.startswith(f"#{k} ") and "injected" in r for r in faults_rows)
        assert any(r.startswith(f"#{k} ") and "detected after" in r for r in faults_rows)
    assert any("bus-off" in text for ent, rs in rows.items() if ent.endswith("bus1/can") for _, text, _ in rs)
    safety = res.metrics["safety"]
    assert safety["gap_below_le"]["violated"] is False and safety["collision"]["violated"] is False
    assert all(v["cause"] for v in safety["coupler_out_of_band"]["violations"])
    assert math.isfinite(res.metrics["gap_min_overall_m"])
