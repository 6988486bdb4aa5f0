"""The real-time rig's scheduling (hil/runtime/realtime/scheduling.py): SCHED_FIFO where the host permits it, the
normal scheduler with the reason where it does not, and what each node really ran under in metrics.json."""
from __future__ import annotations

import json
import subprocess
import sys

import pytest

from hil.runtime.realtime import scheduling
from hil.runtime.realtime.scheduling import SchedulingRefused, choose_scheduling, current_policy

FIFO_PERMITTED = scheduling._probe(1) is None
needs_fifo = pytest.mark.skipif(not FIFO_PERMITTED, reason="this host does not permit SCHED_FIFO")


def refuse(*_args) -> None:
    raise PermissionError(1, "Operation not permitted")


def test_auto_falls_back_to_the_normal_scheduler_and_says_why_where_sched_fifo_is_refused(monkeypatch) -> None:
    monkeypatch.setattr(scheduling.os, "sched_setscheduler", refuse)
    chosen = choose_scheduling("auto", None)
    assert chosen.policy == "normal" and "Operation not permitted" in chosen.why_normal
    assert chosen.as_dict() == {"policy": "normal", "why": chosen.why_normal}
    with pytest.raises(SchedulingRefused, match=r"--scheduling fifo: .*Operation not permitted.*ulimit -r 3"):
        choose_scheduling("fifo", 12345)


def test_normal_never_asks_for_sched_fifo_and_a_bad_mode_is_named(monkeypatch) -> None:
    monkeypatch.setattr(scheduling.os, "sched_setscheduler", lambda *a: pytest.fail("asked for SCHED_FIFO"))
    assert choose_scheduling("normal", 12345).describe() == "normal scheduler (asked for: --scheduling normal)"
    with pytest.raises(ValueError, match="scheduling='rt' must be one of auto, fifo, normal"):
        choose_scheduling("rt", None)  # type: ignore[arg-type]


@needs_fifo
def test_a_node_under_sched_fifo_starts_ordinary_processes_and_threads() -> None:
    """SCHED_RESET_ON_FORK: what firmware starts from a node does not inherit the rig's priority."""
    script = (
        "import os, subprocess, sys, threading\n"
        "from hil.runtime.realtime.scheduling import current_policy, enter_role\n"
        "seen = [enter_role('ecu', True)]\n"
        "t = threading.Thread(target=lambda: seen.append(current_policy())); t.start(); t.join()\n"
        "child = subprocess.run([sys.executable, '-c', 'import os; print(os.sched_getscheduler(0))'],"
        " capture_output=True, text=True)\n"
        "print(*seen, int(child.stdout) == os.SCHED_OTHER)\n")
    out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, check=True).stdout.split()
    assert out == ["fifo", "normal", "True"]


@pytest.mark.parametrize("mode", ["fifo", "normal"])
def test_every_node_reports_the_policy_it_ran_under(tmp_path, monkeypatch, mode: str) -> None:
    if mode == "fifo" and not FIFO_PERMITTED:
        pytest.skip("this host does not permit SCHED_FIFO")
    from hil.runtime.realtime.orchestrator import run_realtime
    from hil.scenario import load_scenario

    monkeypatch.setenv("XDG_RUNTIME_DIR", str(tmp_path))
    res = run_realtime(load_scenario("seed000"), tmp_path / "rt", pace=1.0, duration_s=1.0, ecus_per_process=6,
                       record=False, scheduling=mode)  # type: ignore[arg-type]
    rt = json.loads((tmp_path / "rt" / "metrics.json").read_text())["realtime"]
    assert rt["scheduling"]["policy"] == mode
    assert rt["plant"]["scheduling"] == mode
    assert len(rt["ecus"]) == 12 and {e["scheduling"] for e in rt["ecus"].values()} == {mode}
    assert any(e.source == "rig" and e.text.startswith("scheduling: ") for e in res.log.events)
    assert current_policy() == "normal"  # the orchestrator's own thread stays ordinary


def test_hil_run_refuses_scheduling_without_realtime(tmp_path) -> None:
    out = subprocess.run([sys.executable, "-m", "hil.cli", "run", "seed000", "--scheduling", "fifo", "--out",
                          str(tmp_path / "r")], capture_output=True, text=True, timeout=120)
    assert out.returncode == 2
    assert "--scheduling only applies with --realtime" in out.stderr
