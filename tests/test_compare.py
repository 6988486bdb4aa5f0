"""`hil compare`: accumulators checked by hand, the family registry, and the command on short runs."""
from __future__ import annotations

import csv
import json

import numpy as np
import pytest

from hil.cli import main
from hil.compare.report import (
    Column,
    CommandStats,
    Envelope,
    MetricFamily,
    _FAMILIES,
    choose_family,
    load_traces,
    register_family,
)
from hil.scenario import load_scenario


def test_command_stats_total_variation_effort_and_split():
    st = CommandStats(2, split_s=1.0)
    for t, f in ((0.0, 10.0), (0.5, -10.0), (1.0, 30.0), (2.0, 30.0)):
        st.add(0, f, t)
    st.add(1, 5.0, 0.2)
    st.finish(3.0)
    assert st.tv[:, 0].tolist() == [20.0, 40.0]  # |-10 - 10| before 1 s; |30 - -10| + 0 from 1 s on
    assert st.abs_integral[:, 0].tolist() == [10 * 0.5 + 10 * 0.5, 30 * 1.0 + 30 * 1.0]
    assert st.peak[:, 0].tolist() == [10.0, 30.0]
    assert st.abs_integral[:, 1].tolist() == pytest.approx([5.0 * 0.8, 5.0 * 2.0])  # held 0.2 s .. 3 s, split at 1 s
    assert st.count.sum() == 5


def test_envelope_extremes_per_phase():
    pairs = np.array([[0, 1]])
    env = Envelope(2, pairs, np.array([81.0]), split_s=10.0)
    env.add(0.0, np.array([100.0, 19.0]), np.array([1.0, 2.0]), 1.5)
    env.add(10.0, np.array([100.0, 19.2]), np.array([1.4, 1.5]), 1.5)
    assert env.err_min[0].tolist() == [-0.5, 0.5] and env.err_max[1].tolist() == pytest.approx([-0.1, 0.0])
    assert env.adjacent_max[:, 0].tolist() == pytest.approx([1.0, 0.1])
    assert env.spacing_dev_min[:, 0].tolist() == pytest.approx([0.0, -0.2])


def test_family_registry_chooses_by_scenario_and_names_the_choices():
    one_train, three_trains = load_scenario("seed001"), load_scenario("seed000")
    assert choose_family([one_train]).name == "single_train"
    with pytest.raises(ValueError, match="no metric family applies"):
        choose_family([one_train, three_trains])  # one train and three trains: no family judges both
    with pytest.raises(ValueError, match="'single_train' does not apply to seed000"):
        choose_family([one_train, three_trains], "single_train")
    with pytest.raises(ValueError, match="unknown metric family 'nope'"):
        choose_family([one_train], "nope")

    @register_family
    class Dummy(MetricFamily):
        name = "dummy_test_family"
        columns = [Column("x", "x")]

        def applies(self, scenario):
            return True

        def compute(self, run):
            return {"x": 1.0}

    try:
        assert choose_family([three_trains], "dummy_test_family").name == "dummy_test_family"
    finally:
        _FAMILIES.pop("dummy_test_family")


def test_hil_compare_short_runs_table_csv_json_png(tmp_path, capsys):
    out = tmp_path / "cmp"
    rc = main(["compare", "seed001", "seed001-cca", "--duration", "2", "--out", str(out),
               "--set", "recording.period_s=0.01"])
    assert rc == 0
    printed = capsys.readouterr().out
    assert "seed001-cca" in printed and "chattering" in printed
    data = json.loads((out / "compare.json").read_text())
    assert data["family"] == "single_train"
    stsmca, cca = data["runs"]
    assert (stsmca["law"], cca["law"], stsmca["runtime"]) == ("stsmca", "cca", "virtual")
    m = stsmca["metrics"]
    # 2 s is shorter than the 10 s start-up: nothing "after start-up", but the whole-run figures exist
    assert m["speed_err_min_mps"] is None and m["speed_err_worst_mps"] > 0.1
    assert m["tv_total_mn"] > 0 and m["peak_force_kn"] > 10 and m["commands"] == 6 * 400
    assert stsmca["paper"]["paper_band"].startswith("(-0.8")
    rows = list(csv.DictReader((out / "compare.csv").open()))
    assert [r["run"] for r in rows] == ["seed001", "seed001-cca"]
    assert float(rows[1]["tv_total_mn"]) == pytest.approx(cca["metrics"]["tv_total_mn"])
    assert "| seed001-cca | cca | virtual |" in (out / "compare.md").read_text()
    assert (out / "speed_error.png").read_bytes()[:4] == b"\x89PNG"
    traces = load_traces(out / "traces.npz")
    assert [r.label for r in traces] == ["seed001", "seed001-cca"] and traces[0].speed_error.shape == (200, 6)


def test_hil_compare_after_start_up_on_the_ideal_loop(tmp_path, capsys):
    out = tmp_path / "ideal"
    assert main(["compare", "seed001", "--ideal", "--duration", "12", "--out", str(out),
                 "--set", "ecu.cycle_s=0.001"]) == 0
    m = json.loads((out / "compare.json").read_text())["runs"][0]["metrics"]
    assert 2.5 < m["spacing_time_s"] < 4.5  # the 1 ms ideal loop closes the spacing like the paper says
    assert m["speed_err_min_mps"] < 0 < m["speed_err_max_mps"] < 0.01
    assert 80.99 < m["spacing_min_m"] < 81.0 < m["spacing_max_m"] < 81.01


def test_hil_compare_rejects_mixed_kinds_and_bad_duration(tmp_path, capsys):
    assert main(["compare", "seed001", "seed000", "--duration", "1", "--out", str(tmp_path)]) == 2
    assert "no metric family applies" in capsys.readouterr().err
    assert main(["compare", "seed001", "--duration", "-1", "--out", str(tmp_path)]) == 2
    assert main(["compare", "seed001", "--family", "nope", "--duration", "1", "--out", str(tmp_path)]) == 2
    assert "unknown metric family" in capsys.readouterr().err
