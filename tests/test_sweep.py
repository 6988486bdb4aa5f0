"""Sweeps: file validation, grid and ids, runs in a process pool and on Dask, resume after Ctrl-C, failures, CSV."""
from __future__ import annotations

import hashlib
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from hil.scenario import load_scenario, resolve
from hil.session import run_scenario
from hil.sweep import SweepError, load_sweep, packaged_sweeps
from hil.sweep.results import NONDETERMINISTIC, flatten_metrics, load_results
from hil.sweep.runner import MANIFEST, run_sweep
from hil.sweep.spec import canonical_json, sweep_from_dict
from tests.law_views import law_params

SEED000 = load_scenario("seed000")


def write(tmp_path: Path, text: str, name: str = "sweep.toml") -> Path:
    path = tmp_path / name
    path.write_text(text)
    return path


def deterministic(row: dict) -> dict:
    return {k: v for k, v in row.items() if k not in NONDETERMINISTIC}


# --------------------------------------------------------------------------- validation


def test_bad_axis_key_names_file_axis_and_value(tmp_path):
    path = write(tmp_path, 'name = "x"\nbase = "seed000"\n[axes]\n"radio.latncy_s" = [0.1]\n')
    with pytest.raises(SweepError) as err:
        load_sweep(path)
    msg = str(err.value)
    assert msg.startswith(f"{path}: axes.'radio.latncy_s' value 0.1")
    assert "radio.latncy_s: Extra inputs are not permitted" in msg


def test_bad_axis_value_names_the_axis_and_the_value(tmp_path):
    path = write(tmp_path, 'name = "x"\nbase = "seed000"\n[axes]\n"controller.law" = ["finite_time", "consensus"]\n'
                           '"radio.latency_s" = [0.0, -0.5]\n')
    with pytest.raises(SweepError, match=r"axes.'radio.latency_s' value -0.5 gives an invalid scenario") as err:
        load_sweep(path)
    assert "greater than or equal to 0 (got -0.5)" in str(err.value)
    bad_law = write(tmp_path, 'name = "x"\nbase = "seed000"\n[axes]\n"controller.law" = ["finite_time", "nolaw"]\n', "law.toml")
    with pytest.raises(SweepError, match=r"(?s)axes.'controller.law' value 'nolaw'.*unknown controller law 'nolaw'"):
        load_sweep(bad_law)


def test_unknown_base_and_schema_errors_name_the_field(tmp_path):
    with pytest.raises(SweepError, match=r"sweep.toml: base = 'no-such-scenario': unknown scenario"):
        load_sweep(write(tmp_path, 'name = "x"\nbase = "no-such-scenario"\n'))
    with pytest.raises(SweepError, match=r"base = 'missing.toml': .*no such scenario file"):
        load_sweep(write(tmp_path, 'name = "x"\nbase = "missing.toml"\n'))
    with pytest.raises(SweepError, match=r"invalid sweep \(1 error\)\n  duration_s: .*greater than 0 \(got -1\)"):
        load_sweep(write(tmp_path, 'name = "x"\nbase = "seed000"\nduration_s = -1\n'))
    with pytest.raises(SweepError, match=r"axis 'radio' is a table.*quote dotted keys"):  # unquoted dotted key in TOML
        load_sweep(write(tmp_path, 'name = "x"\nbase = "seed000"\n[axes]\nradio.latency_s = [0.1]\n'))
    with pytest.raises(SweepError, match=r"'seed' cannot be set here: use `seeds"):
        load_sweep(write(tmp_path, 'name = "x"\nbase = "seed000"\n[axes]\n"seed" = [1, 2]\n'))
    with pytest.raises(SweepError, match=r"plots.lines.0.hue: 'law' is not an axis column \(axis columns: controller.law\)"):
        load_sweep(write(tmp_path, 'name = "x"\nbase = "seed000"\n[axes]\n"controller.law" = ["consensus"]\n'
                                   '[plots]\nlines = [{ metric = "gap_min_overall_m", x = "controller.law", hue = "law" }]\n'))
    with pytest.raises(SweepError, match=r"plots.heatmaps.0.where.controller.law: 'pid' is not one of its values \['consensus'\]"):
        load_sweep(write(tmp_path, 'name = "x"\nbase = "seed000"\n[axes]\n"controller.law" = ["consensus"]\n"radio.latency_s" = [0.1]\n'
                                   '[plots]\nheatmaps = [{ metric = "m", x = "radio.latency_s", y = "radio.latency_s", '
                                   'where = { "controller.law" = "pid" } }]\n'))


