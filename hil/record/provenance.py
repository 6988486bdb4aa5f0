"""What produced a run, for its metrics.json: the scenario (name, source, a hash of its resolved content), the law
and its resolved parameters, the ECU programs, the train DBC (as named, and a hash of the file), the seed, every
override, the versions, the runtime and the pace.

The hash is over the validated scenario as JSON (every default filled in), so two runs with the same hash ran the
same scenario whatever files and ``--set`` options produced it.
"""
from __future__ import annotations

import hashlib
import importlib.metadata
import json
import platform
from typing import Any

from hil.scenario.model import Scenario


def scenario_hash(sc: Scenario) -> str:
    """sha256 (hex) of the resolved scenario as canonical JSON: keys sorted, so the order in which a file lists a
    table's keys (or the one an ``extends`` merge leaves) does not change it."""
    return hashlib.sha256(json.dumps(sc.model_dump(mode="json"), sort_keys=True).encode()).hexdigest()


def file_hash(path) -> str | None:
    """sha256 (hex) of a file's bytes; None when it cannot be read."""
    try:
        with open(path, "rb") as f:
            return hashlib.file_digest(f, "sha256").hexdigest()
    except OSError:
        return None


def provenance(sc: Scenario, runtime: str, seed: int, *, pace: float | None = None,
               overrides: dict[str, Any] | None = None, source: str | None = None) -> dict[str, Any]:
    """The ``provenance`` block of metrics.json (see the module docstring)."""
    import trainhil_engine

    from ecu_sim.controllers.base import get_controller
    from hil import __version__

    law = get_controller(sc.controller.law)
    return {
        "scenario": sc.name,
        "scenario_source": source,
        "scenario_sha256": scenario_hash(sc),
        "law": sc.controller.law,
        "law_params": law.Params(**sc.controller.params).model_dump(mode="json"),
        "ecu_program": sc.ecu.program,
        "ecu_units": [o.model_dump(mode="json", exclude_none=True) for o in sc.ecu.units],
        "external_units": list(sc.ecu.external),
        "dbc": sc.can.dbc,
        "dbc_sha256": file_hash(sc.can.dbc_path),  # a DBC of the user's own may change under the same name
        "seed": int(seed),
        "overrides": dict(overrides or {}),
        "runtime": runtime,
        "pace": pace,
        "version": __version__,
        "frame_engine": trainhil_engine.VERSION,
        "python": platform.python_version(),
        "rerun_sdk": importlib.metadata.version("rerun-sdk"),  # rerun's own __version__; importing it takes 0.3 s
    }
