"""What a new user trips over: a run says what produced it, a second run does not silently replace the
first, and sweep plots label values that differ by little, and bit rates, readably."""
from __future__ import annotations

import hashlib
import json
from pathlib import Path

import numpy as np
import pytest

from ecu_sim.codec import default_dbc_path
from hil.cli import main
from hil.record.provenance import scenario_hash
from hil.scenario import load_scenario
from hil.sweep.plots import _fmt, _value_text, value_decimals

ROOT = Path(__file__).resolve().parents[1]
CRUISE = ROOT / "examples" / "cruise.toml"


def test_metrics_say_what_produced_the_run(tmp_path):
    out = tmp_path / "r"
    assert main(["run", str(CRUISE), "--duration", "0.5", "--seed", "3", "--set", "radio.latency_s=0.2",
                 "--no-record", "--quiet", "--out", str(out)]) == 0
    prov = json.loads((out / "metrics.json").read_text())["provenance"]
    resolved = load_scenario(CRUISE, {"radio.latency_s": 0.2, "seed": 3})
    assert prov["scenario"] == "cruise" and prov["scenario_source"] == str(CRUISE)
    assert prov["scenario_sha256"] == scenario_hash(resolved) != scenario_hash(load_scenario(CRUISE))
    assert prov["law"] == "consensus" and prov["law_params"]["cancel_coupler"] is not None  # defaults filled in
    assert prov["seed"] == 3 and prov["overrides"] == {"radio.latency_s": 0.2, "seed": 3, "duration_s": 0.5}
    assert prov["runtime"] == "virtual" and prov["pace"] is None and prov["ecu_program"] == "standard"
    assert prov["version"] and prov["frame_engine"] and prov["rerun_sdk"].startswith("0.41")
    assert prov["dbc"] == "train.dbc" and prov["dbc_sha256"] == hashlib.sha256(default_dbc_path().read_bytes()).hexdigest()


def test_the_same_scenario_spelled_another_way_has_the_same_hash(tmp_path):
    variant = tmp_path / "cruise-latency.toml"
    variant.write_text(CRUISE.read_text() + "\n[radio]\nlatency_s = 0.2\n")
    assert scenario_hash(load_scenario(variant)) == scenario_hash(load_scenario(CRUISE, {"radio.latency_s": 0.2}))


def test_a_second_run_into_the_same_directory_is_refused_unless_overwrite(tmp_path, capsys):
    out = tmp_path / "r"
    argv = ["run", str(CRUISE), "--duration", "0.3", "--quiet", "--can-log", "--out", str(out)]
    assert main(argv) == 0 and (out / "bus2.asc").exists()
    before = (out / "metrics.json").read_text()
    assert main(argv) == 2
    assert f"{out} holds a previous run (written " in capsys.readouterr().err
    assert (out / "metrics.json").read_text() == before  # nothing touched
    assert main(["run", str(CRUISE), "--duration", "0.3", "--quiet", "--overwrite", "--out", str(out)]) == 0
    assert not (out / "bus2.asc").exists()  # the old run's files went first: nothing stale is mistaken for new
    assert main(["run", str(CRUISE), "--duration", "0.3", "--quiet", "--out", str(out / "metrics.json")]) == 2


@pytest.mark.parametrize(("bad", "said"), [
    (["--realtime", "--pace", "0"], "argument --pace: 0 must be a finite number > 0"),
    (["--realtime", "--ecus-per-process", "0"], "argument --ecus-per-process: 0 must be > 0"),
    (["--realtime", "--run", "a/b"], "--run name 'a/b' is invalid"),
    (["--connect", "rerun+http://127.0.0.1:9876/proxy", "--serve", "0"], "--connect and --serve exclude each other"),
])
def test_a_bad_option_with_overwrite_is_refused_before_the_previous_run_goes(tmp_path, capsys, bad, said):
    """--overwrite removes the previous run's files only once every option has passed: a mistyped one loses nothing
    (a bad --pace once emptied the folder, then failed)."""
    out = tmp_path / "r"
    assert main(["run", str(CRUISE), "--duration", "0.3", "--quiet", "--out", str(out)]) == 0
    before = (out / "metrics.json").read_text()
    capsys.readouterr()
    assert _exit_code(["run", str(CRUISE), "--duration", "0.3", "--quiet", "--overwrite", "--out", str(out), *bad]) == 2
    assert said in capsys.readouterr().err
    assert (out / "metrics.json").read_text() == before and (out / "run.rrd").exists()


def _exit_code(argv: list[str]) -> int:
    """``hil``'s exit code for argv: what ``main`` returns, or the code argparse exits with (a bad value's type)."""
    try:
        return main(argv)
    except SystemExit as exc:
        return int(exc.code or 0)


def test_heatmap_cells_keep_close_values_apart_and_axes_read_as_written():
    gaps = np.array([[2473.42, 2477.91], [2475.0, np.nan]])
    d = value_decimals(gaps)
    assert [_value_text(v, d) for v in (2473.42, 2477.91)] == ["2473.4", "2477.9"]  # not 2.47e+03 twice
    loads = np.array([0.3452, 0.3467])
    assert [_value_text(v, value_decimals(loads)) for v in loads] == ["0.3452", "0.3467"]
    assert _value_text(1.5e9, value_decimals(np.array([1.5e9, 2e9]))) == "1.5e+09"
    assert [_fmt(v) for v in (125000.0, 1000000.0, 0.05, "fifo")] == ["125000", "1000000", "0.05", "fifo"]


def test_each_runtime_has_its_own_default_directory():
    """`hil run seed000` then `hil run seed000 --ideal` (as the README's table is made) must not refuse each other."""
    from argparse import Namespace

    from hil.cli import default_output_dir

    assert default_output_dir("seed000", Namespace(ideal=False, realtime=False)) == Path("runs/seed000")
    assert default_output_dir("seed000", Namespace(ideal=True, realtime=False)) == Path("runs/seed000-ideal")
    assert default_output_dir("faults", Namespace(ideal=False, realtime=True)) == Path("runs/faults-realtime")