def test_base_path_is_relative_to_the_sweep_file(tmp_path):
    sub = tmp_path / "studies"
    sub.mkdir()
    (sub / "mine.toml").write_text(resolve("seed000").read_text().replace('name = "seed000"', 'name = "mine"'))
    spec = load_sweep(write(sub, 'name = "x"\nbase = "mine.toml"\n'))
    assert spec.base_path == sub / "mine.toml" and spec.points[0].scenario.name == "mine"


# --------------------------------------------------------------------------- grid and ids


GRID = '''name = "grid"
base = "seed000"
duration_s = 5
seeds = [3, 4]
[overrides]
"radio.jitter_s" = 0.001
[axes]
"radio.latency_s" = [0.0, 0.1, 0.5]
"radio.loss" = [{ model = "bernoulli", p = 0.2 }, { model = "gilbert_elliott", p_good_to_bad = 0.01 }]
'''


def test_grid_is_the_cartesian_product_times_seeds_with_stable_ids(tmp_path):
    spec = load_sweep(write(tmp_path, GRID))
    pts = spec.points
    assert len(pts) == 3 * 2 * 2
    assert [(p.axes["radio.latency_s"], p.axes["radio.loss"]["model"], p.seed) for p in pts[:4]] == [
        (0.0, "bernoulli", 3), (0.0, "bernoulli", 4), (0.0, "gilbert_elliott", 3), (0.0, "gilbert_elliott", 4)]
    p = pts[5]  # latency 0.1, bernoulli, seed 4
    assert p.overrides == {"duration_s": 5, "seed": 4, "radio.jitter_s": 0.001, "radio.latency_s": 0.1,
                           "radio.loss": {"model": "bernoulli", "p": 0.2}}
    expected = hashlib.sha256(json.dumps(p.overrides, sort_keys=True, separators=(",", ":")).encode()).hexdigest()[:12]
    assert p.run_id == expected
    sc = p.scenario
    assert (sc.seed, sc.duration_s, sc.radio.latency_s, sc.radio.jitter_s) == (4, 5.0, 0.1, 0.001)
    assert (sc.radio.loss.model, sc.radio.loss.p, sc.radio.range_m) == ("bernoulli", 0.2, 10_000.0)  # the rest of [radio] kept
    assert len({q.run_id for q in pts}) == len(pts)
    # the same grid written with the axes in another order has the same ids; another duration changes them
    swapped = GRID.replace('"radio.latency_s" = [0.0, 0.1, 0.5]\n', "") + '"radio.latency_s" = [0.0, 0.1, 0.5]\n'
    assert {q.run_id for q in load_sweep(write(tmp_path, swapped, "b.toml")).points} == {q.run_id for q in pts}
    longer = load_sweep(write(tmp_path, GRID.replace("duration_s = 5", "duration_s = 6"), "c.toml"))
    assert not {q.run_id for q in longer.points} & {q.run_id for q in pts}
    assert spec.axis_columns == ["radio.latency_s", "radio.loss.model", "radio.loss.p", "radio.loss.p_good_to_bad"]
    assert pts[2].columns == {"radio.latency_s": 0.0, "radio.loss.model": "gilbert_elliott", "radio.loss.p_good_to_bad": 0.01}


