"""Load and validate scenario files: packaged names or paths, errors that name file, field and value."""
from __future__ import annotations

import tomllib
from importlib import resources
from pathlib import Path
from typing import Any

from pydantic import ValidationError

from hil.scenario.model import Scenario


class ScenarioError(ValueError):
    """A user error in a scenario file: the message names the file, the field and the bad value."""


def packaged_files(folder: str) -> dict[str, Path]:
    """Packaged TOML files of ``hil/<folder>/`` by name (scenarios, sweeps)."""
    return {p.stem: p for p in sorted(Path(str(resources.files("hil") / folder)).glob("*.toml"))}


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
    from hil.runtime.firmware import firmware_errors

    errors = firmware_errors(scenario)
    if len(errors) == 1 and "\n" not in errors[0]:
        raise ScenarioError(f"{source}: {errors[0]}")
    if errors:
        n = len(errors)
        raise ScenarioError(f"{source}: invalid scenario ({n} error{'s' if n > 1 else ''})\n  " + "\n  ".join(errors))


def scenario_from_dict(data: dict[str, Any], source: str = "<scenario>", overrides: dict[str, Any] | None = None) -> Scenario:
    """Validate a parsed scenario (``overrides``: dotted keys -> values, applied first)."""
    for dotted, value in (overrides or {}).items():
        node = data
        *parents, leaf = dotted.split(".")
        for part in parents:
            node = node.setdefault(part, {})
            if not isinstance(node, dict):
                raise ScenarioError(f"{source}: override {dotted!r}: {part!r} is not a table")
        node[leaf] = value
    try:
        scenario = Scenario(**data)
    except ValidationError as exc:
        raise ScenarioError(format_validation_errors(source, exc)) from None
    except RecursionError:
        raise ScenarioError(f"{source}: nested too deeply (arrays or tables inside each other beyond what a "
                            "scenario has)") from None
    _validate_firmware(source, scenario)
    return scenario


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


def load_scenario(name_or_path: str | Path, overrides: dict[str, Any] | None = None) -> Scenario:
    """Read, parse and validate a scenario; every failure is a ScenarioError naming the file."""
    path = resolve(name_or_path)
    return scenario_from_dict(read_toml(path, ScenarioError), str(path), overrides)


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
