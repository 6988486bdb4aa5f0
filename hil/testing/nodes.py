"""Make the user's controller class and ECU program exist in the real-time rig's node processes.

The real-time ECU nodes are fresh ``python -m hil.realtime.ecu_node`` processes that build their firmware from the
scenario (law by name). For a law or ECU program defined in the user's own module, :func:`node_imports` puts a
``sitecustomize`` module on the nodes' ``PYTHONPATH`` (Python imports it at start-up, before the node's own code)
that imports the user's modules, registers the controller class if its module does not, and swaps the ECU program
in, exactly as the virtual rig does. An existing ``sitecustomize`` is still run first. Nothing changes for runs
without user code; the parent's environment is restored afterwards.
"""
from __future__ import annotations

import contextlib
import os
import shutil
import sys
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import Any

ENV_CONTROLLER = "TRAINHIL_NODE_CONTROLLER"
ENV_ECU = "TRAINHIL_NODE_ECU"

SHIM = '''"""trainhil test shim (hil.testing.nodes): import the user's controller and ECU program in this node process."""
import os
import sys



def _run_original_sitecustomize():
    """The environment's own sitecustomize, if there is one further down sys.path."""
    import importlib.machinery
    import importlib.util

    here = os.path.dirname(os.path.abspath(__file__))
    rest = [p for p in sys.path if os.path.abspath(p or ".") != here]
    spec = importlib.machinery.PathFinder.find_spec("sitecustomize", rest)
    if spec is not None and spec.loader is not None:
        module = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(module)


_run_original_sitecustomize()


def _resolve(spec):
    import importlib

    module, _, qualname = spec.partition(":")
    obj = importlib.import_module(module)
    for part in qualname.split("."):
        obj = getattr(obj, part)
    return obj


try:
    if os.environ.get("{controller}"):
        from hil.testing.rig import ensure_registered

        ensure_registered(_resolve(os.environ["{controller}"]))
    if os.environ.get("{ecu}"):
        import hil.runtime.virtual as _virtual
        from hil.testing.rig import ecu_factory

        _virtual.build_ecu = ecu_factory(_resolve(os.environ["{ecu}"]))
except Exception as exc:  # a node must say why it cannot run the user's firmware
    print(f"trainhil: cannot load the firmware under test in this node: {{exc!r}}", file=sys.stderr)
    raise
'''.format(controller=ENV_CONTROLLER, ecu=ENV_ECU)


def import_spec(obj: Any, what: str) -> tuple[str, Path]:
    """("module:qualname", the sys.path root that module is imported from) of a module-level class or function."""
    module, qualname = getattr(obj, "__module__", None), getattr(obj, "__qualname__", "")
    if not module or module == "__main__" or "<locals>" in qualname:
        raise ValueError(f"{what} {qualname or obj!r} must be defined at the top level of an importable module to run "
                         f"in real time (the rig's node processes import it from there); it is in {module!r}")
    mod = sys.modules.get(module)
    file = getattr(mod, "__file__", None)
    if not file:
        raise ValueError(f"{what} {qualname}: module {module!r} has no file to import in the node processes")
    root = Path(file).resolve().parent
    depth = module.count(".") + (1 if Path(file).name == "__init__.py" else 0)
    for _ in range(depth):
        root = root.parent
    return f"{module}:{qualname}", root


@contextlib.contextmanager
def node_imports(controller: Any | None, ecu: Any | None) -> Iterator[None]:
    """While active, node processes started from here load ``controller`` (a class) and ``ecu`` (a class or factory)."""
    specs = {}
    roots: list[str] = []
    for env, obj, what in ((ENV_CONTROLLER, controller, "controller"), (ENV_ECU, ecu, "ECU program")):
        if obj is not None:
            spec, root = import_spec(obj, what)
            specs[env] = spec
            if str(root) not in roots:
                roots.append(str(root))
    if not specs:
        yield
        return
    shim_dir = tempfile.mkdtemp(prefix="trainhil-shim-")
    Path(shim_dir, "sitecustomize.py").write_text(SHIM)
    saved = {k: os.environ.get(k) for k in (*specs, "PYTHONPATH")}
    try:
        os.environ.update(specs)
        old = os.environ.get("PYTHONPATH")
        os.environ["PYTHONPATH"] = os.pathsep.join([shim_dir, *roots, *([old] if old else [])])
        yield
    finally:
        for k, v in saved.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v
        shutil.rmtree(shim_dir, ignore_errors=True)
