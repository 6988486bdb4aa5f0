"""Test controller firmware on the rig with pytest (the ``trainhil`` pytest plugin, loaded automatically).

Fixture ``hil_rig`` builds a :class:`Rig` (a scenario, overrides, your controller class or ECU program); ``run()``
returns a :class:`HilRun` whose ``signals`` are numpy arrays keyed by the recording's entity paths; the
``assert_*`` helpers say which signal failed, when, and by how much. See docs/getting-started.md.

The names load lazily: pytest imports this package for its plugin in every session, which must stay cheap.
"""
from __future__ import annotations

import importlib
from typing import Any

_WHERE = {
    "E2E_ERRORS": "asserts", "HilAssertionError": "asserts", "assert_frame_period": "asserts",
    "assert_never_above": "asserts", "assert_never_below": "asserts", "assert_no_e2e_errors": "asserts",
    "assert_no_events": "asserts", "assert_settles": "asserts", "assert_within": "asserts",
    "HilRun": "results", "Series": "results", "Signals": "results",
    "Rig": "rig", "build_scenario": "rig",
}
__all__ = sorted(_WHERE)


def __getattr__(name: str) -> Any:
    if name not in _WHERE:
        raise AttributeError(f"module 'hil.testing' has no attribute {name!r}")
    value = getattr(importlib.import_module(f"hil.testing.{_WHERE[name]}"), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return __all__
