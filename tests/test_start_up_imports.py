"""What each process imports before it does its work: rerun (about 0.3 s) only where a recording or a live view is
made, and the plant's scipy (about 0.2 s) not in an ECU node, which builds firmware only. Every ``hil`` command
and every real-time node pays its imports at start (hil/deferred_mf4.py has the same kind of check for asammdf)."""
from __future__ import annotations

import json
import subprocess
import sys

import pytest

from hil.runtime.firmware import assemble_firmware
from hil.runtime.assembly import assemble
from hil.scenario import load_scenario

MODULES = ("rerun", "scipy")


def imported_after(code: str) -> dict[str, bool]:
    """Which of MODULES a fresh interpreter (``-P``: not this folder's files) holds after running ``code``, run the
    way the rig runs it: python-can imported first, as ``hil`` and the nodes import it (hil/deferred_mf4.py)."""
    probe = ("import json, sys\n"
             "from hil.deferred_mf4 import import_can_deferring_mf4\n"
             "import_can_deferring_mf4()\n"
             f"{code}\n"
             f"print(json.dumps({{m: m in sys.modules for m in {MODULES!r}}}))")
    proc = subprocess.run([sys.executable, "-P", "-c", probe], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    return json.loads(proc.stdout.splitlines()[-1])


@pytest.mark.parametrize("argv", [["scenarios"], ["bus-server", "--help"], ["recover", "--help"]])
def test_hil_commands_other_than_run_start_without_rerun_or_scipy(argv):
    code = ("import contextlib, io\n"
            "from hil.cli import main\n"
            "with contextlib.redirect_stdout(io.StringIO()):\n"
            "    try:\n"
            f"        main({argv!r})\n"
            "    except SystemExit:\n"
            "        pass")
    assert imported_after(code) == {"rerun": False, "scipy": False}


def test_an_ecu_node_imports_neither_rerun_nor_the_plant():
    assert imported_after("import hil.runtime.realtime.ecu_node") == {"rerun": False, "scipy": False}


def test_the_plant_node_and_the_orchestrator_import_rerun_only_to_record():
    assert imported_after("import hil.runtime.realtime.plant_node")["rerun"] is False
    assert imported_after("import hil.runtime.realtime.orchestrator")["rerun"] is False
    assert imported_after("import hil.runtime.realtime.merge as m, hil.scenario as s, hil.scenario.layout as l, "
                          "tempfile, pathlib\n"
                          "sc = s.load_scenario('seed000')\n"
                          "w = m.open_recording(sc, l.TrainLayout.from_config(sc.trains), "
                          "pathlib.Path(tempfile.mkdtemp()) / 'run.rrd', None, ['bus1'])")["rerun"] is True


def test_a_real_time_run_without_a_recording_never_imports_rerun(tmp_path):
    """The orchestrator's process, start to metrics.json (its provenance names rerun's version without it)."""
    out = tmp_path / "rt"
    code = ("import contextlib, io\n"
            "from hil.cli import main\n"
            "with contextlib.redirect_stdout(io.StringIO()):\n"
            f"    assert main(['run', 'seed000', '--realtime', '--no-record', '--duration', '0.5', '--quiet', "
            f"'--out', {str(out)!r}]) == 0")
    assert imported_after(code)["rerun"] is False
    assert json.loads((out / "metrics.json").read_text())["provenance"]["rerun_sdk"].startswith("0.")


def test_the_firmware_parts_are_the_full_assembly_s_without_the_plant():
    """An ECU node builds its ECUs from ``assemble_firmware``: the same layout, laws and plan as the runtimes'."""
    sc = load_scenario("seed000")
    fw, full = assemble_firmware(sc), assemble(sc)
    assert not hasattr(fw, "plant") and full.plant is not None
    assert fw.layout.n_units == full.layout.n_units == 12
    assert fw.firmware == full.firmware and fw.plant_info == full.plant_info
    assert [type(fw.law(u)) for u in range(12)] == [type(full.law(u)) for u in range(12)]
    assert [fw.law(u) is full.law(u) for u in range(12)] == [False] * 12  # each builds its own
    assert all(fw.law(u) is fw.law(u) for u in range(12))  # once


def test_a_process_builds_the_laws_of_the_units_it_runs_and_no_other(monkeypatch):
    """A real-time ECU node hosting units 0 and 5 builds those two laws (a heavy law, an FMU's instances), not all
    twelve; each once."""
    import hil.runtime.firmware as firmware
    from hil.runtime.train_db import load_train_db

    built: list[int] = []
    real = firmware.build_controller

    def counting(law, params, agent, info):
        built.append(agent.train * agent.n_units + agent.unit)  # seed000: 4 units a train
        return real(law, params, agent, info)

    monkeypatch.setattr(firmware, "build_controller", counting)
    sc = load_scenario("seed000")
    parts, db = assemble_firmware(sc), load_train_db(sc)
    assert built == []  # nothing before it is asked for
    ecus = [firmware.build_ecu(parts, db, u) for u in (0, 5, 0)]
    assert built == [0, 5] and ecus[0].controller is ecus[2].controller
