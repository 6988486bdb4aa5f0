"""Validation gaps: physical bounds instead of tracebacks, hangs
or overflows; output directories that cannot be made; names that cannot name a directory; faults that will never
fire; node names that could forge log lines; unknown flag bits; empty run directories; a squatted runtime root."""
from __future__ import annotations

import logging
import os
import socket
import subprocess
import sys
import tempfile
from pathlib import Path

import pytest

from hil.cli import main
from hil.runtime.realtime import protocol
from hil.runtime.realtime.sockets import InsecureRunDirError, run_dir, runtime_root
from hil.scenario import ScenarioError, load_scenario
from tests.polling import wait_for

ROOT = Path(__file__).resolve().parents[1]
CRUISE = ROOT / "examples" / "cruise.toml"

BOUNDS = [
    ({"plant.step_s": 4e-10}, "plant.step_s: Input should be greater than or equal to 0.00001"),
    ({"plant.step_s": 1e-9}, "plant.step_s: Input should be greater than or equal to 0.00001"),
    ({"radio.latency_s": 1e300}, "radio.latency_s: Input should be less than or equal to 60"),
    ({"radio.rate_cap_hz": 1e-300}, "radio.rate_cap_hz: Input should be greater than or equal to 0.01"),
    ({"ecu.phase_s": 1e300}, "ecu.phase_s: Input should be less than or equal to 10"),
    ({"ecu.stagger_s": 1e300}, "ecu.stagger_s: Input should be less than or equal to 10"),
    ({"duration_s": 1e300}, "duration_s: Input should be less than or equal to 10000000"),
    ({"faults": [{"kind": "ecu_crash", "train": 1, "unit": 1, "at_s": 1e300}]}, "faults.0.ecu_crash.at_s"),
    ({"radio.blackouts": [{"start_m": float(k), "end_m": k + 0.5} for k in range(10_001)]},
     "radio.blackouts: List should have at most 10000 items"),
    ({"controller.params.kx_ref": True}, "controller.params.kx_ref: Input should be a valid number (got True)"),
    ({"name": "a" * 300}, "300 characters, at most 100"),
    ({"name": "two\nlines"}, "control characters (newlines, tabs) are not allowed"),
]


@pytest.mark.parametrize("sets,message", BOUNDS, ids=[m.split(":")[0] for _, m in BOUNDS])
def test_values_beyond_physical_bounds_are_named(sets, message):
    with pytest.raises(ScenarioError) as err:
        load_scenario(CRUISE, sets)
    assert message in str(err.value)


def test_deep_nesting_names_the_file(tmp_path):
    deep = tmp_path / "deep.toml"
    deep.write_text('name = "x"\nv = ' + "[" * 5000 + "]" * 5000 + "\n")
    with pytest.raises(ScenarioError, match=r"deep\.toml: .*nested too deeply"):
        load_scenario(deep)


@pytest.mark.parametrize("where", ["file", "sys", "long"])
def test_an_output_directory_that_cannot_be_made_is_named(tmp_path, capsys, where):
    out = {"file": tmp_path / "f", "sys": Path("/sys/trainhil-test"), "long": tmp_path / ("b" * 300)}[where]
    if where == "file":
        out.write_text("not a directory")
    assert main(["run", str(CRUISE), "--duration", "0.2", "--quiet", "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert f"--out {out}" in err and ("not a directory" in err or "cannot write there" in err)


def test_a_fault_after_the_end_is_said_at_load_and_in_the_report(tmp_path, capsys):
    out = tmp_path / "r"
    fault = "faults=[{kind='ecu_crash', train=1, unit=2, at_s=5.0}]"
    assert main(["run", str(CRUISE), "--duration", "1", "--quiet", "--no-record", "--set", fault, "--out", str(out)]) == 0
    err = capsys.readouterr().err
    assert "hil: warning: faults.0: at_s = 5 is not before the end of the run (t = 1 s): it will not be injected" in err
    import json

    report = json.loads((out / "metrics.json").read_text())["faults"]["faults"][0]
    assert report["injected"] is False
    assert report["not_injected_because"] == "scheduled at t = 5 s, after the end of the run (t = 1 s)"


def test_node_names_cannot_forge_log_lines_and_unknown_flags_are_rejected(rt, server_cls, caplog):
    caplog.set_level(logging.INFO)
    with server_cls("r1", "bus1", 500_000) as srv:
        with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as s:
            s.connect(str(srv.path))
            s.sendall(protocol.pack_hello("ok\nbus bus1: FORGED"))
            assert protocol.unpack_welcome(s.recv(24)).bitrate == 500_000
            record = bytearray(protocol.pack_frame(0x10, b"\x01"))
            record[1] |= 0x40  # a flag bit the protocol does not define
            s.sendall(bytes(record))
            assert wait_for(lambda: srv.stats.frames_rejected == 1)
    text = caplog.text
    assert "FORGED" in text and "\nbus bus1: FORGED" not in text and "ok?bus bus1: FORGED" in text
    assert "unknown flag bits" in text


def test_bus_server_leaves_no_empty_run_directory(rt, tmp_path):
    proc = subprocess.run([sys.executable, "-m", "hil", "bus-server", "--run", "leftover", "--bus", "bus1",
                           "--duration", "0.5"], capture_output=True, text=True, timeout=60)
    assert proc.returncode == 0, proc.stderr
    assert not (runtime_root() / "leftover").exists()


@pytest.mark.skipif(os.geteuid() != 0, reason="making a directory owned by another user needs root")
def test_a_squatted_runtime_root_suggests_xdg_runtime_dir(tmp_path, monkeypatch):
    monkeypatch.delenv("XDG_RUNTIME_DIR", raising=False)
    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))
    root = runtime_root()
    root.mkdir(mode=0o700)
    os.chown(root, 65534, 65534)  # another user made it first (the tests run as root here)
    with pytest.raises(InsecureRunDirError, match=r"not by you .*set XDG_RUNTIME_DIR to a private directory"):
        run_dir("r1", create=True)
