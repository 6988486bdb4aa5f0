"""python-can's MF4 support deferred (hil/deferred_mf4.py): the ``hil`` command and the real-time nodes start
without importing asammdf (0.5-0.9 s: pandas, and sympy where installed); the first MF4 writer or reader loads it, in a
run that writes MF4 or in a user's firmware, and a user's own ``import asammdf`` still works."""
from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest

pytest.importorskip("asammdf")  # installed (the dev extra): otherwise nothing is deferred and nothing to check

HEAVY = ("asammdf", "pandas")  # asammdf requires pandas


def python(code: str, *args: str, env: dict[str, str] | None = None) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-P", *args, *(["-c", code] if code else [])], capture_output=True,
                          text=True, timeout=120, env=env)


def test_python_can_imported_as_usual_loads_asammdf():
    """The cost deferred is real: plain ``import can`` pulls asammdf and with it pandas."""
    proc = python(f"import json, sys, can; print(json.dumps([m in sys.modules for m in {HEAVY!r}]))")
    assert proc.returncode == 0, proc.stderr
    assert json.loads(proc.stdout) == [True, True]


def test_the_hil_command_starts_without_asammdf():
    code = ("import io, sys, contextlib, json; sys.argv = ['hil', 'scenarios']\n"
            "from hil.__main__ import main\n"
            "with contextlib.redirect_stdout(io.StringIO()) as out: code = main()\n"
            f"print(json.dumps([code, 'seed000' in out.getvalue(), [m in sys.modules for m in {HEAVY!r}]]))")
    proc = python(code)
    assert proc.returncode == 0, proc.stderr
    assert json.loads(proc.stdout) == [0, True, [False, False]]


def test_a_node_process_starts_without_asammdf_and_runs_its_module(tmp_path):
    """``node_start`` runs the module named first as ``__main__``, with the arguments after it and its exit code."""
    (tmp_path / "probe.py").write_text(
        "import json, sys, can\n"
        f"print(json.dumps([__name__, sys.argv[1:], [m in sys.modules for m in {HEAVY!r}]]))\n"
        "sys.exit(3)\n")
    env = {**os.environ, "PYTHONPATH": str(tmp_path)}
    proc = python("", "-m", "hil.runtime.realtime.node_start", "probe", "--unit", "2", env=env)
    assert proc.returncode == 3, proc.stderr
    assert json.loads(proc.stdout) == ["__main__", ["--unit", "2"], [False, False]]
    bare = python("", "-m", "hil.runtime.realtime.node_start")
    assert bare.returncode == 1 and "usage: python -m hil.runtime.realtime.node_start MODULE" in bare.stderr


def test_after_the_deferred_import_the_first_mf4_writer_loads_asammdf_and_asammdf_imports_as_usual(tmp_path):
    path = tmp_path / "x.mf4"
    code = ("import sys\n"
            "from hil.deferred_mf4 import import_can_deferring_mf4\n"
            "import_can_deferring_mf4(); assert 'asammdf' not in sys.modules\n"
            "import can\n"
            f"w = can.MF4Writer({str(path)!r})\n"
            "print('asammdf' in sys.modules)\n"
            "w.on_message_received(can.Message(timestamp=1.5, arbitration_id=0x123, data=b'\\x01\\x02', channel=0))\n"
            "w.stop()\n"
            f"print([(m.arbitration_id, bytes(m.data).hex()) for m in can.MF4Reader({str(path)!r})])\n"
            "import asammdf; print(asammdf.__name__)\n")
    proc = python(code)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.split("\n")[:3] == ["True", "[(291, '0102')]", "asammdf"]


def test_firmware_in_a_node_process_logs_mf4_through_python_can_as_anywhere(tmp_path):
    """A user's module run by ``node_start`` (as an ECU program would be) writes and reads MF4 with python-can's
    ``Logger`` and ``LogReader``, which pick the MF4 classes by the file's suffix: nothing to enable."""
    path = tmp_path / "fw.mf4"
    (tmp_path / "probe.py").write_text(
        "import json, sys, can\n"
        "before = 'asammdf' in sys.modules\n"
        f"with can.Logger({str(path)!r}) as log:\n"
        "    log(can.Message(timestamp=2.0, arbitration_id=0x0C1, data=bytes(8), channel=0))\n"
        f"print(json.dumps([before, [m.arbitration_id for m in can.LogReader({str(path)!r})]]))\n")
    env = {**os.environ, "PYTHONPATH": str(tmp_path)}
    proc = python("", "-m", "hil.runtime.realtime.node_start", "probe", env=env)
    assert proc.returncode == 0, proc.stderr
    assert json.loads(proc.stdout) == [False, [0x0C1]]


def test_without_asammdf_the_mf4_writer_refuses_as_python_can_does(tmp_path):
    code = ("import sys\n"
            "from hil.deferred_mf4 import import_can_deferring_mf4\n"
            "import_can_deferring_mf4()\n"
            "sys.modules['asammdf'] = None  # as if it were not installed\n"
            "import can\n"
            f"try:\n    can.MF4Writer({str(tmp_path / 'x.mf4')!r})\n"
            "except NotImplementedError as exc:\n    print('refused:', 'asammdf' in str(exc))\n")
    proc = python(code)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.strip() == "refused: True"
