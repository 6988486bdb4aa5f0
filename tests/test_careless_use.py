"""Careless and hostile use, round three (issue 23): each test is one reproduction and what the user gets instead."""
from __future__ import annotations

import json
import os
import re
import subprocess
import sys
import time
from pathlib import Path

import pytest

from hil.cli import main
from hil.runtime.realtime.orchestrator import Node


def test_a_node_that_prints_a_lot_is_drained_into_a_bounded_tail(tmp_path):
    """A law that prints on every step: the orchestrator reads the node's stdout as it comes and keeps only the
    last lines, so its memory does not grow with the output (the protocol lines still come through)."""
    code = "import sys\nfor i in range(200000): print('law says', i)\nprint('ready', flush=True)\nsys.stdin.read()"
    proc = subprocess.Popen([sys.executable, "-c", code], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True,
                            bufsize=1)
    node = Node("chatty", "ecu", proc, tmp_path / "err")
    node.start_reader()
    try:
        assert node.lines.get(timeout=60) == "ready"
        assert node.printed_count == 200000
        assert list(node.printed)[-1] == "law says 199999" and len(node.printed) <= 20
        assert node.lines.empty()
    finally:
        proc.stdin.close()
        proc.wait(10)


# --------------------------------------------------------------------------- output folders

ROOT = Path(__file__).resolve().parents[1]
CRUISE = ROOT / "examples" / "cruise.toml"


