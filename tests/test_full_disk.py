"""A full disk: `hil run` stops with "no space left on <dir>" (exit 1) within seconds, leaves no temporary file,
and what it wrote before stays readable. Runs on a small tmpfs where the test may mount one (root), else skips."""
from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
import warnings
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture
def tiny_fs():
    """A 3 MiB tmpfs, unmounted afterwards."""
    d = Path(tempfile.mkdtemp(prefix="thfull"))
    if subprocess.run(["mount", "-t", "tmpfs", "-o", "size=3M", "tmpfs", str(d)], capture_output=True).returncode:
        os.rmdir(d)
        pytest.skip("cannot mount a tmpfs here (needs root)")
    try:
        yield d
    finally:
        subprocess.run(["umount", "-l", str(d)], capture_output=True)
        os.rmdir(d)


def hil_run(out: Path, *extra: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "hil", "run", "seed000", "--duration", "120", "--out", str(out),
                           "--quiet", *extra], capture_output=True, text=True, timeout=90, cwd=REPO)


@pytest.mark.parametrize("runtime", [[], ["--realtime", "--pace", "10", "--duration", "20"]])
def test_a_full_disk_is_a_clear_error_and_the_recording_so_far_stays_readable(tiny_fs, runtime):
    """The disk fills while the run records: exit 1 with a message that says truly how far run.rrd reads and that
    metrics.json holds the run (the run's reserve gives it room); it used to leave a stub at t = 0 (virtual time)
    and a 0-byte run.rrd said to be readable (real time)."""
    free = os.statvfs(tiny_fs).f_bavail * os.statvfs(tiny_fs).f_frsize
    (tiny_fs / "filler").write_bytes(bytes(free - 768 * 1024))  # 768 kB left: full within seconds of recording
    out = tiny_fs / "r1"
    res = hil_run(out, *runtime)
    assert res.returncode == 1, res.stderr[-2000:]
    assert f"hil: error: no space left on {out}" in res.stderr and "Traceback" not in res.stderr
    said = res.stderr.split(f"hil: error: no space left on {out}")[1]
    assert "metrics.json holds the run's metrics to t = " in said
    assert sorted(p.name for p in out.iterdir() if p.name != "nodes") == ["metrics.json", "run.rrd"]  # no temp files
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["interrupted"] is True and metrics["error"].startswith("DiskFullError: no space left on")
    assert f"to t = {metrics['sim_time_s']:.1f} s" in said
    from hil.record.reader import recorded_until

    until = recorded_until(out / "run.rrd")  # read up to its last complete message
    if until is not None:
        assert f"run.rrd is readable up to t = {until:.1f} s" in said
    else:
        assert "run.rrd holds no samples" in said


def test_a_full_disk_without_recording_names_the_place_and_leaves_no_temporary_file(tiny_fs):
    filler = tiny_fs / "filler"
    free = os.statvfs(tiny_fs).f_bavail * os.statvfs(tiny_fs).f_frsize
    filler.write_bytes(bytes(free - 8 * 1024))  # 8 kB left: the metrics file does not fit
    out = tiny_fs / "r2"
    res = hil_run(out, "--no-record", "--duration", "2")
    assert res.returncode == 1, res.stderr[-2000:]
    assert "no space left on" in res.stderr and "Traceback" not in res.stderr
    assert not [p for p in out.iterdir() if p.name.endswith(".tmp")]
