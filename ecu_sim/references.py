"""User code by reference: ``"package.module:QualName"`` strings and entry points, resolved the same way everywhere.

A scenario names a control law (``controller.law``) or an ECU program (``ecu.program``) by a registered name or by
an import reference, as ``uvicorn main:app`` and python-can's ``can.interface`` entry points do. Installed packages
can publish names under the entry-point groups :data:`LAW_GROUP` and :data:`PROGRAM_GROUP`. Because the reference
is a string in the scenario, every process of a run (the virtual rig, each real-time node) resolves it itself.

Modules are looked up on ``sys.path``, then in the current directory, then in the folders of the environment
variable ``TRAINHIL_USER_PATH`` (the real-time rig sets it for its node processes to the folders it imported the
user's modules from), so ``hil run --set controller.law=mylaw:PDSpacing`` finds ``./mylaw.py``. Those folders
come *after* the installed packages: a file in the working folder named like one of them (``cantools.py``) is
never imported in its place. Failures raise :class:`ReferenceLoadError`, whose message
names the reference, the module and the exception, in one line.
"""
from __future__ import annotations

import importlib
import importlib.metadata
import os
import sys
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

LAW_GROUP = "trainhil.controllers"
USER_PATH_ENV = "TRAINHIL_USER_PATH"
PROGRAM_GROUP = "trainhil.ecu_programs"


class ReferenceLoadError(LookupError):
    """A name or ``module:QualName`` reference that does not resolve; the message says why, in one line."""


class FirmwareBuildError(ReferenceLoadError, ValueError):
    """A law or program that resolved but could not be built (its ``__init__`` raised, e.g. a parameter that does
    not fit the train); a ValueError too, as the law's own check was."""


def is_import_reference(text: str) -> bool:
    """``"package.module:QualName"`` (a colon with a module part before it), not a registered name."""
    module, sep, qualname = text.partition(":")
    return bool(sep and module and qualname)


def _import_module(module: str, reference: str):
    """Import ``module``, with the current directory and then ``TRAINHIL_USER_PATH``'s folders searched after
    ``sys.path`` (they stay there, so that the user's module can import its siblings later too)."""
    cwd = os.getcwd()
    for folder in [cwd, *filter(None, os.environ.get(USER_PATH_ENV, "").split(os.pathsep))]:
        if folder not in sys.path and not (folder == cwd and "" in sys.path):
            sys.path.append(folder)
    try:
        return importlib.import_module(module)
    except ModuleNotFoundError as exc:
        if exc.name and module.startswith(exc.name):
            raise ReferenceLoadError(f"{reference!r}: no module named {exc.name!r} (looked on sys.path and in {cwd})") from None
        raise ReferenceLoadError(f"{reference!r}: importing module {module!r} failed: {one_line(exc)}") from None
    except Exception as exc:  # the user's module raised at import: say which and what, no traceback
        raise ReferenceLoadError(f"{reference!r}: importing module {module!r} failed: {one_line(exc)}") from None


def one_line(exc: BaseException) -> str:
    """An exception as one line: its type, its words, and the file and line it was raised at."""
    where = ""
    tb = exc.__traceback__
    while tb is not None and tb.tb_next is not None:
        tb = tb.tb_next
    if tb is not None:
        where = f" ({Path(tb.tb_frame.f_code.co_filename).name}, line {tb.tb_lineno})"
    text = " ".join(str(exc).split())
    return f"{type(exc).__name__}: {text}{where}" if text else f"{type(exc).__name__}{where}"


def load_reference(reference: str) -> Any:
    """The object a ``"package.module:QualName"`` reference names (QualName may be dotted: ``Outer.Inner``)."""
    if not is_import_reference(reference):
        raise ReferenceLoadError(f"{reference!r} is not a 'package.module:QualName' reference")
    module_name, _, qualname = reference.partition(":")
    obj = _import_module(module_name, reference)
    for part in qualname.split("."):
        try:
            obj = getattr(obj, part)
        except AttributeError:
            raise ReferenceLoadError(f"{reference!r}: module {module_name!r} has no attribute {qualname!r}") from None
    return obj


def resolve(name: str, registry: Mapping[str, Any], group: str, check: Callable[[Any, str], Any], what: str,
            example: str) -> Any:
    """The one lookup of laws and programs: a name registered here, a ``module:QualName`` reference, or a name an
    installed package publishes in entry-point ``group``; ``check(obj, name)`` vets what was loaded. An unknown
    name is an error listing the known ones (``what``: "controller law"; ``example``: "ClassName")."""
    if name in registry:
        return registry[name]
    if is_import_reference(name):
        return check(load_reference(name), name)
    published = entry_point(group, name)
    if published is not None:
        return check(published, name)
    raise ReferenceLoadError(f"unknown {what} {name!r} (known: {', '.join(known_names(registry, group))}; "
                             f"or a 'package.module:{example}' reference)")


def known_names(registry: Mapping[str, Any], group: str) -> list[str]:
    """Registered and published names."""
    return sorted(set(registry) | set(entry_point_names(group)))


def entry_point(group: str, name: str) -> Any | None:
    """The object an installed package publishes as ``name`` in entry-point ``group``, or None if none does."""
    for ep in importlib.metadata.entry_points(group=group):
        if ep.name == name:
            try:
                return ep.load()
            except Exception as exc:
                raise ReferenceLoadError(f"{name!r}: entry point {ep.value!r} (group {group}) failed to load: "
                                         f"{one_line(exc)}") from None
    return None


def entry_point_names(group: str) -> list[str]:
    """Names published in an entry-point group (for "known: ..." lists)."""
    return sorted(ep.name for ep in importlib.metadata.entry_points(group=group))


def reference_of(obj: Any) -> str | None:
    """``"module:QualName"`` of a class or function defined at the top level of an importable module, else None
    (defined in ``__main__`` or inside a function: other processes cannot import it)."""
    module, qualname = getattr(obj, "__module__", None), getattr(obj, "__qualname__", "")
    if not module or module == "__main__" or not qualname or "<locals>" in qualname:
        return None
    return f"{module}:{qualname}"


def module_root(reference: str) -> Path | None:
    """The ``sys.path`` folder the reference's module is imported from (for child processes' ``TRAINHIL_USER_PATH``), or
    None when the module is not loaded here or has no file."""
    module = reference.partition(":")[0]
    mod = sys.modules.get(module)
    file = getattr(mod, "__file__", None)
    if not file:
        return None
    root = Path(file).resolve().parent
    for _ in range(module.count(".") + (1 if Path(file).name == "__init__.py" else 0)):
        root = root.parent
    return root
