"""Load and validate scenario files: packaged names or paths, errors that name file, field and value."""
from __future__ import annotations

import tomllib
from importlib import resources
from pathlib import Path
from typing import Any

from pydantic import ValidationError

from hil.scenario.fmu_paths import anchor_fmu_paths, resolve_references
from hil.scenario.model import Scenario


class ScenarioError(ValueError):
    """A user error in a scenario file: the message names the file, the field and the bad value."""


def packaged_files(folder: str) -> dict[str, Path]:
    """Packaged TOML files of ``hil/packaged/<folder>/`` by name (scenarios, sweeps)."""
    return {p.stem: p for p in sorted(Path(str(resources.files("hil") / "packaged" / folder)).glob("*.toml"))}


def resolve_packaged(name_or_path: str | Path, folder: str, kind: str, error: type[ValueError]) -> Path:
    """A packaged name (``seed000``) or a path to a TOML file; ``error(...)`` names what was not found."""
    p = Path(name_or_path)
    if p.suffix == ".toml" or p.exists():
        if not p.is_file():
            raise error(f"{p}: no such {kind} file")
        return p
    known = packaged_files(folder)
    if str(name_or_path) in known:
        return known[str(name_or_path)]
    raise error(f"unknown {kind} {str(name_or_path)!r}: not a file, and not a packaged {kind} ({', '.join(known)})")


def packaged_scenarios() -> dict[str, Path]:
    """Packaged scenario name -> file."""
    return packaged_files("scenarios")


def resolve(name_or_path: str | Path) -> Path:
    """A packaged scenario name (``seed000``) or a path to a TOML file."""
    return resolve_packaged(name_or_path, "scenarios", "scenario", ScenarioError)


def format_validation_errors(source: str, err: ValidationError, what: str = "scenario") -> str:
    """One line per pydantic error: the dotted field, the message and the bad value."""
    lines = [f"{source}: invalid {what} ({err.error_count()} error{'s' if err.error_count() > 1 else ''})"]
    for e in err.errors():
        where = ".".join(str(part) for part in e["loc"]) or "(top level)"
        got = e.get("input")
        shown = "" if isinstance(got, dict) else f" (got {got!r})"
        lines.append(f"  {where}: {e['msg']}{shown}")
    return "\n".join(lines)


def _validate_firmware(source: str, scenario: Scenario) -> None:
    """Every law, its parameters and every ECU program load and validate, so errors surface at load, not mid-run
    (a ``module:QualName`` reference is imported here: the error names the field, the module and the exception)."""
    from hil.scenario.firmware import firmware_errors

    errors = firmware_errors(scenario)
    if len(errors) == 1 and "\n" not in errors[0]:
        raise ScenarioError(f"{source}: {errors[0]}")
    if errors:
        n = len(errors)
        raise ScenarioError(f"{source}: invalid scenario ({n} error{'s' if n > 1 else ''})\n  " + "\n  ".join(errors))


def scenario_from_dict(data: dict[str, Any], source: str = "<scenario>", overrides: dict[str, Any] | None = None) -> Scenario:
    """Validate a parsed scenario (``overrides``: dotted keys -> values, applied first).

    As with ``extends``, a ``controller.law`` override naming another law brings only its own parameters: the old
    law's ``controller.params`` are dropped, except those the overrides set themselves."""
    overrides = overrides or {}
    old_law = _table(data, "controller").get("law")
    if "controller.law" in overrides and overrides["controller.law"] != old_law and isinstance(data.get("controller"), dict):
        data["controller"]["params"] = {}  # another law's parameters would not fit it
    for dotted, value in overrides.items():
        node = data
        *parents, leaf = dotted.split(".")
        for part in parents:
            node = node.setdefault(part, {})
            if not isinstance(node, dict):
                raise ScenarioError(f"{source}: override {dotted!r}: {part!r} is not a table")
        node[leaf] = value
    anchor_fmu_paths(data, Path.cwd())  # an override's relative FMU path is the current folder's
    try:
        scenario = Scenario(**data)
        if resolve_references(data, scenario.trains.count, scenario.trains.units):
            scenario = Scenario(**data)
    except ValidationError as exc:
        raise ScenarioError(format_validation_errors(source, exc)) from None
    except ValueError as exc:  # a reference FMU that cannot be built (no gcc): named, before anything runs
        raise ScenarioError(f"{source}: {exc}") from None
    except RecursionError:
        raise ScenarioError(f"{source}: nested too deeply (arrays or tables inside each other beyond what a "
                            "scenario has)") from None
    _validate_firmware(source, scenario)
    return with_full_law_params(scenario)


