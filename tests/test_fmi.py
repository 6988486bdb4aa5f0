"""FMUs as the plant and as the law: the reference FMUs (built here with gcc from hil/fmi/c/) against the built-in
plant and the Python consensus law, in FMI 2 and 3, in both runtimes and in a sweep, and every bad FMU named.

Tolerances, and why they are what they are:
- the plant FMU integrates with RK4 at the 1 ms plant step and evaluates the Davis terms inside the step, where the
  built-in plant has the exact flow of the linear part with the other forces held from the step start: open loop
  over 30 s under random force steps the states differ by 1.1e-4 m and 1.7e-5 m/s (tolerance 1e-3 m, 1e-4 m/s);
- closed loop (seed000's ideal loop, 800 s) the settling time and the final errors agree to within 1 %;
- the law FMU computes the consensus law's sum in the same order in C: the runs agree to rounding (1e-9 relative).
"""
from __future__ import annotations

import json
import math
import re
import zipfile
from pathlib import Path

import numpy as np
import pytest

from ecu_sim.fmu import FmuError, load_fmu
from hil.cli import main
from hil.fmi.build import build_fmu, consensus_law, train_plant
from hil.runtime.assembly import assemble
from hil.scenario import ScenarioError, load_scenario
from hil.session import run_scenario

PACKAGED = Path(__file__).resolve().parents[1] / "hil" / "packaged" / "scenarios"


@pytest.fixture(scope="module", autouse=True)
def fmu_cache(tmp_path_factory):
    """Reference FMUs are built into this module's own cache: nothing from an earlier build is reused."""
    mp = pytest.MonkeyPatch()
    mp.setenv("TRAINHIL_FMU_CACHE", str(tmp_path_factory.mktemp("fmu-cache")))
    yield
    mp.undo()


@pytest.fixture(scope="module")
def plant_fmu(tmp_path_factory) -> Path:
    return build_fmu(train_plant(3, 4), 2, tmp_path_factory.mktemp("fmus") / "train_plant.fmu")


def plant_scenario(tmp_path: Path, path: str | Path, **mapping: str) -> Path:
    """seed000-fmu-plant with another FMU path and some of its mapping replaced."""
    text = (PACKAGED / "seed000-fmu-plant.toml").read_text()
    text = text.replace('path = "trainhil:train_plant"', f'path = "{path}"')
    for key, value in mapping.items():
        text = re.sub(rf'^{key} = .*$', f'{key} = "{value}"', text, flags=re.M)
    out = tmp_path / "plant.toml"
    out.write_text(text)
    return out


def rewrite_description(src: Path, dst: Path, change) -> Path:
    """A copy of the FMU ``src`` with ``change(xml) -> xml`` applied to its modelDescription.xml."""
    with zipfile.ZipFile(src) as zin, zipfile.ZipFile(dst, "w") as zout:
        for item in zin.infolist():
            data = zin.read(item.filename)
            if item.filename == "modelDescription.xml":
                data = change(data.decode()).encode()
            zout.writestr(item, data)
    return dst


# --------------------------------------------------------------------------- the reference FMUs


@pytest.mark.parametrize("version", [2, 3])
def test_reference_fmus_validate_and_have_their_variables(tmp_path, version):
    import fmpy

    for spec in (train_plant(2, 3), consensus_law()):
        path = build_fmu(spec, version, tmp_path / f"{spec.identifier}.fmu")
        md = fmpy.read_model_description(str(path), validate=True)
        assert md.fmiVersion.startswith(str(version)) and md.coSimulation is not None
        names = {v.name for v in md.modelVariables}
        assert {name for _, name, _ in spec.scalars()} == names
    plant = load_fmu(tmp_path / "train_plant.fmu")
    assert plant.variables["e[4]"].causality == "output" and "e[5]" not in plant.variables  # 2 x (3 - 1) couplers


# --------------------------------------------------------------------------- plant agreement


