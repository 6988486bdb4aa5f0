"""Scenario loading: packaged names, and errors that name the file, the field and the bad value."""
from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from hil.scenario import ScenarioError, load_scenario, packaged_scenarios

SEED000 = packaged_scenarios()["seed000"]


def write_variant(tmp_path: Path, old: str, new: str) -> Path:
    text = SEED000.read_text()
    assert old in text, f"test setup: {old!r} not in seed000.toml"
    p = tmp_path / "bad.toml"
    p.write_text(text.replace(old, new, 1))
    return p


def test_every_packaged_scenario_loads():
    names = set(packaged_scenarios())
    assert {"seed000", "seed000-consensus", "seed000-limits"} <= names
    for name in names:
        sc = load_scenario(name)
        assert sc.name == name


def test_seed000_has_the_papers_numbers():
    sc = load_scenario("seed000")
    assert (sc.trains.count, sc.trains.units) == (3, 4)
    assert sc.trains.head_positions_m == [108800.0, 105000.0, 102200.0]
    assert sc.trains.initial_speeds_mps == pytest.approx([295 / 3.6, 275 / 3.6, 285 / 3.6])
    assert sc.controller.params["p1"] == 20.0 and sc.controller.params["alpha1"] == 0.9
    assert sc.plant.limits.enabled is False


@pytest.mark.parametrize("old,new,expected", [
    ("count = 3", "count = 0", "trains.count"),
    ("bitrate = 500000", "bitrate = 300000", "can.bitrate"),
    ("unit_mass_kg = 80e3", "unit_mass_kg = -1.0", "trains.unit_mass_kg"),
    ("range_m = 10000.0", "range_m = 10000.0\nrnage = 3", "radio.rnage"),
    ("p1 = 20.0", "p1 = 'fast'", "controller.params.p1"),
    ('law = "finite_time"', 'law = "no_such_law"', "controller.law"),
    ("speeds_kmh = [295.0, 275.0, 285.0]", "speeds_kmh = [295.0, 275.0]", "speeds_kmh has 2 values"),
    ("step_s = 0.001", "step_s = 0.003", "can.sensor_period_s = 0.01 must be a whole multiple of plant.step_s"),
])
def test_bad_fields_are_named(tmp_path, old, new, expected):
    path = write_variant(tmp_path, old, new)
    with pytest.raises(ScenarioError) as err:
        load_scenario(path)
    assert str(path) in str(err.value)
    assert expected in str(err.value)


def test_bad_toml_and_unknown_names(tmp_path):
    p = tmp_path / "broken.toml"
    p.write_text("name = \n")
    with pytest.raises(ScenarioError, match="not valid TOML"):
        load_scenario(p)
    with pytest.raises(ScenarioError, match="unknown scenario 'nope'"):
        load_scenario("nope")


def test_cli_reports_user_errors_without_traceback(tmp_path):
    path = write_variant(tmp_path, "bitrate = 500000", "bitrate = 300000")
    proc = subprocess.run([sys.executable, "-m", "hil", "run", str(path), "--out", str(tmp_path / "o")],
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2
    assert "can.bitrate" in proc.stderr and "Traceback" not in proc.stderr


def test_cli_set_overrides_fields(tmp_path):
    out = tmp_path / "o"
    proc = subprocess.run([sys.executable, "-m", "hil", "run", "seed000", "--duration", "1", "--out", str(out), "--quiet",
                           "--no-record", "--set", "can.bitrate=1000000", "--set", "controller.law=consensus",
                           "--set", "controller.params={}"], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    import json

    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["per_bus"]["bus1"]["load_max"] < 0.3  # half the 500 kbit/s load
    bad = subprocess.run([sys.executable, "-m", "hil", "run", "seed000", "--set", "radio.latency_s=-1"],
                         capture_output=True, text=True, timeout=120)
    assert bad.returncode == 2 and "radio.latency_s" in bad.stderr
