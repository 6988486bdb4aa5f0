"""The pytest plugin and hil.testing: building rigs with overrides and swapped firmware, signals keyed by the
recording's entity paths, assertion reports that name the signal, the time and the margin, --hil-record."""
from __future__ import annotations

import os
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest
from pydantic import Field

from ecu_sim.controllers.base import Controller, ControllerParams
from ecu_sim.programs import EcuSetup, standard_program
from ecu_sim.runtime import Ecu
from ecu_sim.view import Command, LocalView
from hil.scenario import ScenarioError
from hil.testing import (
    HilAssertionError,
    Rig,
    assert_frame_period,
    assert_never_above,
    assert_never_below,
    assert_no_e2e_errors,
    assert_no_events,
    assert_settles,
    assert_within,
    build_scenario,
)
from hil.testing.results import HilRun
from tests.law_views import law_params
from tests.rrd_reader import read_scalars
from tests.test_rerun_writer import make_log

ROOT = Path(__file__).resolve().parents[1]
CRUISE = ROOT / "examples" / "cruise.toml"


class ConstantForceParams(ControllerParams):
    force_n: float = Field(default=0.0)


class ConstantForce(Controller):
    """A user law that is not registered: every unit commands the same force."""

    name = "test_constant_force"
    Params = ConstantForceParams

    def step(self, view: LocalView) -> Command:
        return Command(force_n=self.params.force_n, accel_mps2=0.0)


class SilentAfterOneSecond(Ecu):
    """An ECU program with a bug: train 2's second unit stops sending anything after t = 1 s."""

    def cycle(self, t: float) -> list[tuple[int, bytes]]:
        frames = super().cycle(t)
        return [] if self.name == "train2/unit2/ecu" and t > 1.0 else frames


def dead_train2_unit2(setup: EcuSetup):
    """An ECU factory: the standard firmware everywhere, but train 2's unit 2 is dead from the start."""
    ecu = standard_program(setup)
    ecu.alive = ecu.name != "train2/unit2/ecu"
    return ecu


def synthetic_run() -> HilRun:
    """20 samples at 0.1 s of 2 trains x 2 units (tests/test_rerun_writer.make_log), no rig needed."""
    sc = build_scenario(CRUISE, {"trains.units": 2})
    log = make_log()
    log.sim_time_s = 1.9
    return HilRun(sc, log, {}, "virtual", "consensus", 0)


# --------------------------------------------------------------------------- building rigs


def test_overrides_and_law_swap_build_a_validated_scenario():
    sc = build_scenario(CRUISE, {"radio.latency_s": 0.2, "can.bitrate": 250000, "controller.params.kx_ref": 0.2})
    assert sc.radio.latency_s == 0.2 and sc.can.bitrate == 250000 and sc.controller.params == law_params(sc.controller.law, kx_ref=0.2)
    swapped = build_scenario(CRUISE, controller=ConstantForce)
    assert swapped.controller.law == "tests.test_hil_testing:ConstantForce" and swapped.controller.params == law_params(ConstantForce)
    assert build_scenario(CRUISE, controller=ConstantForce, params={"force_n": 5.0}).controller.params == law_params(
        ConstantForce, force_n=5.0)
    assert build_scenario(sc, {"seed": 4}).seed == 4  # a Scenario object works too
    assert build_scenario("seed000", {"controller.law": "consensus"}).controller.params == law_params("consensus")  # as in sweeps
    assert build_scenario("seed000", {"controller.params.p1": 5.0}).controller.params["p1"] == 5.0
    with pytest.raises(ScenarioError, match=r"can\.bitrate.*got 300000"):
        build_scenario(CRUISE, {"can.bitrate": 300000})
    with pytest.raises(ScenarioError, match=r"controller\.params\.force"):
        build_scenario(CRUISE, controller=ConstantForce, params={"force": 1.0})
    with pytest.raises(ScenarioError, match="controller.law: unknown controller law 'nope'"):
        build_scenario(CRUISE, controller="nope")

    class Impostor(ConstantForce):  # defined in a function: registered by name, which must be free
        name = "consensus"

    with pytest.raises(ValueError, match="already taken"):
        build_scenario(CRUISE, controller=Impostor)
    with pytest.raises(TypeError, match="Controller subclass"):
        build_scenario(CRUISE, controller=object)