@pytest.mark.parametrize("suffix, step_s", [("", None), ("@3", None), ("", 0.005)])
def test_fmu_plant_open_loop_matches_the_builtin_plant(suffix, step_s):
    """Same random force steps into both plants for 30 s: states agree to the integrators' difference, also with
    a communication step of 5 plant steps (the commands change every 10 ms, on communication points)."""
    builtin = assemble(load_scenario("seed000")).plant
    fmu = assemble(load_scenario("seed000-fmu-plant", {"plant.fmu.path": f"trainhil:train_plant{suffix}",
                                                       "plant.fmu.step_s": step_s})).plant
    assert type(fmu).__name__ == "FmuPlant" and fmu.fmu.fmi_version == (3 if suffix else 2)
    assert fmu.fmu_step_s == (step_s or 0.001)
    forces = np.random.default_rng(1).uniform(-2e5, 2e5, size=(3000, builtin.layout.n_units))
    for k in range(30_000):
        if k % 10 == 0:
            for p in (builtin, fmu):
                for u, f in enumerate(forces[k // 10]):
                    p.command(u, float(f), 0, p.t)
        builtin.step()
        fmu.step()
    assert fmu.t == pytest.approx(builtin.t)
    assert np.abs(fmu.x - builtin.x).max() < 1e-3
    assert np.abs(fmu.v - builtin.v).max() < 1e-4
    assert np.abs(fmu.coupler_displacements() - builtin.coupler_displacements()).max() < 1e-4
    assert np.abs(fmu.a - builtin.a).max() < (1e-3 if step_s is None else 1e-2)  # a: the mean over a longer step
    assert np.abs(builtin.v - builtin.v[0]).max() > 0.1  # the forces did move the units apart


def test_fmu_plant_closed_loop_seed000_agrees_with_the_builtin_plant(tmp_path):
    """seed000's ideal loop for its whole 800 s: settling time and final errors within 1 %."""
    runs = {name: run_scenario(load_scenario(name), tmp_path / name, ideal=True, record=False, progress=False).metrics
            for name in ("seed000", "seed000-fmu-plant")}
    a, b = runs["seed000"], runs["seed000-fmu-plant"]
    assert a["settled"] and b["settled"]
    assert b["settling_time_s"] == pytest.approx(a["settling_time_s"], rel=0.01)
    assert b["speed_error_max_after_settling_mps"] == pytest.approx(a["speed_error_max_after_settling_mps"], rel=0.01)
    assert np.allclose(b["gap_final_m"], a["gap_final_m"], rtol=1e-3)
    assert np.allclose(b["position_error_final_m"], a["position_error_final_m"], atol=0.05)
    assert b["coupler_max_abs_m"] == pytest.approx(a["coupler_max_abs_m"], rel=0.01)


# --------------------------------------------------------------------------- law agreement


@pytest.mark.parametrize("suffix", ["", "@3"])
def test_fmu_law_over_can_agrees_with_the_python_law(tmp_path, suffix):
    """seed000's consensus baseline over CAN for 20 s, the law in Python and in the FMU: the same run."""
    text = (PACKAGED / "seed000-fmu-law.toml").read_text()
    (tmp_path / "law.toml").write_text(text.replace('"fmu:trainhil:consensus_law"', f'"fmu:trainhil:consensus_law{suffix}"'))
    law = load_scenario(tmp_path / "law.toml")
    assert law.controller.law.endswith(f"fmi{3 if suffix else 2}-" + law.controller.law.rsplit("-", 1)[1])
    a = run_scenario(load_scenario("seed000-consensus"), tmp_path / "py", duration_s=20, record=False,
                     progress=False).metrics
    b = run_scenario(law, tmp_path / "fmu", duration_s=20, record=False, progress=False).metrics
    for key in ("speed_error_max_abs_mps", "coupler_max_abs_m", "gap_min_overall_m", "control_effort",
                "jerk_rms_mps3", "frames_sent", "string_stability_ratio"):
        assert b[key] == pytest.approx(a[key], rel=1e-9), key
    assert b["safety"]["coupler_out_of_band"]["count"] == a["safety"]["coupler_out_of_band"]["count"]


def test_fmu_law_keeps_the_firmware_emergency_rule():
    """The gap ahead below l_e brakes the unit in emergency before the FMU is asked, as the Python law does."""
    from ecu_sim.view import BrakeMode, LocalView, NeighbourView, ReferenceView

    parts = assemble(load_scenario("seed000-fmu-law"))
    u = parts.layout.index(1, 0)  # head of train 2: its radio neighbour ahead is train 1's tail
    law = parts.law(u)
    ahead = NeighbourView("inter", "ahead", float(parts.layout.offset_m[u - 1]), x=0.0, v=80.0, age_s=0.0, valid=True)
    delta = parts.plant_info.emergency_gap_m - parts.plant_info.spacing_m - 10.0  # the gap is l_e - 10 m
    own_x = ahead.x + (ahead.offset_m - float(parts.layout.offset_m[u])) - delta
    view = LocalView(t=1.0, dt=0.01, x=own_x, v=80.0, neighbours=[ahead], ref=ReferenceView(0.0, 80.0, valid=True))
    assert law.step(view).mode == BrakeMode.EMERGENCY
    parts.close()


# --------------------------------------------------------------------------- both runtimes, sweeps


def test_fmu_plant_and_law_run_in_real_time(tmp_path):
    for name in ("seed000-fmu-plant", "seed000-fmu-law"):
        out = tmp_path / name
        assert main(["run", name, "--realtime", "--duration", "2", "--out", str(out), "--quiet"]) == 0
        metrics = json.loads((out / "metrics.json").read_text())
        assert metrics["runtime"] == "realtime" and metrics["sim_time_s"] == pytest.approx(2.0, abs=0.02)
        assert metrics["frames_lost"] == 0 and metrics["frames_sent"] > 1000


def test_a_sweep_worker_instantiates_each_fmu_once_and_resets_it_between_runs(tmp_path, monkeypatch):
    import ecu_sim.fmu as fmu_module
    from hil.sweep.runner import execute_point

    made: list[str] = []
    original = fmu_module.FmuInstance.__init__

    def counting(self, fmu, name):
        made.append(name)
        original(self, fmu, name)

    monkeypatch.setattr(fmu_module.FmuInstance, "__init__", counting)
    monkeypatch.setattr(fmu_module, "_LOADED", {})  # a fresh worker: no FMU loaded, no pooled instance
    plant = load_scenario("seed000-fmu-plant", {"duration_s": 0.5})
    law = load_scenario("seed000-fmu-law", {"duration_s": 0.5})
    outcomes = [execute_point(sc) for sc in (plant, plant, law, law, law)]
    assert [o["status"] for o in outcomes] == ["ok"] * 5
    assert made.count("plant:" + Path(plant.plant.fmu.path).name) == 1
    assert len([m for m in made if m.startswith("law:")]) == 12  # one per ECU, for all three runs
    assert outcomes[0]["metrics"]["speed_error_max_abs_mps"] == outcomes[1]["metrics"]["speed_error_max_abs_mps"]
    assert outcomes[2]["metrics"]["control_effort"] == outcomes[4]["metrics"]["control_effort"]


def test_sweeps_over_the_unit_count_build_the_plant_fmu_per_layout_under_the_pool_and_dask(tmp_path, capfd):
    from hil.sweep.runner import run_sweep
    from hil.sweep.spec import load_sweep

    spec_file = tmp_path / "units.toml"
    spec_file.write_text('name = "fmu-units"\nbase = "seed000-fmu-plant"\nduration_s = 0.3\n'
                         '[axes]\n"trains.units" = [2, 4]\n')
    spec = load_sweep(spec_file)
    pool = run_sweep(spec, tmp_path / "pool", workers=2, progress=False)
    dask = run_sweep(spec, tmp_path / "dask", workers=2, dask="local", progress=False)
    for res in (pool, dask):
        assert (res.ok, res.failed) == (2, 0), [r.get("error") for r in res.rows]
    assert [r["frames_sent"] for r in pool.rows] == [r["frames_sent"] for r in dask.rows]
    assert [r["coupler_max_abs_m"] for r in pool.rows] == [r["coupler_max_abs_m"] for r in dask.rows]
    assert pool.rows[0]["frames_sent"] < pool.rows[1]["frames_sent"]  # 2 and 4 units per train: two plant FMUs


# --------------------------------------------------------------------------- bad FMUs


def run_exit(argv: list[str], capsys) -> tuple[int, str]:
    code = main(argv)
    return code, capsys.readouterr().err


def test_an_fmu_that_is_not_a_zip_is_one_line_and_exit_2(tmp_path, capsys):
    bad = tmp_path / "broken.fmu"
    bad.write_bytes(b"not a zip at all")
    code, err = run_exit(["run", str(plant_scenario(tmp_path, bad)), "--out", str(tmp_path / "o"), "--duration", "1"],
                         capsys)
    assert code == 2 and "broken.fmu" in err and "not an FMU" in err and "Traceback" not in err
    assert not (tmp_path / "o").exists()


def test_a_model_exchange_fmu_is_refused(tmp_path, plant_fmu):
    me = rewrite_description(plant_fmu, tmp_path / "me.fmu",
                             lambda xml: re.sub(r"<CoSimulation [^>]*/>", '<ModelExchange modelIdentifier="train_plant"/>', xml))
    with pytest.raises(ScenarioError, match=r"me\.fmu: not a co-simulation FMU \(it offers model exchange\)"):
        assemble(load_scenario(plant_scenario(tmp_path, me)))


def test_an_fmu_of_another_fmi_version_is_refused(tmp_path, plant_fmu):
    old = rewrite_description(plant_fmu, tmp_path / "old.fmu", lambda xml: xml.replace('fmiVersion="2.0"', 'fmiVersion="1.0"'))
    with pytest.raises(ScenarioError, match=r"old\.fmu: (FMI 1\.0 is not supported|invalid model description)"):
        assemble(load_scenario(plant_scenario(tmp_path, old)))


@pytest.mark.parametrize("mapping, message", [
    ({"force": "G[{unit}]"}, r"no variable 'G\[1\]' for plant\.fmu\.inputs\.force"),
    ({"force": "x[{unit}]"}, r"variable 'x\[1\]' \(plant\.fmu\.inputs\.force\) has causality 'output'; expected 'input'"),
    ({"position": "F[{unit}]"}, r"variable 'F\[1\]' \(plant\.fmu\.outputs\.position\) has causality 'input'"),
])
def test_a_mapping_that_does_not_fit_the_fmu_names_the_variable(tmp_path, plant_fmu, mapping, message):
    with pytest.raises(ScenarioError, match=r"plant\.fmu: .*train_plant\.fmu: " + message):
        assemble(load_scenario(plant_scenario(tmp_path, plant_fmu, **mapping)))


def test_a_variable_of_the_wrong_type_is_named(tmp_path, plant_fmu):
    typed = rewrite_description(plant_fmu, tmp_path / "typed.fmu", lambda xml: re.sub(
        r'(name="F\[1\]".*?)variability="continuous"><Real start="0.0"/>', r'\1variability="discrete"><Integer start="0"/>',
        xml, count=1))
    with pytest.raises(ScenarioError, match=r"variable 'F\[1\]' \(plant\.fmu\.inputs\.force\) is of type Integer; a Real is needed"):
        assemble(load_scenario(plant_scenario(tmp_path, typed)))


def test_an_unmapped_grade_on_a_graded_track_is_refused(tmp_path):
    sc = load_scenario("seed000-fmu-plant", {"track.grades": [{"start_m": 0.0, "end_m": 1e6, "grade_permille": 5.0}]})
    with pytest.raises(ScenarioError, match=r"the track has grades, but plant\.fmu\.inputs\.grade maps no FMU input"):
        assemble(sc)


def test_a_failing_do_step_stops_the_run_with_readable_files(tmp_path, capsys):
    """substeps = 0 makes the reference plant's doStep return fmi2Error: the run stops at once, exit 1, the message
    names the FMU and says what it logged, and the recording and metrics of what ran are written."""
    scenario = tmp_path / "bad-step.toml"
    scenario.write_text(f'extends = "{PACKAGED / "seed000-fmu-plant.toml"}"\n[plant.fmu.parameters]\nsubsteps = 0\n')
    out = tmp_path / "out"
    code, err = run_exit(["run", str(scenario), "--out", str(out), "--duration", "1"], capsys)
    assert code == 1
    assert re.search(r"train_plant.*\.fmu: doStep at t = 0\.000000 s failed.*substeps = 0: expected a whole number", err)
    metrics = json.loads((out / "metrics.json").read_text())
    assert "FmuPlantError" in metrics["error"]
    assert (out / "run.rrd").stat().st_size > 0


def test_a_diverging_fmu_plant_is_named(tmp_path):
    """A coupler stiffness of 1e300 N/m blows the state up in the first step: the FMU reports it, the run stops."""
    from hil.plant.fmu_plant import FmuPlantError

    plant = assemble(load_scenario("seed000-fmu-plant", {"plant.fmu.parameters.k": 1e300})).plant
    plant.command(0, 1e5, 0, 0.0)
    with pytest.raises(FmuPlantError, match=r"train_plant.*\.fmu: doStep at t = .* the state of unit \d+ diverged"):
        for _ in range(10):
            plant.step()


def test_a_law_fmu_without_a_mapped_variable_is_exit_2_before_anything_runs(tmp_path, capsys):
    out = tmp_path / "o"
    code, err = run_exit(["run", "seed000-fmu-law", "--set", "controller.params.outputs.force=thrust", "--out",
                          str(out), "--duration", "1"], capsys)
    assert code == 2 and "no variable 'thrust' for controller.params.outputs.force" in err and "consensus_law" in err
    assert not out.exists()


def test_a_law_fmu_that_fails_initialization_is_named(tmp_path, capsys):
    code, err = run_exit(["run", "seed000-fmu-law", "--set", "controller.params.parameters.mass=0.0", "--out",
                          str(tmp_path / "o"), "--duration", "1"], capsys)
    assert code == 2 and "initialization failed" in err and "mass = 0: expected a positive mass" in err


def test_in_real_time_an_fmu_that_allows_one_instance_per_process_is_the_law_of_one_unit_per_process(
        tmp_path, capsys, rt):
    """A real-time ECU process builds the laws of the units it runs and no other: with --ecus-per-process 1 such an
    FMU is each unit's law (one instance in each process), with two units a process it is refused before the run,
    naming the FMU (the check builds each process's laws together, as that process would)."""
    law = rewrite_description(Path(load_scenario("seed000-fmu-law").controller.law.removeprefix("fmu:")),
                              tmp_path / "once_law.fmu", lambda xml: xml.replace(
                                  'canBeInstantiatedOnlyOncePerProcess="false"',
                                  'canBeInstantiatedOnlyOncePerProcess="true"'))
    text = (PACKAGED / "seed000-fmu-law.toml").read_text().replace('"fmu:trainhil:consensus_law"', f'"fmu:{law}"')
    scenario = tmp_path / "once_rt.toml"  # one train of two units: two ECU processes
    scenario.write_text(text + "[trains]\ncount = 1\nunits = 2\nhead_positions_m = [108800.0]\n"
                               "speeds_kmh = [295.0]\n")
    argv = ["run", str(scenario), "--realtime", "--duration", "0.5", "--quiet", "--no-record"]
    code, err = run_exit([*argv, "--ecus-per-process", "2", "--out", str(tmp_path / "two")], capsys)
    assert code == 2 and "once_law.fmu: it can be instantiated only once per process" in err
    assert not (tmp_path / "two").exists()
    assert main([*argv, "--ecus-per-process", "1", "--out", str(tmp_path / "one")]) == 0
    m = json.loads((tmp_path / "one" / "metrics.json").read_text())
    assert m["sim_time_s"] == pytest.approx(0.5) and m["frames_lost"] == 0


def test_a_missing_law_fmu_file_is_named(tmp_path, capsys):
    code, err = run_exit(["run", "seed000-fmu-law", "--set", "controller.law=fmu:nowhere.fmu", "--out",
                          str(tmp_path / "o"), "--duration", "1"], capsys)
    assert code == 2 and "nowhere.fmu" in err and "cannot read the FMU" in err


def test_an_fmu_that_allows_one_instance_per_process_is_not_instantiated_twice_in_one(tmp_path, plant_fmu, capsys):
    """An FMU that says canBeInstantiatedOnlyOncePerProcess (its instances would share static state, as exports from
    Simulink often do) is refused as every unit's law, naming the FMU and why, before anything is written; as the
    plant it runs (one instance a process: the check's is given back before the run takes its own)."""
    def once(xml: str) -> str:
        return xml.replace('canBeInstantiatedOnlyOncePerProcess="false"', 'canBeInstantiatedOnlyOncePerProcess="true"')

    law = rewrite_description(Path(load_scenario("seed000-fmu-law").controller.law.removeprefix("fmu:")),
                              tmp_path / "once_law.fmu", once)
    text = (PACKAGED / "seed000-fmu-law.toml").read_text()
    (tmp_path / "once.toml").write_text(text.replace('"fmu:trainhil:consensus_law"', f'"fmu:{law}"'))
    code, err = run_exit(["run", str(tmp_path / "once.toml"), "--duration", "1", "--quiet", "--out",
                          str(tmp_path / "v")], capsys)
    assert code == 2 and "once_law.fmu: it can be instantiated only once per process" in err
    assert "the law of one unit per process" in err and not (tmp_path / "v").exists()
    plant = rewrite_description(plant_fmu, tmp_path / "once_plant.fmu", once)
    assert main(["run", str(plant_scenario(tmp_path, plant)), "--duration", "1", "--quiet", "--out",
                 str(tmp_path / "p")]) == 0


def test_fmu_paths_are_relative_to_the_scenario_file(tmp_path, plant_fmu):
    (tmp_path / "models").mkdir()
    (tmp_path / "models" / "plant.fmu").write_bytes(plant_fmu.read_bytes())
    sc = load_scenario(plant_scenario(tmp_path, "models/plant.fmu"))
    assert sc.plant.fmu.path == str((tmp_path / "models" / "plant.fmu").resolve())
    assert math.isfinite(assemble(sc).plant.x[0])


def test_a_law_fmu_failing_mid_run_stops_that_ecu_like_any_law_that_raises(tmp_path):
    """Gains of 1e308 overflow the FMU's force: the ECUs whose law fails stop (verdict ecu_failure, an ERROR event
    naming the FMU), the plant's fail-safe holds their units, and the run goes on to its end."""
    sc = load_scenario("seed000-fmu-law", {"controller.params.parameters.kx_intra": 1e308})
    result = run_scenario(sc, tmp_path / "out", duration_s=2, record=False, progress=False)
    assert result.metrics["sim_time_s"] == pytest.approx(2.0)
    assert result.metrics["safety"]["ecu_failure"]["violated"]
    errors = [e.text for e in result.log.events if e.level == "ERROR"]
    assert any("consensus_law" in text and ("force = inf" in text or "doStep" in text) for text in errors), errors[:3]


def test_a_reference_fmu_cache_others_can_write_to_is_refused(tmp_path, monkeypatch):
    """An FMU in the cache is native code every run loads: a folder others can write is refused, by name."""
    shared = tmp_path / "shared"
    shared.mkdir()
    shared.chmod(0o777)
    monkeypatch.setenv("TRAINHIL_FMU_CACHE", str(shared))
    with pytest.raises(ScenarioError, match=r"trainhil:train_plant: the FMU cache .*shared is not yours alone .*mode 777"):
        load_scenario("seed000-fmu-plant")
    assert not list(shared.iterdir())


def test_a_crashed_ecu_restarts_its_law_fmu_from_the_start(tmp_path):
    """An ECU crash and restart resets its FMU instance; after the restart the unit's commands are those of the
    Python law restarted the same way (the FMU is initialized again at the first cycle after the restart)."""
    crash = {"faults": [{"kind": "ecu_crash", "train": 2, "unit": 3, "at_s": 1.0, "duration_s": 0.5}]}
    runs = {}
    for name in ("seed000-consensus", "seed000-fmu-law"):
        result = run_scenario(load_scenario(name, crash), tmp_path / name, duration_s=4, record=False, progress=False)
        runs[name] = result.metrics
    a, b = runs["seed000-consensus"], runs["seed000-fmu-law"]
    assert a["faults"]["ecu_restarts"] == b["faults"]["ecu_restarts"] == 1
    for key in ("speed_error_max_abs_mps", "coupler_max_abs_m", "control_effort", "frames_sent"):
        assert b[key] == pytest.approx(a[key], rel=1e-9), key
