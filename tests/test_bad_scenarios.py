"""Malformed scenario files: every one is a ScenarioError whose message names the file and the field.

Each case edits the packaged seed000 scenario (parsed, changed, written back as TOML), loads the file and checks
the message: wrong types, missing fields, unknown keys, impossible values (negative mass, overlapping trains,
NaN/inf, empty lists, durations shorter than a period, ...). A last case shows that the run itself never
starts on such a file: `hil run` exits 2 with one line per error and no traceback.
"""
from __future__ import annotations

import copy
import json
import math
import subprocess
import sys
import tomllib
from pathlib import Path
from typing import Any

import pytest

from hil.scenario import ScenarioError, load_scenario, packaged_scenarios

BASE = tomllib.loads(packaged_scenarios()["seed000"].read_text())
DELETE = object()


def toml_value(v: Any) -> str:
    """A TOML value (inline tables and arrays; nan/inf as TOML writes them)."""
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, float):
        return "nan" if math.isnan(v) else ("inf" if v > 0 else "-inf") if math.isinf(v) else repr(v)
    if isinstance(v, int):
        return str(v)
    if isinstance(v, str):
        return json.dumps(v)
    if isinstance(v, list):
        return "[" + ", ".join(toml_value(x) for x in v) + "]"
    if isinstance(v, dict):
        return "{ " + ", ".join(f"{json.dumps(k)} = {toml_value(x)}" for k, x in v.items()) + " }"
    raise TypeError(v)


def to_toml(data: dict[str, Any]) -> str:
    return "".join(f"{json.dumps(k)} = {toml_value(v)}\n" for k, v in data.items())


def edited(changes: dict[str, Any]) -> dict[str, Any]:
    """seed000 with dotted keys set (list items by index) or deleted (DELETE)."""
    data = copy.deepcopy(BASE)
    for dotted, value in changes.items():
        node: Any = data
        *parents, leaf = dotted.split(".")
        for part in parents:
            node = node[int(part)] if isinstance(node, list) else node[part]
        key: Any = int(leaf) if isinstance(node, list) else leaf
        if value is DELETE:
            del node[key]
        else:
            node[key] = value
    return data