def test_a_folder_that_a_live_run_holds_is_refused_even_with_overwrite(tmp_path, capsys):
    """Two runs into one folder used to both exit 0, leaving one run's metrics beside the other's recording."""
    from hil.record.out_dir import LOCK_NAME

    out = tmp_path / "same"
    holder = subprocess.Popen([sys.executable, "-c", HOLD_FOLDER, str(out)], stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "held"
        assert main(["run", str(CRUISE), "--duration", "1", "--quiet", "--out", str(out), "--overwrite"]) == 2
        err = capsys.readouterr().err
        assert f"is in use by a run that is still going (pid {holder.pid}, started " in err
        assert not (out / "metrics.json").exists()
    finally:
        holder.kill()
        holder.wait()
    assert (out / LOCK_NAME).exists()  # a killed holder leaves its file, but not its lock
    assert main(["run", str(CRUISE), "--duration", "1", "--quiet", "--out", str(out), "--overwrite"]) == 0
    assert not (out / LOCK_NAME).exists()  # a finished run lets its folder go


HOLD_FOLDER = """
import sys, time
from hil.record.out_dir import hold_folder
import pathlib
out = pathlib.Path(sys.argv[1]); out.mkdir(parents=True)
hold_folder(out)
print("held", flush=True)
time.sleep(600)
"""


@pytest.fixture
def read_only_dir(tmp_path):
    """An existing folder on a read-only file system (root ignores permission bits, so a mount it is)."""
    where = tmp_path / "ro"
    where.mkdir()
    if subprocess.run(["mount", "-t", "tmpfs", "-o", "ro,size=1m", "tmpfs", str(where)],
                      capture_output=True).returncode != 0:
        if os.geteuid() == 0:
            pytest.skip("cannot mount a read-only tmpfs here")
        where.chmod(0o555)
        yield where
        where.chmod(0o755)
        return
    try:
        yield where
    finally:
        subprocess.run(["umount", str(where)], check=True)


@pytest.mark.parametrize("command", [["run", str(CRUISE), "--duration", "1"],
                                     ["run", str(CRUISE), "--duration", "1", "--realtime"],
                                     ["compare", str(CRUISE), str(CRUISE), "--duration", "1"],
                                     ["sweep", "bitrate", "--duration", "1"]])
def test_a_read_only_output_folder_is_refused_before_any_work(read_only_dir, capsys, command):
    """It used to be an OSError traceback, in compare after every run was done."""

    started = time.monotonic()
    assert main([*command, "--quiet", "--out", str(read_only_dir)] if command[0] != "compare"
                else [*command, "--out", str(read_only_dir)]) == 2
    err = capsys.readouterr().err
    assert f"hil: error: --out {read_only_dir}: cannot write there: Read-only file system" in err \
        or "Permission denied" in err
    assert time.monotonic() - started < 10


# --------------------------------------------------------------------------- firmware that fails must fail CI

BAD_LAWS = '''
import os, sys
from ecu_sim.controllers.base import Controller, ControllerParams
from ecu_sim.view import Command


class _Law(Controller):
    Params = ControllerParams

    def step(self, view):
        return Command(force_n=0.0, accel_mps2=0.0)


class Raises(_Law):
    def step(self, view):
        raise ValueError("boom")


class ReturnsNan(_Law):
    def step(self, view):
        return Command(force_n=float("nan"), accel_mps2=0.0)


class ReturnsNone(_Law):
    def step(self, view):
        return None


class SysExit3(_Law):
    def step(self, view):
        sys.exit(3)


class OsExit0(_Law):
    def step(self, view):
        os._exit(0)


class Hangs(_Law):
    def step(self, view):
        while True:  # never returns (in real time only: virtual time would wait for it forever)
            pass


class Silences(_Law):
    def step(self, view):
        sys.stdout = open(os.devnull, "w")  # quiets a chatty library for good
        return super().step(view)


class NoStep(Controller):
    Params = ControllerParams


class InitRaises(_Law):
    def __init__(self, *args, **kwargs):
        raise RuntimeError("init boom")
'''


@pytest.fixture
def bad_laws(tmp_path_factory, monkeypatch):
    """A folder with careless_laws.py as the working folder (imported once per test session)."""
    where = tmp_path_factory.getbasetemp() / "careless_laws"
    where.mkdir(exist_ok=True)
    (where / "careless_laws.py").write_text(BAD_LAWS)
    monkeypatch.chdir(where)
    return where


@pytest.mark.parametrize("law", ["Raises", "ReturnsNan", "ReturnsNone", "SysExit3", "OsExit0"])
def test_a_law_that_fails_on_every_step_fails_check(bad_laws, capsys, law):
    """Every ECU stops: ``--check`` used to exit 0 with "safe" (sys.exit(3) exited 3 with no word, os._exit(0)
    exited 0 leaving a stub). Now each ECU's stop is the ecu_failure verdict, named on stderr, exit 3."""
    out = bad_laws / f"out-{law}"
    code = main(["run", str(CRUISE), "--duration", "1", "--quiet", "--check", "--overwrite", "--out", str(out),
                 "--set", f"controller.law=careless_laws:{law}"])
    captured = capsys.readouterr()
    assert code == 3, captured.err
    assert "hil: unsafe: ecu_failure (6x, first at t = " in captured.err
    assert "ecu_failure: 6x from t = " in captured.out and "ECU stopped" in captured.out
    metrics = json.loads((out / "metrics.json").read_text())
    assert not metrics["safety"]["safe"] and metrics["safety"]["ecu_failure"]["count"] == 6
    assert metrics["sim_time_s"] == 1.0  # the run went on to its end, the plant's fail-safe holding the trains


@pytest.mark.slow  # a real-time run: about 8 s
def test_an_ecu_process_that_exits_fails_check_in_real_time(bad_laws):
    proc = subprocess.run([sys.executable, "-P", "-m", "hil", "run", str(CRUISE), "--realtime", "--duration", "2",
                           "--quiet", "--check", "--out", "rt", "--set", "controller.law=careless_laws:OsExit0"],
                          capture_output=True, text=True, timeout=300, cwd=bad_laws)
    assert proc.returncode == 3, proc.stderr
    assert "hil: unsafe: ecu_failure (6x" in proc.stderr
    assert re.search(r"ecu_failure: 6x from t = .* \(rig: ECU process train\d/unit\d exited with code 0\)", proc.stdout)


@pytest.mark.slow  # a real-time run: about 10 s
def test_an_ecu_whose_law_never_returns_is_stopped_as_hung_and_fails_check(bad_laws):
    """A law in an endless loop: its process used to run on to the end, then hold the rig 10 s (``nodes did not
    finish``) with a "safe" verdict. Its heartbeat falls silent: it is killed within seconds, each unit's stop is
    the ecu_failure verdict, and the run ends on time with the plant's fail-safe holding the trains."""
    started = time.monotonic()
    proc = subprocess.run([sys.executable, "-P", "-m", "hil", "run", str(CRUISE), "--realtime", "--duration", "5",
                           "--quiet", "--check", "--out", "rt-hang", "--overwrite",
                           "--set", "controller.law=careless_laws:Hangs"],
                          capture_output=True, text=True, timeout=300, cwd=bad_laws)
    assert proc.returncode == 3, proc.stderr
    assert "hil: unsafe: ecu_failure (6x" in proc.stderr
    assert re.search(r"ecu_failure: 6x from t = .* \(rig: ECU process train\d/unit\d hung: no cycle ended for "
                     r"\d\.\d s \(wall\)", proc.stdout), proc.stdout
    metrics = json.loads((bad_laws / "rt-hang" / "metrics.json").read_text())
    first = metrics["safety"]["ecu_failure"]["first_s"]
    assert first < 3.5, first  # silent for 2 s (HUNG_AFTER_S) after its first cycle, seen within a supervising turn
    assert "stopped_early" not in metrics
    assert time.monotonic() - started < 60


@pytest.mark.slow  # a real-time run: about 10 s
def test_a_law_that_redirects_stdout_is_not_taken_for_hung(bad_laws):
    """The heartbeat goes to the process's own stdout, not to whatever ``sys.stdout`` a law put there."""
    proc = subprocess.run([sys.executable, "-P", "-m", "hil", "run", str(CRUISE), "--realtime", "--duration", "4",
                           "--quiet", "--out", "rt-silent", "--overwrite",
                           "--set", "controller.law=careless_laws:Silences"],
                          capture_output=True, text=True, timeout=300, cwd=bad_laws)
    assert proc.returncode == 0, proc.stderr
    metrics = json.loads((bad_laws / "rt-silent" / "metrics.json").read_text())
    assert metrics["safety"]["ecu_failure"]["count"] == 0, metrics["safety"]["ecu_failure"]


@pytest.mark.parametrize("law, says", [
    ("NoStep", "'careless_laws:NoStep': NoStep does not define step (a law needs step(view) -> Command)"),
    ("InitRaises", "'careless_laws:InitRaises': building the law for train 1 unit 1 failed: RuntimeError: init boom "
                   "(careless_laws.py, line ")])
@pytest.mark.parametrize("runtime", [[], ["--realtime"]])
def test_a_law_that_cannot_be_built_is_one_line_and_exit_2_before_anything_is_written(bad_laws, capsys, law, says,
                                                                                      runtime):
    out = bad_laws / f"out-{law}-{len(runtime)}"
    code = main(["run", str(CRUISE), "--duration", "1", "--quiet", "--out", str(out), *runtime,
                 "--set", f"controller.law=careless_laws:{law}"])
    err = capsys.readouterr().err
    assert code == 2 and says in err and "Traceback" not in err
    assert not out.exists()


def test_a_sweep_set_on_one_of_its_axes_is_refused(tmp_path, capsys):
    """``hil sweep latency-loss --set radio.latency_s=0.5`` used to run the sweep with the axis winning, silently."""
    assert main(["sweep", "latency-loss", "--set", "radio.latency_s=0.5", "--out", str(tmp_path / "sw"), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "--set radio.latency_s=...: 'radio.latency_s' is an axis of this sweep (values [0.0, 0.2, 0.5])" in err
    assert not (tmp_path / "sw").exists()


def test_can_analysis_refuses_a_measured_run_of_another_scenario(tmp_path, capsys):
    """``--scenario seed001-fd --measured RUN`` of a seed001 run used to say "EXCEEDS BOUND"."""
    assert main(["run", "seed001", "--duration", "0.2", "--quiet", "--no-record", "--out", str(tmp_path / "r")]) == 0
    capsys.readouterr()
    assert main(["can-analysis", "--scenario", "seed001-fd", "--measured", str(tmp_path / "r")]) == 2
    assert "a run of scenario 'seed001', not of 'seed001-fd'" in capsys.readouterr().err
    assert main(["can-analysis", "--scenario", "seed001", "--measured", str(tmp_path / "r")]) == 0


def test_another_law_by_set_brings_only_its_own_parameters(bad_laws, capsys):
    """``--set controller.law=mymodule:Cls`` on seed000 used to fail with 13 "Extra inputs are not permitted" (the
    finite-time law's parameters); as with ``extends``, the old law's parameters go with it."""
    from hil.scenario import load_scenario

    sc = load_scenario("seed000", {"controller.law": "careless_laws:_Law"})
    assert sc.controller.law == "careless_laws:_Law" and sc.controller.params == {}
    kept = load_scenario("seed000", {"controller.law": "consensus", "controller.params.kx_ref": 0.5})
    assert kept.controller.params["kx_ref"] == 0.5
    assert main(["run", "seed000", "--duration", "0.5", "--quiet", "--no-record", "--out", str(bad_laws / "o17"),
                 "--overwrite", "--set", "controller.law=careless_laws:_Law"]) == 0
    out = capsys.readouterr().out
    assert f"written to {bad_laws / 'o17'}/ (metrics.json)" in out  # --no-record: no run.rrd named