def test_the_users_controller_class_runs_on_every_ecu(hil_rig):
    run = hil_rig(str(CRUISE), controller=ConstantForce, params={"force_n": 2500.0}).run(0.5)
    commands = run.signals.match("/trains/*/units/*/traction_kn")
    assert len(commands) == 6
    for path, (t, v) in commands.items():
        assert v[0] == 0.0 and np.all(v[t >= 0.1] == 2.5), path  # 2.5 kN as soon as the first command arrived
    assert run.controller == "tests.test_hil_testing:ConstantForce" and run.runtime == "virtual"


def test_signals_are_the_recordings_scalars_with_the_same_values(hil_rig, tmp_path):
    run = hil_rig(CRUISE).run(1.0)
    recorded = read_scalars(run.save(tmp_path))
    scalars = {p for p in recorded if not p.startswith("/limits/")}
    assert scalars == set(run.signals)
    for path in ("/trains/2/units/3/speed_error_kmh", "/trains/1/couplers/2/displacement_m", "/trains/2/gap_ahead_m",
                 "/buses/bus2/frame_latency_ms", "/buses/bus1/load"):
        t, v = run.signals[path]
        np.testing.assert_allclose(recorded[path][0], t, atol=1e-9)
        np.testing.assert_allclose(recorded[path][1], v)
    assert (tmp_path / "metrics.json").exists()
    np.testing.assert_allclose(run.signals["/trains/1/units/1/speed_kmh"].v, run.log.v[:, 0] * 3.6)


def test_identical_virtual_runs_are_simulated_once_per_session(hil_rig):
    a = hil_rig(CRUISE).run(0.3)
    assert hil_rig(CRUISE).run(0.3) is a
    assert hil_rig(CRUISE, set={"seed": 3}).run(0.3) is not a
    assert Rig(CRUISE).run(0.3) is not a  # outside the plugin: no cache


def test_an_ecu_program_swap_and_the_frame_period_report(hil_rig):
    run = hil_rig(CRUISE, ecu=SilentAfterOneSecond).run(2.0)
    assert_frame_period(run, "TractionCmd_U02", max_gap_ms=12.0, bus="bus1")  # train 1's unit 2 is fine
    with pytest.raises(HilAssertionError) as err:
        assert_frame_period(run, "TractionCmd_U*", max_gap_ms=12.0)
    msg = str(err.value)
    assert "TractionCmd_U* received at least every 12 ms throughout" in msg
    assert "1 of 6 frame streams fails" in msg
    assert "TractionCmd_U02 (0x081) on bus2: 1 gap longer than 12 ms" in msg
    assert "to 2.0000 s (the end of the window: no frame since)" in msg
    last = run.frame_times(0x081, "bus2")[-1]
    assert 0.98 < last <= 1.0 and f"from t = {last:.4f} s" in msg
    assert "run: scenario 'cruise', law 'consensus', virtual, 2 s simulated, seed 0" in msg
    assert_no_events(run, "ERROR", source="train1/*")
    with pytest.raises(HilAssertionError, match="plant"):  # the plant's fail-safe took over train 2's unit 2
        assert_no_events(run, "WARN")
    with pytest.raises(KeyError, match="no DBC message 'TractionCmd'"):
        assert_frame_period(run, "TractionCmd", 12.0)


def test_an_ecu_factory_and_a_frame_never_sent(hil_rig):
    run = hil_rig(CRUISE, ecu=dead_train2_unit2).run(0.5)
    assert_frame_period(run, "AgentState_U02", max_gap_ms=12.0, bus="bus1")
    with pytest.raises(HilAssertionError, match=r"AgentState_U02 \(0x101\) on bus2: no frame between t = 0 s and 0.5 s"):
        assert_frame_period(run, "AgentState_U02", max_gap_ms=12.0)


# --------------------------------------------------------------------------- assertion reports


def test_within_names_the_signal_the_time_and_the_margin():
    run = synthetic_run()
    assert_within(run, "/trains/*/units/*/speed_kmh", 35.0, 50.0)
    with pytest.raises(HilAssertionError) as err:
        assert_within(run, "/trains/*/units/*/speed_kmh", 35.0, 46.0, after=0.5)
    lines = str(err.value).splitlines()
    # speed of unit u at sample k: (10 + 0.01 k + u) * 3.6 km/h; unit 3 exceeds 46 from k = 0 (46.8 km/h)
    assert lines[0] == "HIL check failed: /trains/*/units/*/speed_kmh within [35, 46] km/h from t = 0.5 s"
    assert lines[1] == "  1 of 4 signals fails:"
    assert lines[2].startswith("  - /trains/2/units/2/speed_kmh: left [35, 46] km/h at t = 0.500 s (46.98 km/h, "
                               "0.98 above); worst 47.48 km/h at t = 1.900 s (1.484 beyond); outside for 1.4 s")


