"""The user's own firmware through the one seam (hil/runtime/firmware.py): laws and ECU programs by name, by
``module:QualName`` reference and by entry point, per-unit overrides, clear load errors, external units refused
outside real time; and the run's verdict for CI (``--check``) with every violation on the timeline."""
from __future__ import annotations

import os
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

from ecu_sim.controllers.base import get_controller
from ecu_sim.programs import get_program
from ecu_sim.references import ReferenceLoadError
from hil.cli import EXIT_UNSAFE, main
from hil.scenario.firmware import firmware_plan
from hil.scenario import ScenarioError
from hil.testing import Rig, build_scenario
from tests.rrd_reader import read_text_rows

ROOT = Path(__file__).resolve().parents[1]
CRUISE = ROOT / "examples" / "cruise.toml"

USER_LAW = '''
from pydantic import Field
from ecu_sim.controllers.base import Controller, ControllerParams
from ecu_sim.view import Command, LocalView


class PushParams(ControllerParams):
    force_n: float = Field(default=1000.0)


class Push(Controller):
    """Every unit pushes with a constant force."""
    name = "push"
    Params = PushParams

    def step(self, view: LocalView) -> Command:
        return Command(force_n=self.params.force_n, accel_mps2=0.0)
'''

USER_PROGRAM = '''
from ecu_sim.programs import standard_program


def quiet_after_half_a_second(setup):
    """A factory: the standard firmware, which stops sending after t = 0.5 s."""
    ecu = standard_program(setup)
    cycle = ecu.cycle
    ecu.cycle = lambda t: [] if t > 0.5 else cycle(t)
    return ecu
'''


@pytest.fixture
def user_dir(tmp_path, monkeypatch):
    """A folder outside the repository with the user's law and program, as the current directory."""
    (tmp_path / "mylaw.py").write_text(USER_LAW)
    (tmp_path / "myecu.py").write_text(USER_PROGRAM)
    (tmp_path / "broken.py").write_text("import numpy\nraise RuntimeError('calibration table missing')\n")
    monkeypatch.chdir(tmp_path)
    yield tmp_path
    for name in ("mylaw", "myecu", "broken"):
        sys.modules.pop(name, None)


def traction_kn(run, train: int, unit: int) -> np.ndarray:
    return run.signals[f"/trains/{train}/units/{unit}/traction_kn"].v


def test_a_law_by_reference_from_the_current_directory_runs_on_every_unit(user_dir):
    run = Rig(CRUISE, set={"controller.law": "mylaw:Push", "controller.params": {"force_n": 2500.0}}).run(0.5)
    for train in (1, 2):
        for unit in (1, 2, 3):
            t = run.signals[f"/trains/{train}/units/{unit}/traction_kn"].t
            assert np.all(traction_kn(run, train, unit)[t >= 0.1] == 2.5)
    assert run.controller == "mylaw:Push"


def test_one_unit_runs_its_own_law_and_program_among_standard_ones(user_dir):
    sc = build_scenario(CRUISE, {"ecu.units": [{"unit": "train2/unit3", "law": "mylaw:Push", "params": {"force_n": 4000.0}},
                                               {"unit": "train1/unit2", "program": "myecu:quiet_after_half_a_second"}]})
    plan = firmware_plan(sc)
    assert [f.law for f in plan] == ["consensus"] * 5 + ["mylaw:Push"]
    assert plan[1].program == "myecu:quiet_after_half_a_second" and plan[0].program == "standard"
    run = Rig(sc).run(1.0)
    t = run.signals["/trains/2/units/3/traction_kn"].t
    assert np.all(traction_kn(run, 2, 3)[t >= 0.1] == 4.0)
    assert not np.all(traction_kn(run, 2, 2)[t >= 0.1] == 4.0)  # its neighbours keep the scenario's law
    assert run.frame_times(0x081, "bus1")[-1] <= 0.51  # train 1's unit 2 fell silent after 0.5 s ...
    assert run.frame_times(0x081, "bus2")[-1] > 0.95  # ... train 2's unit 2 did not