def test_changing_the_law_resets_params_unless_they_are_given(tmp_path):
    spec = load_sweep(write(tmp_path, 'name = "x"\nbase = "seed000"\n[axes]\n"controller.law" = ["finite_time", "consensus"]\n'))
    ft, cons = (p.scenario.controller for p in spec.points)
    assert ft == SEED000.controller  # the base's law keeps the base's params
    assert (cons.law, cons.params) == ("consensus", law_params("consensus"))  # another law: its own defaults
    assert spec.points[1].overrides["controller.params"] == {}
    # single params on top of the new law's defaults
    spec = load_sweep(write(tmp_path, 'name = "x"\nbase = "seed000"\n[overrides]\n"controller.law" = "consensus"\n'
                                      '[axes]\n"controller.params.kx_ref" = [0.05, 0.2]\n', "b.toml"))
    assert [p.scenario.controller.params for p in spec.points] == [law_params("consensus", kx_ref=0.05),
                                                                   law_params("consensus", kx_ref=0.2)]
    # a law with its own params as a table axis value; a table without params means defaults
    spec = load_sweep(write(tmp_path, 'name = "x"\nbase = "seed000"\n[axes]\n"controller" = [{ law = "consensus", '
                                      'params = { cancel_coupler = true } }, { law = "finite_time" }]\n', "c.toml"))
    assert [(p.scenario.controller.law, p.scenario.controller.params) for p in spec.points] == [
        ("consensus", law_params("consensus", cancel_coupler=True)), ("finite_time", law_params("finite_time"))]
    assert spec.axis_columns == ["controller.law", "controller.params.cancel_coupler"]


def test_packaged_studies_load_with_their_documented_grids():
    assert {"latency-loss", "latency-loss-large", "bitrate"} <= set(packaged_sweeps())
    small = load_sweep("latency-loss")
    assert len(small.points) == 12 and small.duration_s <= 100
    assert {p.scenario.controller.law for p in small.points} == {"finite_time", "consensus"}
    assert {p.scenario.radio.loss.model for p in small.points} == {"bernoulli"}
    large = load_sweep("latency-loss-large")
    assert large.duration_s == 600 and max(large.axes["radio.latency_s"]) == 1.0 and max(large.axes["radio.loss.p"]) == 0.5
    bitrate = load_sweep("bitrate")
    assert [p.scenario.can.bitrate for p in bitrate.points] == [125_000, 250_000, 500_000, 1_000_000]
    assert {p.scenario.trains.units for p in bitrate.points} == {8}


# --------------------------------------------------------------------------- running


RUNS = '''name = "runs"
base = "seed000"
duration_s = 3
[axes]
"controller.law" = ["finite_time", "consensus"]
"plant.davis_c2" = [1.6e-5, 1e3]   # 1e3 N s^2/(m^2 kg) is legal but makes the plant diverge within 10 ms
'''


@pytest.fixture(scope="module")
def pool_sweep(tmp_path_factory):
    d = tmp_path_factory.mktemp("pool")
    spec = load_sweep(write(d, RUNS))
    return spec, run_sweep(spec, d / "out", workers=2, progress=False)


def test_a_failing_run_is_recorded_and_the_sweep_goes_on(pool_sweep):
    spec, res = pool_sweep
    assert (res.total, res.ok, res.failed, res.ran, res.reused, res.interrupted) == (4, 2, 2, 4, 0, False)
    by_c2 = {(r["controller.law"], r["plant.davis_c2"]): r for r in res.rows}
    for law in ("finite_time", "consensus"):
        bad, good = by_c2[(law, 1e3)], by_c2[(law, 1.6e-5)]
        assert bad["status"] == "failed" and bad["error"].startswith("PlantDiverged: plant diverged at t = 0.00")
        assert bad["gap_min_overall_m"] is None
        assert good["status"] == "ok" and good["error"] is None and good["sim_time_s"] == pytest.approx(3.0)
        run = res.out_dir / "runs" / bad["run_id"]
        text = (run / "error.txt").read_text()
        assert "Traceback (most recent call last)" in text and "PlantDiverged" in text
        assert not (run / "metrics.json").exists()
        assert json.loads((run / "overrides.json").read_text())["axes"] == {"controller.law": law, "plant.davis_c2": 1e3}
    assert res.failures == [by_c2[("finite_time", 1e3)]["run_id"], by_c2[("consensus", 1e3)]["run_id"]]
    assert load_results(res.out_dir) == res.rows == load_results(res.csv_path)