def with_full_law_params(scenario: Scenario) -> Scenario:
    """The scenario with ``controller.params`` as the law runs them: every parameter, defaults included, so the
    resolved scenario (and its hash in a run's provenance) says what ran, however the file wrote it."""
    from ecu_sim.controllers.base import get_controller

    params = get_controller(scenario.controller.law).Params(**scenario.controller.params).model_dump(mode="json")
    controller = scenario.controller.model_copy(update={"params": params})
    return scenario.model_copy(update={"controller": controller})


def read_toml(path: Path, error: type[ValueError]) -> dict[str, Any]:
    """Parse a TOML file; unreadable or malformed files raise ``error`` naming the file."""
    try:
        return tomllib.loads(path.read_text(encoding="utf-8"))
    except tomllib.TOMLDecodeError as exc:
        raise error(f"{path}: not valid TOML: {exc}") from None
    except RecursionError:
        raise error(f"{path}: not valid TOML here: nested too deeply") from None
    except UnicodeDecodeError as exc:
        raise error(f"{path}: not valid TOML: not UTF-8 text (byte {exc.start}: {exc.reason})") from None
    except OSError as exc:
        raise error(f"{path}: cannot read: {exc.strerror}") from None


MAX_EXTENDS = 8  # a chain of scenario files extending each other longer than this is a mistake


def read_scenario_data(path: Path, error: type[ValueError] = ScenarioError, _chain: tuple[Path, ...] = ()) -> dict[str, Any]:
    """A scenario file's table with its ``extends`` resolved: the base scenario (a packaged name, or a path
    relative to this file) deep-merged under this file's own keys. Tables merge key by key; a value or an array
    replaces the base's; a ``controller.law`` other than the base's brings only its own ``controller.params``
    (another law's parameters would not fit it)."""
    data = read_toml(path, error)
    anchor_fmu_paths(data, path.parent)  # an FMU path is relative to the file that names it
    base = data.pop("extends", None)
    if base is None:
        return data
    if not isinstance(base, str) or not base.strip():
        raise error(f"{path}: extends: expected a packaged scenario name or a path to a .toml file, got {base!r}")
    chain = (*_chain, path.resolve())
    if len(chain) > MAX_EXTENDS:
        raise error(f"{path}: extends: more than {MAX_EXTENDS} files extend each other")
    base_path = _extends_path(base, path, error)
    if base_path.resolve() in chain:
        names = " -> ".join(p.name for p in (*chain, base_path))
        raise error(f"{path}: extends: a cycle ({names})")
    base_data = read_scenario_data(base_path, error, chain)
    merged = deep_merge(base_data, data)
    own = data.get("controller")
    if isinstance(own, dict) and "law" in own and own["law"] != _table(base_data, "controller").get("law"):
        merged["controller"]["params"] = dict(_table(own, "params"))  # a new law: its own parameters only
    return merged


def _table(data: dict[str, Any], key: str) -> dict[str, Any]:
    value = data.get(key)
    return value if isinstance(value, dict) else {}


def _extends_path(base: str, path: Path, error: type[ValueError]) -> Path:
    """The file ``extends = base`` names: a path relative to ``path``'s folder, else a packaged scenario."""
    local = path.parent / base
    if base.endswith(".toml") or local.exists():
        if not local.is_file():
            raise error(f"{path}: extends: no such scenario file {local}")
        return local
    known = packaged_scenarios()
    if base not in known:
        raise error(f"{path}: extends: unknown scenario {base!r}: not a file next to it, and not a packaged scenario "
                    f"({', '.join(known)})")
    return known[base]


def deep_merge(base: dict[str, Any], over: dict[str, Any]) -> dict[str, Any]:
    """``base`` with ``over`` on top: tables merge key by key, anything else in ``over`` replaces."""
    out = dict(base)
    for key, value in over.items():
        if isinstance(value, dict) and isinstance(out.get(key), dict):
            out[key] = deep_merge(out[key], value)
        else:
            out[key] = value
    return out


def load_scenario(name_or_path: str | Path, overrides: dict[str, Any] | None = None) -> Scenario:
    """Read, parse and validate a scenario; every failure is a ScenarioError naming the file."""
    path = resolve(name_or_path)
    return scenario_from_dict(read_scenario_data(path), str(path), overrides)


def parse_assignment(text: str) -> tuple[str, object]:
    """``dotted.key=value`` with the value read as TOML (numbers, booleans, strings, arrays, inline tables)."""
    key, sep, raw = text.partition("=")
    if not sep or not key.strip():
        raise ScenarioError(f"--set {text!r}: expected dotted.key=value, e.g. radio.latency_s=0.2")
    try:
        value = tomllib.loads(f"v = {raw}")["v"]
    except tomllib.TOMLDecodeError:
        value = raw  # a bare word: take it as a string (e.g. controller.law=consensus)
    return key.strip(), value
