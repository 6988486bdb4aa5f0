"""Property: any TOML-like data given to the scenario (and sweep) loader is a valid Scenario or a ScenarioError
naming where it went wrong, never another exception.

Inputs are seed000 with random edits (a key set to a random TOML value, deleted, or added) and wholly random
tables; overrides (`--set`) get random dotted keys and values.
"""
from __future__ import annotations

import copy
import tomllib
from typing import Any

from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from hil.scenario import ScenarioError, packaged_scenarios
from hil.scenario.loader import scenario_from_dict
from hil.scenario.model import Scenario
from hil.sweep import SweepError
from hil.sweep.spec import sweep_from_dict

BASE = tomllib.loads(packaged_scenarios()["seed000"].read_text())
SETTINGS = settings(max_examples=150, deadline=None, database=None, suppress_health_check=[HealthCheck.too_slow])

KEYS = st.sampled_from(["count", "units", "start", "end", "speed_kmh", "p1", "law", "kind", "x", "model", "p",
                        "period_s", "name", "enabled", "grades", "segments", "train"]) | st.text(max_size=8)
SCALARS = (st.integers(-10**6, 10**6) | st.floats(allow_nan=True, allow_infinity=True) | st.booleans()
           | st.text(max_size=12) | st.sampled_from(["finite_time", "consensus", "bernoulli", "position", "time", "step"]))
TOML_VALUES = st.recursive(SCALARS, lambda inner: st.lists(inner, max_size=4) | st.dictionaries(KEYS, inner, max_size=4),
                           max_leaves=12)


def paths(node: Any, prefix: tuple = ()) -> list[tuple]:
    """Every key path inside a parsed TOML document (list items by index)."""
    out = []
    items = node.items() if isinstance(node, dict) else enumerate(node) if isinstance(node, list) else []
    for k, v in items:
        out.append(prefix + (k,))
        out += paths(v, prefix + (k,))
    return out


ALL_PATHS = paths(BASE)


@st.composite
def edited_scenarios(draw) -> dict[str, Any]:
    data = copy.deepcopy(BASE)
    for _ in range(draw(st.integers(1, 4))):
        path = draw(st.sampled_from(ALL_PATHS))
        node: Any = data
        try:
            for part in path[:-1]:
                node = node[part]
            action = draw(st.sampled_from(["set", "set", "delete", "add"]))
            if action == "set":
                node[path[-1]] = draw(TOML_VALUES)
            elif action == "delete":
                del node[path[-1]]
            elif isinstance(node, dict):
                node[draw(KEYS)] = draw(TOML_VALUES)
        except (KeyError, IndexError, TypeError):
            pass  # an earlier edit removed or replaced this path
    return data


def load_or_error(data: Any, overrides: dict[str, Any] | None = None) -> Scenario | ScenarioError:
    try:
        return scenario_from_dict(data, "<hypothesis>", overrides)
    except ScenarioError as exc:
        assert str(exc).startswith("<hypothesis>"), str(exc)
        return exc


@SETTINGS
@given(edited_scenarios())
def test_edited_seed000_is_a_scenario_or_a_scenario_error(data):
    result = load_or_error(data)
    if isinstance(result, ScenarioError):
        assert "\n" in str(result) or ":" in str(result)
    else:
        assert isinstance(result, Scenario)


@SETTINGS
@given(st.dictionaries(KEYS | st.sampled_from(list(BASE)), TOML_VALUES, max_size=8))
def test_random_tables_are_a_scenario_error(data):
    assert isinstance(load_or_error(data), ScenarioError)


DOTTED = st.lists(st.sampled_from(["trains", "radio", "loss", "p", "count", "latency_s", "controller", "params",
                                   "law", "plant", "limits", "x", "0"]), min_size=1, max_size=4).map(".".join)


@SETTINGS
@given(st.dictionaries(DOTTED, TOML_VALUES, max_size=3))
def test_random_overrides_are_applied_or_rejected_with_a_scenario_error(overrides):
    load_or_error(copy.deepcopy(BASE), overrides)


@SETTINGS
@given(st.dictionaries(st.sampled_from(["name", "base", "duration_s", "seeds", "axes", "overrides", "plots", "x"]),
                       TOML_VALUES, max_size=6))
def test_random_sweeps_are_a_sweep_error_or_valid(data):
    data.setdefault("base", "seed000")
    try:
        spec = sweep_from_dict(data, "<sweep>")
    except SweepError as exc:
        assert str(exc).startswith("<sweep>"), str(exc)
    else:
        assert spec.points
