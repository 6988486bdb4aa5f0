"""The real-time rig's CPU layout (hil/runtime/realtime/cpu_layout.py): the bus serving thread and the plant on the
first core the rig may use, the ECU processes on the others; each node pins itself from its arguments."""
from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest

from hil.runtime.realtime.cpu_layout import CpuLayout, choose_cpu_layout, parse_cores

ALLOWED = sorted(os.sched_getaffinity(0))


def test_auto_keeps_the_first_allowed_core_for_the_rig_and_gives_the_ecus_the_others() -> None:
    assert choose_cpu_layout("auto", {0, 1}) == CpuLayout(rig=(0,), ecus=(1,))
    assert choose_cpu_layout("auto", {7, 2, 5}) == CpuLayout(rig=(2,), ecus=(5, 7))  # a taskset mask is kept
    assert choose_cpu_layout("auto", {3}) is None  # one core: nothing to separate
    assert choose_cpu_layout("none", {0, 1}) is None
    assert choose_cpu_layout("auto", {0, 1}, pace=10.0) is None  # faster than real time: the ECU processes queued
    assert choose_cpu_layout("auto", {0, 1}, pace=0.5) == CpuLayout(rig=(0,), ecus=(1,))
    with pytest.raises(ValueError, match="cpu_layout='spread' must be one of auto, none"):
        choose_cpu_layout("spread", {0, 1})  # type: ignore[arg-type]
    layout = CpuLayout(rig=(0,), ecus=(1, 2))
    assert (layout.cores_for("ecu"), layout.cores_for("plant"), layout.cores_for("radio")) == ((1, 2), (0,), (0,))
    assert layout.describe() == "CPU layout: bus servers and plant on 0, ECU processes on 1,2"


def test_a_nodes_cores_argument_is_checked() -> None:
    assert parse_cores("1") == (1,) and parse_cores("1,3") == (1, 3)
    for bad in ("", "a", "1,,2", "-1"):
        with pytest.raises(ValueError):
            parse_cores(bad)


def run_role(cores: str) -> subprocess.CompletedProcess:
    """A node's first step (``enter_role``) on ``cores``, in a process of its own; it prints where it may run."""
    script = ("import os\nfrom hil.runtime.realtime.scheduling import enter_role\nfrom hil.runtime.realtime.cpu_layout "
              f"import parse_cores\nenter_role('ecu', False, parse_cores({cores!r}))\n"
              "print(','.join(map(str, sorted(os.sched_getaffinity(0)))))\n")
    return subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=60, check=True)


def test_a_node_runs_on_the_cores_it_is_given_and_says_so_when_it_cannot() -> None:
    last = str(ALLOWED[-1])
    assert run_role(last).stdout.split() == [last]
    refused = run_role("4095")  # no such core here: the node goes on anywhere and says why
    assert refused.stdout.split() == [",".join(map(str, ALLOWED))]
    assert "ecu node: cannot run on cores 4095" in refused.stderr


def test_a_real_time_run_puts_its_ecu_processes_on_their_own_cores_and_records_it(tmp_path, monkeypatch) -> None:
    from hil.runtime.realtime.orchestrator import run_realtime
    from hil.scenario import load_scenario

    monkeypatch.setenv("XDG_RUNTIME_DIR", str(tmp_path))
    res = run_realtime(load_scenario("seed000"), tmp_path / "rt", duration_s=0.5, record=False)
    rt = json.loads((tmp_path / "rt" / "metrics.json").read_text())["realtime"]
    expected = choose_cpu_layout("auto")
    assert rt["cpu_layout"] == (None if expected is None else expected.as_dict())
    said = [e.text for e in res.log.events if e.source == "rig" and e.text.startswith("CPU layout")]
    assert said == [expected.describe() if expected is not None else
                    "CPU layout: none (the kernel places every process)"]
    assert sorted(os.sched_getaffinity(0)) == ALLOWED  # the orchestrator's own thread is not pinned
