"""`hil run` and `hil scenarios` as a user runs them: files written, CAN logs python-can reads."""
from __future__ import annotations

import json
import subprocess
import sys

import can
import numpy as np
import pytest

from ecu_sim.codec import TrainDb
from tests.rrd_reader import read_scalars


def hil(*args: str, timeout: float = 300) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "hil", *args], capture_output=True, text=True, timeout=timeout)


def test_scenarios_lists_the_packaged_ones():
    proc = hil("scenarios")
    assert proc.returncode == 0
    names = [line.split()[0] for line in proc.stdout.splitlines()]
    assert {"seed000", "seed000-consensus", "seed000-limits"} <= set(names)


@pytest.fixture(scope="module")
def short_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("run")
    proc = hil("run", "seed000", "--duration", "3", "--out", str(out), "--can-log", "--quiet")
    assert proc.returncode == 0, proc.stderr
    return out, proc.stdout


def test_run_prints_a_summary_and_writes_metrics(short_run):
    out, stdout = short_run
    assert "settling time" in stdout and "frame latency p99" in stdout
    metrics = json.loads((out / "metrics.json").read_text())
    for key in ("settling_time_s", "coupler_max_abs_m", "gap_min_m", "gap_final_m", "speed_error_max_after_settling_mps",
                "frames_sent", "frames_lost", "bus_load_max", "frame_latency_p99_s", "sim_time_s", "wall_time_s"):
        assert key in metrics, key
    assert metrics["sim_time_s"] == pytest.approx(3.0)
    assert len(metrics["gap_min_m"]) == 2 and metrics["frames_sent"] > 3 * 19 * 300 * 0.9
    assert 0.0 < metrics["bus_load_max"] < 1.0


def test_run_records_signals_on_the_sim_timeline(short_run):
    out, _ = short_run
    data = read_scalars(out / "run.rrd")
    for path in ("/trains/1/units/1/speed_kmh", "/trains/3/units/4/traction_kn", "/trains/2/couplers/1/displacement_m",
                 "/trains/2/gap_ahead_m", "/buses/bus1/load", "/buses/bus2/frame_latency_ms", "/reference/speed_kmh"):
        assert path in data, path
    t, v = data["/trains/2/units/1/speed_kmh"]
    assert t[0] == 0.0 and t[-1] == pytest.approx(2.9) and v[0] == pytest.approx(275.0)


def test_can_log_is_readable_by_python_can_with_end_of_frame_times(short_run):
    out, _ = short_run
    msgs = list(can.ASCReader(out / "bus2.asc"))
    assert len(msgs) > 1000
    db = TrainDb.load()
    ids = {m.arbitration_id for m in msgs}
    assert db.sensor(0).frame_id in ids and db.radio_ahead_state.frame_id in ids and db.radio_behind_state.frame_id in ids
    times = np.array([m.timestamp for m in msgs])
    assert np.all(np.diff(times) > 0) and times[-1] <= 3.0  # one frame at a time on the wire, sim seconds
    first = next(m for m in msgs if m.arbitration_id == db.reference.frame_id)
    x_r, v_r = db.reference.decode(bytes(first.data))
    assert x_r == pytest.approx(109_000.0, abs=1.0) and v_r == pytest.approx(316 / 3.6, abs=1e-3)


def test_sigint_mid_run_leaves_readable_results(tmp_path):
    """A real Ctrl-C (SIGINT) during `hil run`: exit 130, metrics.json and run.rrd readable up to the stop."""
    import signal
    import time

    proc = subprocess.Popen([sys.executable, "-m", "hil", "run", "seed000", "--duration", "600", "--out", str(tmp_path),
                             "--quiet"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    deadline, rrd = time.monotonic() + 120, tmp_path / "run.rrd"

    def size() -> int:
        return rrd.stat().st_size if rrd.exists() else 0

    while size() == 0:  # the writer starts with the blueprint ...
        assert proc.poll() is None and time.monotonic() < deadline, "run ended or never recorded"
        time.sleep(0.1)
    time.sleep(0.5)
    initial = size()
    while size() < initial + 20_000:  # ... and the first flush of simulated signals follows
        assert proc.poll() is None and time.monotonic() < deadline, "run ended or never recorded"
        time.sleep(0.1)
    proc.send_signal(signal.SIGINT)
    stdout, stderr = proc.communicate(timeout=120)
    assert proc.returncode == 130, stderr
    assert "INTERRUPTED" in stdout and "Traceback" not in stderr
    metrics = json.loads((tmp_path / "metrics.json").read_text())
    assert metrics["interrupted"] is True and 0 < metrics["sim_time_s"] < 600
    t, _ = read_scalars(tmp_path / "run.rrd")["/trains/3/units/4/speed_kmh"]
    assert t[-1] >= 10.0  # at least the first flush (every 10 simulated seconds)


def test_sigint_before_the_run_loop_exits_cleanly(tmp_path):
    """Ctrl-C while the rig is still being built: no traceback, exit 130."""
    import signal

    proc = subprocess.Popen([sys.executable, "-m", "hil", "run", "seed000", "--out", str(tmp_path), "--quiet"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    rrd = tmp_path / "run.rrd"
    while not rrd.exists() and proc.poll() is None:  # the recording is opened before the rig is built
        pass
    proc.send_signal(signal.SIGINT)
    _, stderr = proc.communicate(timeout=120)
    assert proc.returncode == 130 and "Traceback" not in stderr


def test_output_piped_into_head_ends_quietly():
    proc = subprocess.run(f"{sys.executable} -m hil can-analysis --bitrate 500000 | head -n 1", shell=True,
                          capture_output=True, text=True, timeout=120)
    assert proc.stdout.strip() and "Traceback" not in proc.stderr and "BrokenPipe" not in proc.stderr