def test_never_below_and_above_report_the_extreme_and_its_time():
    run = synthetic_run()
    gap = run.signals["/trains/2/gap_ahead_m"]
    assert_never_below(run, "/trains/2/gap_ahead_m", float(gap.v.min()) - 1.0)
    with pytest.raises(HilAssertionError) as err:
        assert_never_below(run, "/trains/2/gap_ahead_m", 150.0)
    i = int(np.argmin(gap.v))
    assert f"minimum {gap.v[i]:.4g} m at t = {gap.t[i]:.3f} s ({150.0 - gap.v[i]:.4g} m below the limit)" in str(err.value)
    with pytest.raises(HilAssertionError, match=r"/trains/1/units/1/traction_kn: above 15 kN from t = 1.600 s \(16 kN\)"):
        assert_never_above(run, "/trains/1/units/1/traction_kn", 15.0)


def test_settles_reports_late_and_never():
    run = synthetic_run()
    # speed error of every unit: (0.01 k + u) * 3.6 km/h - grows, so unit 0 leaves +-0.2 at k = 6 and never returns
    with pytest.raises(HilAssertionError) as err:
        assert_settles(run, "/trains/1/units/1/speed_error_kmh", within=1.0, tol=0.2)
    assert "never settles in 0 ± 0.2 km/h: still 0.684 km/h at the end (t = 1.900 s, 0.484 km/h outside)" in str(err.value)
    assert_settles(run, "/trains/1/units/1/speed_error_kmh", within=1.0, tol=0.5, target=0.4)  # in band throughout
    with pytest.raises(ValueError, match="run it for longer"):
        assert_settles(run, "/trains/*/units/*/speed_error_kmh", within=5.0, tol=0.5)


def test_settles_late_message():
    run = synthetic_run()
    t, v = run.signals["/trains/1/units/1/speed_error_kmh"]
    # target 0.684 (the last value), tol 0.1: inside from the first sample within 0.1 of it, i.e. v >= 0.584 (k = 17)
    with pytest.raises(HilAssertionError) as err:
        assert_settles(run, "/trains/1/units/1/speed_error_kmh", within=1.0, tol=0.1, target=float(v[-1]))
    assert "settles in 0.684 ± 0.1 km/h at t = 1.700 s, 0.7 s later than 1 s; last outside at t = 1.600 s" in str(err.value)


def test_e2e_and_events_reports():
    run = synthetic_run()
    run.log.e2e = {"train1/unit1/ecu": {"OK": 100, "INITIAL": 2}, "train2/unit1/ecu": {"OK": 90, "CRC_ERROR": 3, "OK_SOME_LOST": 4}}
    with pytest.raises(HilAssertionError) as err:
        assert_no_e2e_errors(run)
    assert "1 of 2 ECUs fails" in str(err.value) and "train2/unit1/ecu: 3 CRC_ERROR (of 97 checked frames)" in str(err.value)
    with pytest.raises(HilAssertionError, match="3 CRC_ERROR, 4 OK_SOME_LOST"):
        assert_no_e2e_errors(run, statuses=("CRC_ERROR", "OK_SOME_LOST"))
    with pytest.raises(HilAssertionError, match=r"t = 1.200 s ERROR plant: emergency brake"):
        assert_no_events(run)
    assert_no_events(run, source="radio*")


def test_unknown_paths_say_what_exists():
    run = synthetic_run()
    with pytest.raises(KeyError, match=r"no signal matches '/trains/\*/units/\*/speed_mps'; signal names: .*speed_kmh"):
        assert_within(run, "/trains/*/units/*/speed_mps", 0, 1)
    with pytest.raises(KeyError, match=r"no signal '/trains/3/units/1/speed_kmh'; e.g. /trains/1/units/1/speed_kmh"):
        assert_within(run, "/trains/3/units/1/speed_kmh", 0, 1)


# --------------------------------------------------------------------------- real-time node processes


