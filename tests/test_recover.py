"""A real-time rig killed with SIGKILL: what the nodes recorded is recoverable with
``hil recover`` into a readable recording and metrics that say what was lost, and the next run removes the dead
run directory the killed rig left."""
from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from hil.record import load_run
from hil.runtime.realtime.sockets import STALE_AFTER_S, remove_stale_run_dirs, run_dir

ROOT = Path(__file__).resolve().parents[1]
CRUISE = ROOT / "examples" / "cruise.toml"


def hil(*argv: str, **kw) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "hil", *argv], capture_output=True, text=True, timeout=120, **kw)


@pytest.mark.slow  # about 15 s: start-up, 3 s of real time, the kill, the merge
def test_a_killed_rig_is_recovered_from_its_nodes_files(tmp_path):
    out = tmp_path / "r"
    rig = subprocess.Popen([sys.executable, "-m", "hil", "run", str(CRUISE), "--realtime", "--duration", "60",
                            "--ecus-per-process", "3", "--quiet", "--out", str(out)],
                           stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    stream, row = out / "nodes" / "signals.bin", 8 * (3 + 5 * 6)
    deadline = time.monotonic() + 90
    while not (stream.exists() and stream.stat().st_size >= 30 * row):  # 3 s of samples at 0.1 s
        assert time.monotonic() < deadline and rig.poll() is None, "the rig did not start streaming"
        time.sleep(0.2)
    rig.send_signal(signal.SIGKILL)
    rig.wait(10)
    stub = json.loads((out / "metrics.json").read_text())
    assert stub["status"] == "running" and "hil recover" in stub["note"] and not (out / "run.rrd").exists()

    done = hil("recover", str(out))
    assert done.returncode == 0, done.stderr
    assert done.stdout.startswith(f"recovered {out}: ")
    run = load_run(out)
    t, v = run["/trains/1/units/1/speed_kmh"]
    assert t[-1] >= 2.9 and len(t) >= 30 and run.metrics["sim_time_s"] == pytest.approx(t[-1], abs=0.11)
    m = run.metrics
    assert m["recovered"] is True and m["interrupted"] is True and "orchestrator events" in m["recovered_missing"]
    bus = m["per_bus"]["bus1"]  # spooled every second by the orchestrator, so recovered too
    assert bus["frames_sent"] > 1000 and bus["latency_p99_s"] is not None and bus["load_max"] > 0
    assert len(m["realtime"]["ecus"]) == 6  # every ECU process wrote its results when its bus went away
    assert m["e2e_latency_p50_s"] is not None
    texts = [e.text for e in run.events]
    assert any(text.startswith("recovered by hil recover") for text in texts)
    assert any(text.startswith("the bus went away, the ECU stopped") for text in texts)

    again = hil("recover", str(out))
    assert again.returncode == 2 and "the run finished and wrote its results; nothing to recover" in again.stderr
    nothing = hil("recover", str(tmp_path))
    assert nothing.returncode == 2 and "not the output directory of a real-time run" in nothing.stderr


def test_dead_run_directories_are_removed_and_live_ones_kept(tmp_path, monkeypatch):
    monkeypatch.setenv("XDG_RUNTIME_DIR", str(tmp_path))
    dead = run_dir(f"dead{os.getpid()}", create=True)
    (dead / "bus1.sock").touch()  # a socket file nobody listens on
    live = run_dir(f"live{os.getpid()}", create=True)
    server = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    server.bind(str(live / "bus1.sock"))
    server.listen()
    young = run_dir(f"young{os.getpid()}", create=True)
    (young / "bus1.sock").touch()
    old = time.time() - STALE_AFTER_S - 5
    for d in (dead, live):
        os.utime(d, (old, old))
    try:
        assert remove_stale_run_dirs() == [dead.name]
        assert not dead.exists() and live.exists() and young.exists()  # a young one may be a rig starting up
    finally:
        server.close()


@pytest.fixture(scope="module")
def finished_rt_run(tmp_path_factory):
    """A 2 s real-time run that ended normally: its nodes' files are what a killed rig leaves."""
    out = tmp_path_factory.mktemp("rt") / "run"
    done = hil("run", str(CRUISE), "--realtime", "--duration", "2", "--ecus-per-process", "3", "--quiet", "--out", str(out))
    assert done.returncode == 0, done.stderr
    return out


def as_killed(run: Path, where: Path) -> Path:
    """A copy of ``run`` as its killed rig would have left it: a "running" stub and no run.rrd."""
    import shutil

    from hil.record.integrity import mark_running

    shutil.copytree(run, where)
    (where / "run.rrd").unlink()
    mark_running(where / "metrics.json", "cruise", "realtime")
    return where


@pytest.mark.parametrize("damage, says", [
    ("random", "nodes/signals.bin: row 0 is not a sample of this run"),
    ("no run.json", "the rig never started (no valid nodes/run.json): there is no run to recover"),
    ("bad scenario", "nodes/scenario.json: not a valid scenario ("),
    ("empty stream", "nodes/signals.bin: no samples: the plant never recorded"),
])
def test_recover_refuses_what_it_cannot_trust(finished_rt_run, tmp_path, damage, says):
    """Random bytes in signals.bin used to give exit 0 and a coupler of 7.8e307 m; a rig that never started was
    "recovered" as a 0 s run; a corrupt scenario.json was a pydantic traceback."""
    run = as_killed(finished_rt_run, tmp_path / "r")
    stream = run / "nodes" / "signals.bin"
    if damage == "random":
        stream.write_bytes(np.random.default_rng(1).bytes(stream.stat().st_size))
    elif damage == "no run.json":
        (run / "nodes" / "run.json").unlink()
    elif damage == "bad scenario":
        (run / "nodes" / "scenario.json").write_text('{"name": 5, "trains": "many"}')
    else:
        stream.write_bytes(b"")
    done = hil("recover", str(run))
    assert done.returncode == 2 and says in done.stderr and "Traceback" not in done.stderr, done.stderr
    assert json.loads((run / "metrics.json").read_text())["status"] == "running"  # nothing was made up


def test_recover_reports_the_time_a_cut_stream_really_covers(finished_rt_run, tmp_path):
    """A half-cut signals.bin used to be reported as the plant's whole time: now the figures say what they cover."""
    run = as_killed(finished_rt_run, tmp_path / "r")
    stream = run / "nodes" / "signals.bin"
    data = stream.read_bytes()
    stream.write_bytes(data[:len(data) // 2 + 5])  # half the rows and a cut one
    done = hil("recover", str(run))
    assert done.returncode == 0, done.stderr
    m = json.loads((run / "metrics.json").read_text())
    t, _ = load_run(run)["/trains/1/units/1/speed_kmh"]
    assert m["sim_time_s"] == pytest.approx(t[-1]) and t[-1] < 1.2 and m["recovered_covers_s"] == [0.0, t[-1]]
    assert any(e[3].startswith("the plant's signal stream ends at t = ") for e in [
        (ev.t, ev.level, ev.source, ev.text) for ev in load_run(run).events])
