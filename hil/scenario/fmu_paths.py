"""Where a scenario's FMUs are: paths made absolute against the file that names them, and the ``trainhil:`` names
of the reference FMUs built (once, into a cache) for the scenario, so that every process of a run sees one file.

FMUs are named by ``plant.fmu.path`` and by the laws ``controller.law`` and ``ecu.units.<i>.law`` of the form
``fmu:PATH``. ``trainhil:NAME`` (FMI 2) or ``trainhil:NAME@3`` (FMI 3) names a reference FMU (hil/fmi/build.py)."""
from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

from hil.fmi.build import REFERENCE_PREFIX, FmuBuildError, reference_fmu

LAW_PREFIX = "fmu:"


def _anchored(path: str, folder: Path) -> str:
    if path.startswith(REFERENCE_PREFIX) or Path(path).expanduser().is_absolute():
        return path
    return str((folder / Path(path).expanduser()).resolve())


def _anchored_law(law: Any, folder: Path) -> Any:
    if isinstance(law, str) and law.startswith(LAW_PREFIX):
        return LAW_PREFIX + _anchored(law.removeprefix(LAW_PREFIX), folder)
    return law


def anchor_fmu_paths(data: dict[str, Any], folder: Path) -> None:
    """Make the relative FMU paths of a parsed scenario table absolute against ``folder`` (in place)."""
    _each_fmu_field(data, lambda value, is_law: _anchored_law(value, folder) if is_law else _anchored(value, folder))


def _each_fmu_field(data: dict[str, Any], change: Callable[[str, bool], str]) -> None:
    """Apply ``change(value, is_law)`` to every FMU-naming string of a scenario table."""
    fmu = data.get("plant", {}).get("fmu") if isinstance(data.get("plant"), dict) else None
    if isinstance(fmu, dict) and isinstance(fmu.get("path"), str):
        fmu["path"] = change(fmu["path"], False)
    controller = data.get("controller")
    if isinstance(controller, dict) and isinstance(controller.get("law"), str):
        controller["law"] = change(controller["law"], True)
    units = data.get("ecu", {}).get("units") if isinstance(data.get("ecu"), dict) else None
    for entry in units if isinstance(units, list) else []:
        if isinstance(entry, dict) and isinstance(entry.get("law"), str):
            entry["law"] = change(entry["law"], True)


def reference_path(name: str, n_trains: int, units_per_train: int) -> str:
    """The built file of ``trainhil:NAME[@VERSION]``; a build failure is a ValueError naming the reference."""
    spec, _, version = name.removeprefix(REFERENCE_PREFIX).partition("@")
    if version not in ("", "2", "3"):
        raise ValueError(f"{name}: FMI version {version!r}: the reference FMUs are built for FMI 2 or 3 (@2, @3)")
    try:
        return str(reference_fmu(spec, int(version or 2), n_trains, units_per_train))
    except FmuBuildError as exc:
        raise ValueError(f"{name}: {exc}") from None


def resolve_references(data: dict[str, Any], n_trains: int, units_per_train: int) -> bool:
    """Replace every ``trainhil:`` FMU name of a scenario table by the path of the built reference FMU; True when
    there was one."""
    found = []

    def change(value: str, is_law: bool) -> str:
        body = value.removeprefix(LAW_PREFIX) if is_law else value
        if (is_law and not value.startswith(LAW_PREFIX)) or not body.startswith(REFERENCE_PREFIX):
            return value
        built = reference_path(body, n_trains, units_per_train)
        found.append(value)
        return LAW_PREFIX + built if is_law else built

    _each_fmu_field(data, change)
    return bool(found)