def test_load_errors_name_the_field_the_module_and_the_exception(user_dir):
    cases = [
        ({"controller.law": "nomodule:Law"}, "controller.law: 'nomodule:Law': no module named 'nomodule'"),
        ({"controller.law": "mylaw:Nope"}, "controller.law: 'mylaw:Nope': module 'mylaw' has no attribute 'Nope'"),
        ({"controller.law": "broken:Law"}, "controller.law: 'broken:Law': importing module 'broken' failed: "
                                           "RuntimeError: calibration table missing (broken.py, line 2)"),
        ({"controller.law": "pd_spacing"}, "controller.law: unknown controller law 'pd_spacing' (known: "),
        ({"ecu.program": "mylaw:Push"}, "ecu.program: 'mylaw:Push' is the class Push, not a subclass of "
                                        "ecu_sim.runtime.Ecu"),
        ({"ecu.units": [{"unit": "train1/unit1", "law": "mylaw:Push", "params": {"force": 1}}]},
         "ecu.units.0.params.force: Extra inputs are not permitted"),
        ({"ecu.units": [{"unit": "train3/unit1"}]}, "ecu.units.0.unit: 'train3/unit1': there is no train 3"),
        ({"ecu.units": [{"unit": "unit1"}]}, "ecu.units.0.unit: 'unit1' is not a unit name"),
        ({"ecu.external": ["train1/unit4"]}, "ecu.external.0: 'train1/unit4': a train has no unit 4"),
        ({"ecu.units": [{"unit": "train1/unit2"}], "ecu.external": ["train1/unit2"]},
         "ecu.external.0 = 'train1/unit2': already given in ecu.units.0.unit"),
    ]
    for sets, message in cases:
        with pytest.raises(ScenarioError) as err:
            build_scenario(CRUISE, sets)
        assert message in str(err.value), (sets, str(err.value))
        assert "Traceback" not in str(err.value)


def test_hil_run_takes_a_law_by_reference_and_reports_a_broken_one_without_traceback(user_dir):
    ok = subprocess.run([sys.executable, "-m", "hil", "run", str(CRUISE), "--set", "controller.law=mylaw:Push",
                         "--duration", "0.5", "--no-record", "--quiet", "--out", "r"], capture_output=True, text=True,
                        timeout=300, cwd=user_dir)
    assert ok.returncode == 0, ok.stderr
    bad = subprocess.run([sys.executable, "-m", "hil", "run", str(CRUISE), "--set", "controller.law=broken:Law",
                          "--duration", "0.5", "--quiet"], capture_output=True, text=True, timeout=300, cwd=user_dir)
    assert bad.returncode == 2
    assert bad.stderr.strip() == (f"hil: error: {CRUISE}: controller.law: 'broken:Law': importing module 'broken' "
                                  "failed: RuntimeError: calibration table missing (broken.py, line 2)")


def test_installed_packages_publish_laws_and_programs_by_entry_point(tmp_path, monkeypatch):
    pkg = tmp_path / "site"
    (pkg / "trainhil_plugin_demo").mkdir(parents=True)
    (pkg / "trainhil_plugin_demo" / "__init__.py").write_text(USER_LAW + USER_PROGRAM)
    dist = pkg / "trainhil_plugin_demo-1.0.dist-info"
    dist.mkdir()
    (dist / "METADATA").write_text("Metadata-Version: 2.1\nName: trainhil-plugin-demo\nVersion: 1.0\n")
    (dist / "entry_points.txt").write_text(textwrap.dedent("""
        [trainhil.controllers]
        demo_push = trainhil_plugin_demo:Push

        [trainhil.ecu_programs]
        demo_quiet = trainhil_plugin_demo:quiet_after_half_a_second
    """))
    monkeypatch.syspath_prepend(str(pkg))
    try:
        assert get_controller("demo_push").__name__ == "Push"
        assert callable(get_program("demo_quiet"))
        from ecu_sim.controllers.base import known_controllers
        from ecu_sim.programs import known_programs

        assert "demo_push" in known_controllers() and "demo_quiet" in known_programs()
        sc = build_scenario(CRUISE, {"controller.law": "demo_push", "ecu.program": "demo_quiet"})
        run = Rig(sc).run(1.0)
        assert run.frame_times(0x080, "bus1")[-1] <= 0.51
    finally:
        sys.modules.pop("trainhil_plugin_demo", None)


def test_an_external_unit_is_refused_outside_real_time_with_a_pointer_to_ecu_program(capsys, tmp_path):
    code = main(["run", str(CRUISE), "--external", "train2/unit3", "--duration", "0.5", "--no-record", "--quiet",
                 "--out", str(tmp_path / "r")])
    assert code == 2
    err = capsys.readouterr().err
    assert "ecu.external = ['train2/unit3']: an external unit needs a real-time run (hil run --realtime)" in err
    assert "name it in ecu.program" in err and not (tmp_path / "r").exists()  # refused before anything is written
    with pytest.raises(ScenarioError, match="not the ideal loop"):
        from hil.runtime.ideal import IdealLoop

        IdealLoop(build_scenario(CRUISE, {"ecu.external": ["train1/unit1"]}))


def test_a_program_that_returns_no_ecu_is_named(user_dir):
    (user_dir / "notecu.py").write_text("def make(setup):\n    return 42\n")
    try:
        with pytest.raises(ReferenceLoadError, match="ECU program 'notecu:make' returned int, not an ecu_sim.runtime.Ecu"):
            Rig(CRUISE, set={"ecu.program": "notecu:make"}).run(0.1)
    finally:
        sys.modules.pop("notecu", None)


# --------------------------------------------------------------------------- verdicts for CI


