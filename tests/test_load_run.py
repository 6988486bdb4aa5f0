"""hil.record.load_run: the public reader gives back what the run wrote, by entity path, with events and metrics."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from hil.record import load_run
from hil.scenario import load_scenario
from hil.session import run_scenario

ROOT = Path(__file__).resolve().parents[1]


def test_load_run_reads_series_events_and_metrics_back(tmp_path):
    sc = load_scenario(ROOT / "examples" / "cruise.toml",  # a crash gives fault, plant and safety events
                       {"faults": [{"kind": "ecu_crash", "train": 2, "unit": 1, "at_s": 0.5}]})
    result = run_scenario(sc, tmp_path, duration_s=2.0)
    run = load_run(tmp_path)
    t, v = run["/trains/2/units/1/speed_kmh"]
    np.testing.assert_allclose(t, result.log.t, atol=1e-9)
    np.testing.assert_allclose(v, result.log.v[:, 3] * 3.6)
    loads = [run[f"/buses/bus{i}/load"].v.max() for i in (1, 2)]
    assert max(loads) == pytest.approx(result.metrics["bus_load_max"], rel=1e-9)
    def rows(events):
        return sorted((round(e.t, 6), e.level, e.source, e.text) for e in events)

    assert len(run.events) > 3 and rows(run.events) == rows(result.log.events)
    assert [e.t for e in run.events] == sorted(e.t for e in run.events)
    assert run.metrics == json.loads((tmp_path / "metrics.json").read_text())
    assert load_run(tmp_path / "run.rrd").series.keys() == run.series.keys()
    with pytest.raises(KeyError, match=r"no series .*e\.g\. /reference/speed_kmh, /trains/1/units/1/speed_kmh"):
        run["/trains/9/units/1/speed_kmh"]
    with pytest.raises(FileNotFoundError, match="no recording"):
        load_run(tmp_path / "nothing")
