"""The real-time rig's scheduling (hil/runtime/realtime/scheduling.py): SCHED_FIFO where the host permits it, the
normal scheduler with the reason where it does not, and what each node really ran under in metrics.json."""
from __future__ import annotations

import json
import os
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
    out = subprocess.run([sys.executable, "-m", "hil", "run", "seed000", "--scheduling", "fifo", "--out",
                          str(tmp_path / "r")], capture_output=True, text=True, timeout=120)
    assert out.returncode == 2
    assert "--scheduling only applies with --realtime" in out.stderr


# --------------------------------------------------------------------------- the standalone bus server


def serve_briefly(tmp_path, *options: str) -> tuple[subprocess.CompletedProcess, dict]:
    """``hil bus-server`` for 0.3 s with ``options``; its run and its final statistics."""
    stats = tmp_path / "stats.json"
    proc = subprocess.run([sys.executable, "-m", "hil.runtime.realtime.bus_server", "--run", "sched", "--bus", "bus1",
                           "--duration", "0.3", "--stats-json", str(stats), *options],
                          capture_output=True, text=True, timeout=60, env={**os.environ, "XDG_RUNTIME_DIR": str(tmp_path)})
    return proc, json.loads(stats.read_text()) if stats.exists() else {}


def test_the_standalone_server_sleeps_to_frame_ends_under_sched_fifo_and_spins_under_the_normal_scheduler(tmp_path):
    """By default where permitted, SCHED_FIFO and no spin (bench_busserver --busy-core: p99 61-82 us against
    198-301 us spinning 200 us under the normal scheduler); the statistics say which it ran under."""
    proc, stats = serve_briefly(tmp_path)
    assert proc.returncode == 0, proc.stderr
    assert (stats["scheduling"], stats["spin_us"]) == (("fifo", 0) if FIFO_PERMITTED else ("normal", 200))
    proc, stats = serve_briefly(tmp_path, "--scheduling", "normal")
    assert proc.returncode == 0 and (stats["scheduling"], stats["spin_us"]) == ("normal", 200), proc.stderr
    proc, stats = serve_briefly(tmp_path, "--spin-us", "30")
    assert proc.returncode == 0 and stats["spin_us"] == 30, proc.stderr
    proc, _ = serve_briefly(tmp_path, "--fifo", "5", "--scheduling", "normal")
    assert proc.returncode == 2 and "--fifo PRIORITY with --scheduling normal: choose one" in proc.stderr
    proc, _ = serve_briefly(tmp_path, "--fifo", "0")
    assert proc.returncode == 2 and "'0' is not a SCHED_FIFO priority (a whole number from 1 to 99)" in proc.stderr


def test_the_standalone_server_refused_sched_fifo_falls_back_or_exits_1(tmp_path, monkeypatch, capsys):
    from hil.runtime.realtime.command_line import bus_server_main

    monkeypatch.setattr(scheduling.os, "sched_setscheduler", refuse)
    chosen = scheduling.choose_server_scheduling("auto", 7)
    assert chosen.policy == "normal" and "Operation not permitted" in chosen.why_normal
    monkeypatch.setenv("XDG_RUNTIME_DIR", str(tmp_path))
    assert bus_server_main(["--run", "sched", "--bus", "bus1", "--scheduling", "fifo", "--fifo", "7"]) == 1
    err = capsys.readouterr().err
    assert "hil bus-server: error: --scheduling fifo: SCHED_FIFO is not permitted here" in err and "ulimit -r 7" in err
    assert not (tmp_path / "trainhil" / "sched").exists()  # refused before any socket was made