def test_csv_rows_equal_single_runs_of_the_same_points(pool_sweep, tmp_path):
    """The finite-time point is `hil run seed000`; the consensus point (law changed, params reset) is seed000-consensus."""
    _, res = pool_sweep
    rows = {r["controller.law"]: r for r in res.rows if r["status"] == "ok"}
    for law, scenario in (("finite_time", "seed000"), ("consensus", "seed000-consensus")):
        single = run_scenario(load_scenario(scenario, {"duration_s": 3}), tmp_path / law, record=False).metrics
        expected = deterministic(flatten_metrics(single))
        got = {k: v for k, v in deterministic(rows[law]).items() if k in expected}
        assert expected.keys() - {"scenario"} <= got.keys()
        for key in ("scenario", "provenance.scenario_sha256"):  # the scenario's name: seed000-consensus vs seed000
            expected.pop(key), got.pop(key)
        assert got == expected
        assert rows[law]["frames_sent"] > 10_000 and rows[law]["seed"] == 0


def test_dask_local_cluster_gives_the_process_pool_results(pool_sweep, tmp_path, capfd):
    spec, res = pool_sweep
    dres = run_sweep(spec, tmp_path / "dask", workers=2, dask="local", progress=False)
    assert (dres.ok, dres.failed) == (2, 2)
    # the engine's objects may be dropped on a worker's other thread (they were "unsendable": a traceback each)
    assert "unsendable" not in capfd.readouterr().err
    assert [deterministic(r) for r in dres.rows] == [deterministic(r) for r in res.rows]


def test_resume_does_not_redo_finished_runs_and_failures_are_retried(pool_sweep):
    spec, res = pool_sweep
    ok_files = [res.out_dir / "runs" / r["run_id"] / "metrics.json" for r in res.rows if r["status"] == "ok"]
    before = [f.stat().st_mtime_ns for f in ok_files]
    again = run_sweep(spec, res.out_dir, workers=1, progress=False)
    assert (again.reused, again.ran, again.ok, again.failed) == (2, 2, 2, 2)  # only the failed points ran again
    assert [f.stat().st_mtime_ns for f in ok_files] == before