def test_check_exits_with_its_own_code_naming_the_verdicts_and_violations_reach_the_timeline(user_dir, capsys):
    """A law that pushes with 300 kN on every unit (power-limited to 4.8 MW) overspeeds within 10 s: --check fails the run (exit 3, not 2
    or 130), names the verdict, and the recording of this fault-free run has the violation as an event."""
    argv = ["run", str(CRUISE), "--set", "controller.law=mylaw:Push", "--set", "controller.params.force_n=300000.0",
            "--duration", "10", "--quiet", "--overwrite", "--out", str(user_dir / "r")]
    assert main(argv) == 0  # without --check the verdict is reported, not enforced
    assert main([*argv, "--check"]) == EXIT_UNSAFE == 3
    err = capsys.readouterr().err
    assert "hil: unsafe: overspeed (" in err and "first at t = " in err
    rows = read_text_rows(user_dir / "r" / "run.rrd", "/events/safety")
    texts = [text for entity_rows in rows.values() for _, text, _ in entity_rows]
    assert any(text.startswith("SAFETY overspeed on train 1 unit 1") for text in texts), texts
    assert main(["run", str(CRUISE), "--duration", "1", "--quiet", "--no-record", "--check",
                 "--out", str(user_dir / "safe")]) == 0


PLANTED = """
import os, pathlib
pathlib.Path(os.environ["PLANTED_MARKER"]).open("a").write(f"{os.getpid()}\\n")
raise ImportError("the planted module was imported")
"""


@pytest.mark.slow  # about 10 s: node start-up and 2 s of real time
def test_hil_run_realtime_runs_the_users_law_from_their_own_folder(user_dir):
    """The user's ./mylaw.py is found by every node, and modules planted in the same folder under the names of
    installed packages (cantools, numpy, can) are never imported: nodes start with ``python -P``."""
    marker = user_dir / "planted.log"
    for name in ("cantools", "numpy", "can", "scipy"):
        (user_dir / f"{name}.py").write_text(PLANTED)
    env = {**os.environ, "PLANTED_MARKER": str(marker)}
    proc = subprocess.run([sys.executable, "-P", "-m", "hil", "run", str(CRUISE), "--realtime", "--duration", "2",
                           "--ecus-per-process", "3", "--set", "controller.law=mylaw:Push",
                           "--set", "controller.params.force_n=2500.0", "--quiet", "--out", "rt"],
                          capture_output=True, text=True, timeout=300, cwd=user_dir, env=env)
    assert proc.returncode == 0, proc.stderr
    assert not marker.exists(), "a module planted in the working folder ran in a node: " + marker.read_text()
    from hil.record import load_run

    run = load_run(user_dir / "rt")
    t, v = run["/trains/2/units/3/traction_kn"]
    assert np.all(v[t >= 0.2] == 2.5)  # every ECU process imported ./mylaw.py and ran it
    assert run.metrics["runtime"] == "realtime"


def test_saturations_in_real_time_are_counted_once_per_encode_with_several_ecus_in_a_process(user_dir, tmp_path):
    """A law that always asks more than the DBC's Force signal carries: every TractionCmd it sends saturates, so each
    message's count is at most its units' cycles (and near them), though a process's ECUs share one set of codecs
    and each writes its own file (the merge once summed the process's count once per ECU: three times here)."""
    from hil.runtime.realtime.orchestrator import run_realtime

    sc = build_scenario(CRUISE, {"controller.law": "mylaw:Push", "controller.params": {"force_n": 1e9}})
    m = run_realtime(sc, tmp_path / "rt", duration_s=2.0, ecus_per_process=3, record=False).metrics
    cycles = {slot: sum(e["cycles"] for name, e in m["realtime"]["ecus"].items() if f"/unit{slot}/" in name)
              for slot in (1, 2, 3)}
    for slot, n in cycles.items():
        saturated = m["codec_saturations"][f"TractionCmd_U{slot:02d}.Force"]
        assert 0.8 * n <= saturated <= n, (slot, saturated, n)


def test_a_real_time_node_that_cannot_load_the_law_reports_the_whole_error(tmp_path):
    """A law registered in this process only is unknown to the node processes: the start-up error comes through
    whole, the node's last line included, not cut mid-word."""
    from ecu_sim.controllers.base import _REGISTRY, register
    from hil.runtime.realtime.orchestrator import NodeError, run_realtime

    class OnlyHere(get_controller("consensus")):  # registered here, not importable by the nodes
        name = "test_only_in_this_process"

    if OnlyHere.name not in _REGISTRY:
        register(OnlyHere)
    sc = build_scenario(CRUISE, {"controller.law": OnlyHere.name})
    with pytest.raises(NodeError) as err:
        run_realtime(sc, tmp_path, duration_s=1.0, ecus_per_process=6)
    stub = __import__("json").loads((tmp_path / "metrics.json").read_text())
    assert stub["status"] == "failed" and "hil recover" not in stub["note"]  # nothing ran: nothing to recover
    msg = str(err.value)
    assert "exited with code 1 before it was ready:" in msg
    assert "unknown controller law 'test_only_in_this_process' (known: " in msg
    assert "or a 'package.module:ClassName' reference)" in msg  # the end of the node's message
