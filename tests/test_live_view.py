"""Live viewing: ``hil run --connect URL`` streams to a listening rerun gRPC sink while the run goes, in virtual and
in real time. The sink is rerun's own headless proxy (``rerun --bind 127.0.0.1 --port P --save FILE``), on
loopback, with its analytics off; the test reads what arrived with rerun's RrdReader while the run is going."""
from __future__ import annotations

import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest
from rerun.chunk import RrdReader

ROOT = Path(__file__).resolve().parents[1]
CRUISE = ROOT / "examples" / "cruise.toml"
ENTITY = "/trains/2/units/3/speed_kmh"

pytestmark = [pytest.mark.skipif(shutil.which("rerun") is None, reason="the rerun CLI (rerun-sdk) is not on PATH"),
              pytest.mark.filterwarnings("ignore:RRD file has no footer")]  # the sink's file is still growing


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture
def sink(tmp_path):
    """(url, file): a headless rerun proxy on loopback that saves everything it receives."""
    port, saved = free_port(), tmp_path / "received.rrd"
    config = tmp_path / "rerun-config"
    (config / "rerun").mkdir(parents=True)
    (config / "rerun" / "analytics.json").write_text(json.dumps({"analytics_enabled": False}))
    env = {**os.environ, "XDG_CONFIG_HOME": str(config), "XDG_DATA_HOME": str(tmp_path / "rerun-data")}
    proc = subprocess.Popen(["rerun", "--bind", "127.0.0.1", "--port", str(port), "--save", str(saved)],
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, env=env,
                            start_new_session=True)  # `rerun` is a launcher: its viewer binary is a child
    deadline = time.monotonic() + 30
    while True:  # until it accepts connections
        try:
            socket.create_connection(("127.0.0.1", port), timeout=0.5).close()
            break
        except OSError:
            if proc.poll() is not None or time.monotonic() > deadline:
                pytest.fail(f"rerun proxy did not start: {proc.stderr.read().decode(errors='replace')}")
            time.sleep(0.1)
    yield f"rerun+http://127.0.0.1:{port}/proxy", saved
    os.killpg(proc.pid, signal.SIGTERM)  # the launcher and the binary it started
    proc.wait(10)


def received_times(path: Path, entity: str) -> list[float]:
    """sim_time (s) of every row of ``entity`` the sink has saved so far (the file is still being written)."""
    out = []
    try:
        for ch in RrdReader(path).stream():
            if ch.entity_path == entity:
                rb = ch.to_record_batch()
                if "sim_time" in rb.schema.names:
                    out += (rb.column("sim_time").cast("int64").to_numpy() * 1e-9).tolist()
    except Exception:  # noqa: BLE001  (a message cut mid-write at the end of a growing file)
        pass
    return sorted(out)


def watch(proc: subprocess.Popen, saved: Path, timeout_s: float) -> list[tuple[bool, float]]:
    """While the run goes: (run still going, latest sim time received) every 0.25 s."""
    seen, deadline = [], time.monotonic() + timeout_s
    while proc.poll() is None and time.monotonic() < deadline:
        times = received_times(saved, ENTITY) if saved.exists() else []
        seen.append((proc.poll() is None, times[-1] if times else -1.0))
        time.sleep(0.25)
    return seen


@pytest.mark.slow  # about 10 s: 120 s simulated at ~30x
def test_a_virtual_run_streams_to_a_viewer_as_the_simulation_goes(sink, tmp_path):
    url, saved = sink
    proc = subprocess.Popen([sys.executable, "-m", "hil", "run", str(CRUISE), "--duration", "120", "--quiet",
                             "--connect", url, "--out", str(tmp_path / "r")], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    seen = watch(proc, saved, 300)
    out, err = proc.communicate(timeout=60)
    assert proc.returncode == 0, err
    during = [t for going, t in seen if going and t > 0]
    assert len(set(during)) >= 2, seen  # rows arrived, more than once, before the run ended
    assert min(during) < 100.0, seen  # ... long before its end
    final = received_times(saved, ENTITY)
    assert final[-1] == pytest.approx(119.9, abs=0.11)  # and everything by the end, as in the file
    assert len(final) == len(received_times(tmp_path / "r" / "run.rrd", ENTITY))


@pytest.mark.slow  # about 15 s: 6 s of real time
def test_a_real_time_run_streams_to_a_viewer_on_the_wall_clock(sink, tmp_path):
    url, saved = sink
    proc = subprocess.Popen([sys.executable, "-m", "hil", "run", str(CRUISE), "--realtime", "--duration", "6",
                             "--ecus-per-process", "3", "--quiet", "--connect", url, "--out", str(tmp_path / "r")],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    seen = watch(proc, saved, 300)
    out, err = proc.communicate(timeout=60)
    assert proc.returncode == 0, err
    during = sorted({t for going, t in seen if going and t > 0})
    assert len(during) >= 3 and during[0] < 4.0, seen  # arriving while the wall clock runs, not at the end
    final = received_times(saved, ENTITY)
    assert final[-1] == pytest.approx(5.9, abs=0.11)
    assert len(final) == len(set(final)) == len(received_times(tmp_path / "r" / "run.rrd", ENTITY))  # once each


class SilentPeer:
    """A TCP peer on loopback that accepts connections and never reads from them (a stalled viewer)."""

    def __init__(self) -> None:
        import threading

        self.sock = socket.socket()
        self.sock.bind(("127.0.0.1", 0))
        self.sock.listen(8)
        self.port = self.sock.getsockname()[1]
        self.held: list[socket.socket] = []
        threading.Thread(target=self._accept, daemon=True).start()

    def _accept(self) -> None:
        try:
            while True:
                self.held.append(self.sock.accept()[0])
        except OSError:
            pass

    def close(self) -> None:
        self.sock.close()
        for c in self.held:
            c.close()


def _run_with_viewer(url: str, out: Path) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "hil", "run", str(CRUISE), "--duration", "5", "--quiet",
                           "--connect", url, "--out", str(out)], capture_output=True, text=True, timeout=90)


def _assert_whole_run(out: Path) -> None:
    from hil.record import load_run

    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["sim_time_s"] == 5.0 and not metrics["interrupted"]
    t, _ = load_run(out)[ENTITY]
    assert t[-1] >= 4.9


@pytest.mark.parametrize("peer", ["silent", "dead"])
def test_a_viewer_that_never_reads_or_is_not_there_costs_neither_the_run_nor_its_files(tmp_path, peer):
    """``--connect`` to a peer that accepts and never reads (it used to hang past SIGTERM), or to a dead port (it
    used to lose run.rrd): the run ends on its own within seconds, exit 0, files whole, the viewer named."""
    silent = SilentPeer() if peer == "silent" else None
    port = silent.port if silent is not None else free_port()
    url = f"rerun+http://127.0.0.1:{port}/proxy"
    try:
        started = time.monotonic()
        proc = _run_with_viewer(url, tmp_path / "out")
        took = time.monotonic() - started
    finally:
        if silent is not None:
            silent.close()
    assert proc.returncode == 0, proc.stderr
    assert f"hil: warning: live view at {url} dropped" in proc.stderr
    assert took < 45, took
    _assert_whole_run(tmp_path / "out")