def test_interrupted_sweep_resumes_where_it_stopped(tmp_path):
    """Ctrl-C (SIGINT to the process group, as a terminal sends it) mid-sweep, then the same sweep again."""
    latencies = ", ".join(str(0.01 * i) for i in range(6))
    path = write(tmp_path, f'name = "resume"\nbase = "seed000"\nduration_s = 4\n[axes]\n"radio.latency_s" = [{latencies}]\n')
    out = tmp_path / "out"
    code = ("import argparse, sys\nfrom hil.commands.sweep import add_sweep_parser\np = argparse.ArgumentParser()\n"
            "add_sweep_parser(p.add_subparsers(required=True))\na = p.parse_args(sys.argv[1:])\nsys.exit(a.func(a))\n")
    proc = subprocess.Popen([sys.executable, "-c", code, "sweep", str(path), "--out", str(out), "--workers", "1", "--quiet"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True)
    deadline = time.monotonic() + 60
    while not list(out.glob("runs/*/metrics.json")) and time.monotonic() < deadline and proc.poll() is None:
        time.sleep(0.02)
    os.killpg(proc.pid, signal.SIGINT)
    stdout, stderr = proc.communicate(timeout=60)
    assert proc.returncode == 130, stderr
    assert "INTERRUPTED" in stdout and "not run" in stdout
    done = {f.parent.name: f.stat().st_mtime_ns for f in out.glob("runs/*/metrics.json")}
    assert 1 <= len(done) < 6
    for run in done:
        json.loads((out / "runs" / run / "metrics.json").read_text())  # complete files only
    assert not list(out.glob("runs/*/error.txt"))  # abandoned runs are not failures
    assert {r["run_id"] for r in load_results(out)} == set(done)

    spec = load_sweep(path)
    res = run_sweep(spec, out, workers=2, progress=False)
    assert (res.reused, res.ran, res.ok, res.failed) == (len(done), 6 - len(done), 6, 0)
    assert {run: (out / "runs" / run / "metrics.json").stat().st_mtime_ns for run in done} == done
    assert [r["radio.latency_s"] for r in res.rows] == spec.axes["radio.latency_s"]


def test_an_out_dir_of_another_base_is_refused(tmp_path):
    spec = sweep_from_dict({"name": "x", "base": "seed000", "axes": {"radio.latency_s": [0.1]}})
    (tmp_path / MANIFEST).write_text(json.dumps({"base": "other.toml", "base_sha256": "0" * 64}))
    with pytest.raises(SweepError, match="holds runs of another base scenario"):
        run_sweep(spec, tmp_path, progress=False)


# --------------------------------------------------------------------------- the CSV's columns


def test_metrics_flatten_to_columns_with_per_item_tables_summed():
    metrics = {"gap_min_m": [1.0, 2.0], "settled": False, "settling_time_s": None,
               "per_bus": {"bus1": {"load_max": 0.5, "latency_max_by_id": {"0x0C0": 0.001}}},
               "e2e": {"train1/unit1/ecu": {"OK": 10, "CRC": 1}, "train1/unit2/ecu": {"OK": 7}},
               "codec_saturations": {"A.Force": 3, "B.Accel": 4}, "radio": {"1>2": {"lost": 2}, "2>1": {"lost": 5}},
               "events_by_level": {"WARN": 2}}
    assert flatten_metrics(metrics) == {
        "gap_min_m_1": 1.0, "gap_min_m_2": 2.0, "settled": False, "settling_time_s": None, "per_bus.bus1.load_max": 0.5,
        "e2e_total.OK": 17, "e2e_total.CRC": 1, "codec_saturations_total": 7, "radio_total.lost": 7,
        "events_by_level.WARN": 2}
    assert canonical_json({"b": 1, "a": [1.5]}) == '{"a":[1.5],"b":1}'


def test_results_keep_one_column_per_verdict_and_the_violations_go_to_a_side_file(pool_sweep):
    """results.csv once had 410 columns, mostly safety.*.violations_N.*: one per verdict now."""
    import csv

    spec, res = pool_sweep
    columns = list(res.rows[0])
    assert len(columns) < 200 and not [c for c in columns if ".violations" in c or "overspeed_margin" in c]
    assert {"safety.safe", "safety.coupler_out_of_band.count", "safety.overspeed.total_s",
            "safety.gap_below_le.first_s", "provenance.scenario_sha256"} <= set(columns)
    with (res.out_dir / "safety_violations.csv").open() as f:
        details = list(csv.DictReader(f))
    ok = {r["run_id"]: r for r in res.rows if r["status"] == "ok"}
    for run_id, row in ok.items():
        mine = [d for d in details if d["run_id"] == run_id]
        assert len(mine) == sum(min(row[f"safety.{v}.count"], 50) for v in
                                ("gap_below_le", "collision", "coupler_out_of_band", "overspeed"))
    assert details and details[0]["verdict"] and float(details[0]["start_s"]) >= 0.0


def test_set_and_duration_adjust_every_run_of_a_sweep(tmp_path):
    path = write(tmp_path, RUNS)
    plain = load_sweep(path)
    adjusted = load_sweep(path, {"radio.latency_s": 0.3, "can.bitrate": 250000}, 1.5)
    assert len(adjusted.points) == len(plain.points) == 4
    for p in adjusted.points:
        assert (p.scenario.radio.latency_s, p.scenario.can.bitrate, p.scenario.duration_s) == (0.3, 250000, 1.5)
    assert not {p.run_id for p in adjusted.points} & {p.run_id for p in plain.points}  # never reuses other runs
    bad = subprocess.run([sys.executable, "-m", "hil", "sweep", str(path), "--duration", "-1"],
                         capture_output=True, text=True, timeout=120)
    assert bad.returncode == 2 and "--duration" in bad.stderr
    typo = subprocess.run([sys.executable, "-m", "hil", "sweep", str(path), "--set", "radio.latncy_s=0.3"],
                          capture_output=True, text=True, timeout=120)
    assert typo.returncode == 2 and "radio.latncy_s" in typo.stderr and "Traceback" not in typo.stderr