# (case id, changes, substrings the message must contain besides the file name)
CASES: list[tuple[str, dict[str, Any], tuple[str, ...]]] = [
    # wrong types
    ("count-string", {"trains.count": "3"}, ("trains.count", "expected a number")),
    ("count-fraction", {"trains.count": 2.5}, ("trains.count",)),
    ("mass-word", {"trains.unit_mass_kg": "80t"}, ("trains.unit_mass_kg",)),
    ("mass-bool", {"trains.unit_mass_kg": True}, ("trains.unit_mass_kg", "got a boolean")),
    ("enabled-string", {"plant.limits.enabled": "no"}, ("plant.limits.enabled", "expected a boolean")),
    ("enabled-number", {"plant.limits.enabled": 0}, ("plant.limits.enabled", "expected a boolean")),
    ("bitrate-string", {"can.bitrate": "500000"}, ("can.bitrate",)),
    ("positions-scalar", {"trains.head_positions_m": 108800.0}, ("trains.head_positions_m",)),
    ("speed-list-item-string", {"trains.speeds_kmh": ["295", 275.0, 285.0]}, ("trains.speeds_kmh", "item 0")),
    ("segments-table", {"reference.segments": {"start": 0.0, "end": 1.0, "speed_kmh": 300.0}}, ("reference.segments",)),
    ("controller-string", {"controller": "finite_time"}, ("controller",)),
    ("duration-string", {"duration_s": "800"}, ("duration_s",)),
    ("blackouts-numbers", {"radio.blackouts": [1, 2]}, ("radio.blackouts.0",)),
    ("param-string", {"controller.params.p1": "fast"}, ("controller.params.p1",)),
    # missing fields
    ("no-mass", {"trains.unit_mass_kg": DELETE}, ("trains.unit_mass_kg", "Field required")),
    ("no-reference", {"reference": DELETE}, ("reference", "Field required")),
    ("no-law", {"controller.law": DELETE}, ("controller.law", "Field required")),
    ("no-duration", {"duration_s": DELETE}, ("duration_s", "Field required")),
    ("no-segment-end", {"reference.segments.0.end": DELETE}, ("reference.segments.0.end", "Field required")),
    ("no-speeds", {"trains.speeds_kmh": DELETE}, ("trains", "speeds_mps or speeds_kmh")),
    # unknown keys
    ("typo-top", {"durration_s": 800.0}, ("durration_s", "Extra inputs")),
    ("typo-trains", {"trains.unit_mass": 1.0}, ("trains.unit_mass", "Extra inputs")),
    ("typo-limits", {"plant.limits.max_force_n": 1.0}, ("plant.limits.max_force_n",)),
    ("typo-segment", {"reference.segments.1.speed_kph": 300.0}, ("reference.segments.1.speed_kph",)),
    ("unknown-param", {"controller.params.p9": 1.0}, ("controller.params.p9",)),
    ("unknown-law", {"controller.law": "no_such_law"}, ("controller.law",)),
    # impossible values
    ("negative-mass", {"trains.unit_mass_kg": -80e3}, ("trains.unit_mass_kg", "greater than 0")),
    ("zero-length", {"trains.unit_length_m": 0.0}, ("trains.unit_length_m",)),
    ("overlapping-trains", {"trains.head_positions_m": [108800.0, 108700.0, 102200.0]}, ("trains", "overlapping")),
    ("trains-out-of-order", {"trains.head_positions_m": [102200.0, 105000.0, 108800.0]}, ("trains", "overlapping")),
    ("emergency-above-spacing", {"trains.emergency_gap_m": 3500.0}, ("trains", "emergency_gap_m")),
    ("too-many-units", {"trains.units": 17}, ("trains.units",)),
    ("zero-trains", {"trains.count": 0}, ("trains.count",)),
    ("negative-duration", {"duration_s": -5.0}, ("duration_s",)),
    ("nan-duration", {"duration_s": math.nan}, ("duration_s", "finite number")),
    ("inf-duration", {"duration_s": math.inf}, ("duration_s", "finite number")),
    ("nan-mass", {"trains.unit_mass_kg": math.nan}, ("trains.unit_mass_kg", "finite number")),
    ("inf-position", {"trains.head_positions_m": [math.inf, 105000.0, 102200.0]}, ("trains.head_positions_m.0",)),
    ("nan-param", {"controller.params.p1": math.nan}, ("controller.params.p1", "finite")),
    ("inf-param", {"controller.params.gamma1": -math.inf}, ("controller.params.gamma1", "finite")),
    ("empty-positions", {"trains.head_positions_m": []}, ("trains", "head_positions_m has 0 values")),
    ("empty-segments", {"reference.segments": []}, ("reference.segments",)),
    ("duration-below-a-period", {"duration_s": 0.005}, ("duration_s", "shorter than")),
    ("zero-step", {"plant.step_s": 0.0}, ("plant.step_s",)),
    ("negative-cycle", {"ecu.cycle_s": -0.01}, ("ecu.cycle_s",)),
    ("cycle-not-a-step-multiple", {"ecu.cycle_s": 0.0105}, ("ecu.cycle_s", "whole multiple of plant.step_s")),
    ("band-reversed", {"plant.coupler_band_m": [0.1, -0.1]}, ("plant.coupler_band_m",)),
    ("band-one-value", {"plant.coupler_band_m": [0.1]}, ("plant.coupler_band_m",)),
    ("loss-above-one", {"radio.loss": {"model": "bernoulli", "p": 1.5}}, ("radio.loss.p",)),
    ("blackout-reversed", {"radio.blackouts": [{"start_m": 5000.0, "end_m": 1000.0}]}, ("radio.blackouts.0", "end_m")),
    ("grades-overlap", {"track": {"grades": [{"start_m": 0.0, "end_m": 2000.0, "grade_permille": 5.0},
                                             {"start_m": 1000.0, "end_m": 3000.0, "grade_permille": -5.0}]}},
     ("track.grades.1", "overlaps")),
    ("curve-empty", {"track": {"curves": [{"start_m": 10.0, "end_m": 10.0, "radius_m": 4000.0}]}}, ("track.curves.0",)),
    ("disturbance-train-missing", {"plant.disturbances": [{"kind": "step", "train": 9, "start_s": 1.0, "end_s": 2.0,
                                                           "amplitude_n": 1e3}]}, ("plant.disturbances.0.train",)),
    ("disturbance-ends-first", {"plant.disturbances": [{"kind": "step", "start_s": 5.0, "end_s": 2.0,
                                                        "amplitude_n": 1e3}]}, ("plant.disturbances.0", "end_s")),
    ("segments-gap", {"reference.segments.1.start": 162000.0}, ("reference", "contiguous")),
    ("x0-outside", {"reference.x0_m": 10.0}, ("reference", "x0_m")),
    ("reference-speed-zero", {"reference.segments.0.speed_kmh": 0.0}, ("reference.segments.0", "v_r > 0")),
    ("negative-seed", {"seed": -1}, ("seed", ">= 0")),
    ("name-with-slash", {"name": "../elsewhere"}, ("name",)),
    ("empty-name", {"name": " "}, ("name",)),
    ("queue-depth-zero", {"can.tx_queue_depth": 0}, ("can.tx_queue_depth",)),
    ("rotating-mass-factor", {"trains.rotating_mass_factor": 2.0}, ("trains.rotating_mass_factor",)),
]


