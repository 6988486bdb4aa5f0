"""The example firmware test suite (examples/) passes as a user runs it: all green, the deliberately failing test
xfails, and --hil-record keeps its recording. It includes a short real-time run (separate processes)."""
from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.slow  # 14 s at load average 5 on the 2-core VM, 31 s at 12 (pytest start-up, 2 virtual runs, 2 s real time)
def test_example_suite_passes_and_keeps_the_recording_of_its_deliberate_failure(tmp_path):
    proc = subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", str(ROOT / "examples"),
                           "--hil-record", str(tmp_path)], capture_output=True, text=True, cwd=tmp_path, timeout=600)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-2000:]
    assert "9 passed, 1 xfailed" in proc.stdout
    kept = [p.relative_to(tmp_path).as_posix() for p in tmp_path.rglob("run.rrd")]
    assert kept == ["examples_test_my_controller.py_test_deliberately_failing_settles_within_5_s/cruise/run.rrd"]
