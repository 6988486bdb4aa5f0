"""Non-finite values from a controller or from the plant: a clear event, the run degrades or ends cleanly, and the
recording and metrics stay readable.

* A law that returns NaN (or inf) for one unit mid-run: that ECU stops (ERROR event naming the law and the
  value), the plant's fail-safe brakes the unit (its events), every other ECU carries on, the run completes.
* A plant pushed to non-finite state (a 1e200 N disturbance): the run ends at once with an ERROR event naming
  the units, run.rrd and metrics.json (``interrupted``, ``error``) are written, then PlantDiverged is raised;
  ``hil run`` reports it in one line, exit 1, no traceback.
"""
from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from ecu_sim.controllers.base import _REGISTRY, register
from ecu_sim.controllers.consensus import OrdinaryConsensus
from ecu_sim.view import Command, LocalView
from hil.plant import PlantDiverged
from hil.record.integrity import check_run_dir
from hil.scenario import load_scenario
from hil.session import run_scenario
from tests.rrd_reader import read_scalars


class _NonFiniteAfter1s(OrdinaryConsensus):
    """The consensus law, except that train 2's head unit returns a non-finite force from t = 1 s on."""

    name = "test_non_finite_after_1s"
    value = math.nan

    def step(self, view: LocalView) -> Command:
        cmd = super().step(view)
        if self.agent.train == 1 and self.agent.unit == 0 and view.t >= 1.0:
            return Command(self.value, cmd.mode, cmd.accel_mps2)
        return cmd


class _InfAfter1s(_NonFiniteAfter1s):
    name = "test_inf_after_1s"
    value = -math.inf


for law in (_NonFiniteAfter1s, _InfAfter1s):
    if law.name not in _REGISTRY:
        register(law)


@pytest.mark.parametrize("law", ["test_non_finite_after_1s", "test_inf_after_1s"])
def test_a_law_returning_non_finite_force_stops_its_ecu_and_the_run_degrades_cleanly(tmp_path: Path, law: str):
    sc = load_scenario("seed000", {"controller.law": law, "controller.params": {}})
    result = run_scenario(sc, tmp_path, duration_s=4.0)
    events = result.log.events
    failed = [e for e in events if e.level == "ERROR" and "failed" in e.text and "non-finite force" in e.text
              and e.source != "safety"]  # a safety violation quotes the failure as its cause
    assert len(failed) == 1, failed  # only the faulty unit's ECU
    assert failed[0].source == ECU_NAME and "ECU stopped" in failed[0].text and 1.0 <= failed[0].t < 1.1
    plant = [e for e in events if e.source == "plant" and e.t > failed[0].t]
    assert plant, "the plant's fail-safe did not act on the silent unit"
    metrics = json.loads((tmp_path / "metrics.json").read_text())
    assert metrics["interrupted"] is False and metrics["sim_time_s"] == pytest.approx(4.0)
    assert metrics["events_by_level"]["ERROR"] >= 1
    rep = check_run_dir(tmp_path, expect_complete=True)
    assert rep.ok, rep.problems
    v = result.log.v
    assert np.all(np.isfinite(v)) and np.all(np.isfinite(result.log.force_applied))
    t, speed = read_scalars(tmp_path / "run.rrd")["/trains/2/units/1/speed_kmh"]
    assert t[-1] >= 3.9 and np.all(np.isfinite(speed))


ECU_NAME = "train2/unit1/ecu"

DIVERGE = {"plant.disturbances": [{"kind": "step", "train": 2, "unit": 1, "start_s": 2.0, "end_s": 3.0,
                                   "amplitude_n": 1e200}]}


def test_a_diverging_plant_ends_the_run_with_an_event_and_readable_files(tmp_path: Path):
    sc = load_scenario("seed000", DIVERGE)
    with np.errstate(all="ignore"), pytest.raises(PlantDiverged, match=r"plant diverged at t = 2\.0\d* s.*train 2 unit 1"):
        run_scenario(sc, tmp_path, duration_s=5.0)
    metrics = json.loads((tmp_path / "metrics.json").read_text())
    assert metrics["interrupted"] is True and metrics["error"].startswith("PlantDiverged: plant diverged at t = 2.0")
    assert 2.0 <= metrics["sim_time_s"] < 2.1
    assert metrics["events_by_level"]["ERROR"] == 1 + metrics["safety"]["overspeed"]["count"] \
        + sum(metrics["safety"][k]["count"] for k in ("gap_below_le", "collision", "coupler_out_of_band"))
    rep = check_run_dir(tmp_path, expect_complete=False)
    assert rep.ok, rep.problems
    assert 1.9 <= rep.rrd_last_time_s <= metrics["sim_time_s"] + 1e-9
    t, _ = read_scalars(tmp_path / "run.rrd")["/trains/1/units/1/speed_kmh"]
    assert t[-1] >= 1.9  # the samples before the divergence are recorded


def test_hil_run_reports_a_diverging_plant_in_one_line(tmp_path: Path):
    bad = "plant.disturbances=[{kind = 'step', train = 2, unit = 1, start_s = 2.0, end_s = 3.0, amplitude_n = 1e200}]"
    proc = subprocess.run([sys.executable, "-m", "hil", "run", "seed000", "--duration", "3", "--quiet", "--out",
                           str(tmp_path), "--set", bad], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 1, proc.stderr
    assert "hil: error: plant diverged at t = 2.0" in proc.stderr and "Traceback" not in proc.stderr
    assert check_run_dir(tmp_path, expect_complete=False).ok