@pytest.mark.parametrize(("changes", "expected"), [c[1:] for c in CASES], ids=[c[0] for c in CASES])
def test_malformed_scenario_names_file_and_field(tmp_path: Path, changes: dict[str, Any], expected: tuple[str, ...]) -> None:
    path = tmp_path / "bad.toml"
    path.write_text(to_toml(edited(changes)))
    with pytest.raises(ScenarioError) as err:
        load_scenario(path)
    msg = str(err.value)
    assert msg.startswith(str(path)), msg
    for part in expected:
        assert part in msg, f"{part!r} not in:\n{msg}"


def test_the_unedited_base_loads(tmp_path: Path) -> None:
    """The cases fail because of their edit: seed000 written back by the same writer is valid."""
    path = tmp_path / "good.toml"
    path.write_text(to_toml(edited({})))
    assert load_scenario(path) == load_scenario("seed000")


def test_at_least_thirty_cases() -> None:
    assert len(CASES) >= 30 and len({c[0] for c in CASES}) == len(CASES)


@pytest.mark.parametrize(("text", "expected"), [
    ("name = \n", "not valid TOML"),
    ("name = 'a'\nname = 'b'\n", "not valid TOML"),  # a duplicated key
    ("\x00\x01garbage", "not valid TOML"),
    ("", "duration_s"),  # an empty file: every required field is named
])
def test_unparseable_files_name_the_file(tmp_path: Path, text: str, expected: str) -> None:
    path = tmp_path / "broken.toml"
    path.write_text(text)
    with pytest.raises(ScenarioError, match=expected) as err:
        load_scenario(path)
    assert str(path) in str(err.value)


def test_non_utf8_and_directory_are_clear_errors(tmp_path: Path) -> None:
    path = tmp_path / "latin1.toml"
    path.write_bytes('name = "Zürich"\n'.encode("latin-1"))
    with pytest.raises(ScenarioError, match="latin1.toml"):
        load_scenario(path)
    folder = tmp_path / "dir.toml"
    folder.mkdir()
    with pytest.raises(ScenarioError, match="dir.toml"):
        load_scenario(folder)


def test_bad_overrides_name_the_field() -> None:
    with pytest.raises(ScenarioError, match="radio.latency_s"):
        load_scenario("seed000", {"radio.latency_s": math.nan})
    with pytest.raises(ScenarioError, match="'duration_s' is not a table"):
        load_scenario("seed000", {"duration_s.x": 1})


def test_cli_refuses_a_bad_file_with_every_error_and_no_traceback(tmp_path: Path) -> None:
    path = tmp_path / "bad.toml"
    path.write_text(to_toml(edited({"trains.unit_mass_kg": -1.0, "can.bitrate": 300000, "radio.rnage": 3})))
    out = tmp_path / "out"
    proc = subprocess.run([sys.executable, "-m", "hil", "run", str(path), "--out", str(out)],
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2 and "Traceback" not in proc.stderr
    for field in ("trains.unit_mass_kg", "can.bitrate", "radio.rnage"):
        assert field in proc.stderr
    assert not out.exists()  # nothing was written for a run that never started
