"""The firmware package stands alone (docs/architecture.md: firmware never touches the rig): importing every module of
``ecu_sim`` loads nothing of ``hil``."""
from __future__ import annotations

import pkgutil
import subprocess
import sys

import ecu_sim


def test_ecu_sim_imports_nothing_from_hil():
    modules = sorted(m.name for m in pkgutil.walk_packages(ecu_sim.__path__, "ecu_sim."))
    assert "ecu_sim.runtime" in modules and "ecu_sim.controllers.multi_train" in modules
    code = (f"import importlib, sys; [importlib.import_module(m) for m in {modules!r}]; "
            "bad = sorted(m for m in sys.modules if m == 'hil' or m.startswith('hil.')); assert not bad, bad")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr[-2000:]