def test_real_time_nodes_import_the_users_law_and_ecu_program(tmp_path):
    """The node processes resolve the scenario's references themselves, after their sys.path, in the folders the
    rig names in TRAINHIL_USER_PATH."""
    from hil.runtime.realtime.orchestrator import node_environment
    from hil.runtime.assembly import assemble
    from hil.runtime.firmware import build_ecu

    sc = build_scenario(CRUISE, controller=ConstantForce, ecu=SilentAfterOneSecond)
    assert (sc.controller.law, sc.ecu.program) == ("tests.test_hil_testing:ConstantForce",
                                                   "tests.test_hil_testing:SilentAfterOneSecond")
    parts = assemble(sc)
    ecu = build_ecu(parts, __import__("ecu_sim.codec").codec.TrainDb.load(), 4)
    assert type(ecu) is SilentAfterOneSecond and type(ecu.controller) is ConstantForce
    (tmp_path / "scenario.json").write_text(sc.model_dump_json())
    probe = ("import sys; from hil.runtime.realtime.node import load_scenario_json; from hil.runtime.assembly import assemble; "
             "from hil.runtime.firmware import build_ecu; from ecu_sim.codec import TrainDb; "
             "e = build_ecu(assemble(load_scenario_json(sys.argv[1])), TrainDb.load(), 4); "
             "print(type(e).__qualname__, type(e.controller).__qualname__)")
    env = node_environment(sc)
    out = subprocess.run([sys.executable, "-P", "-c", probe, str(tmp_path / "scenario.json")], capture_output=True, text=True,
                         timeout=120, cwd=tmp_path, env=env)
    assert out.returncode == 0, out.stderr
    assert out.stdout.split() == ["SilentAfterOneSecond", "ConstantForce"]
    assert env.get("PYTHONPATH") == os.environ.get("PYTHONPATH")  # nothing put before the installed packages
    assert str(ROOT) in env["TRAINHIL_USER_PATH"].split(os.pathsep)

    class Local(ConstantForce):
        name = "test_local"

    rig = Rig(CRUISE, controller=Local)
    assert rig.run(0.1).controller == "test_local"  # virtual time: registered in this process
    with pytest.raises(ValueError, match="top level of an importable module"):
        rig.run(0.1, realtime=True)

    def silent_train1(setup):  # a local ECU factory: virtual time only, as a local law
        ecu = standard_program(setup)
        ecu.alive = not setup.name.startswith("train1/")
        return ecu

    local = Rig(CRUISE, ecu=silent_train1)
    assert local.scenario.ecu.program.startswith("local:tests.test_hil_testing.")
    run = local.run(0.2)
    assert len(run.frame_times(0x080, "bus1")) == 0 and len(run.frame_times(0x080, "bus2")) > 0
    with pytest.raises(ValueError, match="the ECU program of this rig must be defined at the top level"):
        local.run(0.1, realtime=True)


# --------------------------------------------------------------------------- the plugin in a pytest session


def test_the_marker_is_registered(pytestconfig):
    assert any(m.startswith("hil_realtime(") for m in pytestconfig.getini("markers"))


def test_hil_record_keeps_the_rrd_of_failing_tests_only(tmp_path):
    (tmp_path / "test_user.py").write_text(textwrap.dedent(f"""
        import pytest
        from hil.testing import assert_never_below

        CRUISE = {str(CRUISE)!r}

        def test_passes(hil_rig):
            hil_rig(CRUISE).run(0.5)

        def test_fails(hil_rig):
            assert_never_below(hil_rig(CRUISE).run(0.5), "/trains/2/gap_ahead_m", 2100.0)

        @pytest.mark.xfail(reason="expected")
        def test_xfails(hil_rig):
            assert_never_below(hil_rig(CRUISE, set={{"seed": 1}}).run(0.5), "/trains/2/gap_ahead_m", 2100.0)
    """))
    rec = tmp_path / "kept"
    proc = subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "test_user.py",
                           "--hil-record", str(rec)], capture_output=True, text=True, cwd=tmp_path, timeout=300)
    assert proc.returncode == 1, proc.stdout + proc.stderr
    assert "1 failed, 1 passed, 1 xfailed" in proc.stdout
    assert "HIL check failed: /trains/2/gap_ahead_m never below 2100 m throughout" in proc.stdout
    assert "hil recording" in proc.stdout and "open: hil view" in proc.stdout
    kept = sorted(p.relative_to(rec).as_posix() for p in rec.rglob("*") if p.is_file())
    assert kept == ["test_user.py_test_fails/cruise/metrics.json", "test_user.py_test_fails/cruise/run.rrd",
                    "test_user.py_test_xfails/cruise/metrics.json", "test_user.py_test_xfails/cruise/run.rrd"]
    assert "/trains/2/gap_ahead_m" in read_scalars(rec / "test_user.py_test_fails" / "cruise" / "run.rrd")
