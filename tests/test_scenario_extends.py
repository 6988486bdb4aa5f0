"""Scenario files inherit: ``extends = "seed000"`` (a packaged name, or a path next to the file) deep-merges the
base under the file's own keys. The packaged families are written as their differences, and each resolves to the
same content as before it was (the snapshot in tests/data, made from the whole files of commit 439ff8b^ loaded
with today's loader, which resolves ``controller.params`` to every parameter of the law, defaults included)."""
from __future__ import annotations

import json
from pathlib import Path

import pytest

from ecu_sim.controllers.base import get_controller
from hil.record.provenance import scenario_hash
from hil.scenario import ScenarioError, load_scenario, packaged_scenarios

SNAPSHOT = json.loads((Path(__file__).parent / "data" / "packaged_scenario_hashes.json").read_text())


def test_every_packaged_scenario_resolves_to_the_content_it_had_as_a_whole_file():
    assert set(SNAPSHOT) <= set(packaged_scenarios())
    changed = [name for name, digest in SNAPSHOT.items() if scenario_hash(load_scenario(name)) != digest]
    assert not changed, changed


def test_the_families_are_written_as_their_differences():
    import tomllib

    files = packaged_scenarios()
    bases = {n: tomllib.loads(p.read_text()).get("extends") for n, p in files.items()}
    derived = {n: b for n, b in bases.items() if b is not None}
    assert {"faults", "seed000-consensus", "seed000-limits", "seed001-fd", "seed004-kn", "seed004-ours"} <= set(derived)
    lines = {n: len(p.read_text().splitlines()) for n, p in files.items()}
    assert all(lines[n] < lines[b] for n, b in derived.items()), {n: (lines[n], lines[b]) for n, b in derived.items()}


def write(folder: Path, name: str, text: str) -> Path:
    path = folder / f"{name}.toml"
    path.write_text(text)
    return path


def test_tables_merge_values_and_arrays_replace_and_a_new_law_brings_its_own_params(tmp_path):
    write(tmp_path, "base", 'extends = "seed001"\nname = "base"\n[can]\nsensor_period_s = 0.01\n')
    child = write(tmp_path, "child", 'extends = "base.toml"\nname = "child"\n[can]\nbitrate = 500000\n'
                  '[controller]\nlaw = "cca"\n[trains]\nspeeds_mps = [1.0]\n')
    sc, seed001 = load_scenario(child), load_scenario("seed001")
    assert sc.name == "child" and sc.can.bitrate == 500_000 and sc.can.sensor_period_s == 0.01  # merged across two files
    assert sc.ecu == seed001.ecu and sc.trains.unit_positions_m == seed001.trains.unit_positions_m
    assert sc.trains.speeds_mps == [1.0]  # an array replaces
    cca_defaults = get_controller("cca").Params().model_dump(mode="json")
    assert sc.controller.law == "cca" and sc.controller.params == cca_defaults  # not STSMCA's c, k1, k2


@pytest.mark.parametrize("text, message", [
    ('extends = "no-such"\nname = "x"\n', "extends: unknown scenario 'no-such'"),
    ('extends = "gone.toml"\nname = "x"\n', "extends: no such scenario file"),
    ("extends = 3\nname = \"x\"\n", "extends: expected a packaged scenario name or a path"),
    ('extends = "loop.toml"\nname = "x"\n', "extends: a cycle (loop.toml -> loop.toml)"),
])
def test_a_bad_extends_is_named(tmp_path, text, message):
    path = write(tmp_path, "loop", text)
    with pytest.raises(ScenarioError, match=__import__("re").escape(message)):
        load_scenario(path)
    assert str(path) in _message(path)


def _message(path: Path) -> str:
    try:
        load_scenario(path)
    except ScenarioError as exc:
        return str(exc)
    return ""


def test_a_field_error_in_a_derived_file_is_still_named(tmp_path):
    path = write(tmp_path, "bad", 'extends = "seed000"\nname = "bad"\n[can]\nbitrate = 300000\n')
    with pytest.raises(ScenarioError, match=r"can\.bitrate"):
        load_scenario(path)


def test_a_resolved_scenario_names_every_parameter_its_law_runs_with():
    """seed004-ours writes only feedforward and gain_scale over seed004's params; the resolved scenario also has the
    law's defaults (rbf_centres, memory_window, ...), so its hash says what ran however the file wrote it."""
    sc = load_scenario("seed004-ours")
    law = get_controller(sc.controller.law)
    assert set(sc.controller.params) == set(law.Params.model_fields)
    assert sc.controller.params["gain_scale"] == 20.0 and sc.controller.params["force_unit"] == "N"
    assert law.Params(**sc.controller.params) == law.Params(**load_scenario("seed004").controller.params).model_copy(
        update={"feedforward": True, "gain_scale": 20.0})
