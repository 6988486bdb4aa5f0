"""The CPUs' wake-up latency limit a real-time run holds (hil/runtime/realtime/idle_latency.py): held for the run
only, at 0 where permitted unless asked otherwise, the host's where not (said in the events), refused with the file
named where a number was asked and the host does not permit it, and never without --realtime."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from hil.runtime.realtime import idle_latency
from hil.runtime.realtime.idle_latency import (IdleLatencyHold, IdleLatencyRefused, current_limit_us, latency_us,
                                               may_hold)

needs_pm_qos = pytest.mark.skipif(not may_hold(), reason="this host does not let us hold /dev/cpu_dma_latency")


def test_the_limit_is_written_as_the_kernel_takes_it_and_let_go_on_close(tmp_path: Path) -> None:
    target = tmp_path / "latency"
    target.write_bytes(b"")
    hold = IdleLatencyHold(125, target).open()
    assert target.read_bytes() == (125).to_bytes(4, "little")
    hold.close()
    hold.close()  # twice is harmless
    assert hold.describe() == f"CPU wake-up latency held at 125 µs ({target})"
    with IdleLatencyHold(7, target) as held:  # as a context manager: held inside, let go after
        assert held._fd is not None and target.read_bytes()[-4:] == (7).to_bytes(4, "little")
    assert held._fd is None


@pytest.mark.parametrize("bad", [-1, 2**31, 1.5, True, "0"])
def test_a_limit_that_is_not_a_whole_number_of_microseconds_is_named(bad) -> None:
    with pytest.raises(ValueError, match=r"idle_latency_us=.* must be a whole number of µs from 0 to 2147483647"):
        IdleLatencyHold(bad)


def test_a_host_without_the_file_refuses_and_names_it(tmp_path: Path) -> None:
    with pytest.raises(IdleLatencyRefused, match=r"--idle-latency-us 0: cannot open .*missing .*needs root"):
        IdleLatencyHold(0, tmp_path / "missing").open()


@needs_pm_qos
def test_holding_zero_keeps_the_kernels_limit_at_zero_until_closed() -> None:
    before = current_limit_us()
    hold = IdleLatencyHold(0).open()
    try:
        assert current_limit_us() == 0
    finally:
        hold.close()
    assert current_limit_us() == before


@needs_pm_qos
def test_a_real_time_run_holds_the_limit_while_it_runs_and_reports_it(tmp_path: Path, monkeypatch) -> None:
    from hil.runtime.realtime.orchestrator import run_realtime
    from hil.scenario import load_scenario

    monkeypatch.setenv("XDG_RUNTIME_DIR", str(tmp_path))
    before, during = current_limit_us(), []
    res = run_realtime(load_scenario("seed000"), tmp_path / "rt", duration_s=0.5, ecus_per_process=12, record=False,
                       idle_latency_us=0, on_start=lambda _t0: during.append(current_limit_us()))
    assert during == [0]
    assert current_limit_us() == before
    assert json.loads((tmp_path / "rt" / "metrics.json").read_text())["realtime"]["idle_latency_us"] == 0
    assert any(e.source == "rig" and e.text.startswith("CPU wake-up latency held at 0 µs") for e in res.log.events)


def test_a_run_the_host_refuses_the_limit_fails_before_any_node_starts(tmp_path: Path, monkeypatch) -> None:
    from hil.runtime.realtime.orchestrator import run_realtime
    from hil.scenario import load_scenario

    monkeypatch.setenv("XDG_RUNTIME_DIR", str(tmp_path))
    monkeypatch.setattr(idle_latency, "CPU_LATENCY_FILE", tmp_path / "no_pm_qos")
    with pytest.raises(IdleLatencyRefused, match="no_pm_qos"):
        run_realtime(load_scenario("seed000"), tmp_path / "rt", duration_s=0.5, record=False, idle_latency_us=0)
    metrics = json.loads((tmp_path / "rt" / "metrics.json").read_text())
    assert metrics["status"] == "failed" and "no_pm_qos" in metrics["error"]
    assert not (tmp_path / "rt" / "nodes" / "plant.json").exists()


@pytest.mark.parametrize("argv, message", [
    (["--idle-latency-us", "0"], "--idle-latency-us only applies with --realtime"),
    (["--idle-latency-us", "host"], "--idle-latency-us only applies with --realtime"),
    (["--realtime", "--idle-latency-us", "-5"],
     "argument --idle-latency-us: -5 must be from 0 to 2147483647 (µs), auto or host"),
    (["--realtime", "--idle-latency-us", "low"],
     "argument --idle-latency-us: 'low' is not auto, host or a whole number of microseconds"),
])
def test_hil_run_refuses_a_limit_it_cannot_use(tmp_path: Path, argv: list[str], message: str) -> None:
    out = subprocess.run([sys.executable, "-m", "hil", "run", "seed000", *argv, "--out", str(tmp_path / "r")],
                         capture_output=True, text=True, timeout=120)
    assert out.returncode == 2
    assert message in out.stderr


def _run_seed000(tmp_path: Path, monkeypatch, read_limit: bool = True, **kwargs):
    """Half a second of seed000 in real time: the limit it held, the kernel's limit as read when every node was
    ready (with ``read_limit``), and what the run's events say of it."""
    from hil.runtime.realtime.orchestrator import run_realtime
    from hil.scenario import load_scenario

    monkeypatch.setenv("XDG_RUNTIME_DIR", str(tmp_path))
    during: list[int] = []
    res = run_realtime(load_scenario("seed000"), tmp_path / "rt", duration_s=0.5, ecus_per_process=12, record=False,
                       on_start=lambda _t0: during.append(current_limit_us()) if read_limit else None, **kwargs)
    rig_events = [e.text for e in res.log.events if e.source == "rig" and e.text.startswith("CPU wake-up latency")]
    return res.metrics["realtime"]["idle_latency_us"], during, rig_events


@needs_pm_qos
def test_by_default_a_run_holds_zero_where_permitted_and_says_so(tmp_path: Path, monkeypatch) -> None:
    before = current_limit_us()
    held, during, said = _run_seed000(tmp_path, monkeypatch)
    assert (held, during) == (0, [0])
    assert current_limit_us() == before
    assert len(said) == 1 and "held at 0 µs" in said[0] and "(auto:" in said[0]


@needs_pm_qos
def test_host_leaves_the_hosts_limit(tmp_path: Path, monkeypatch) -> None:
    before = current_limit_us()
    held, during, said = _run_seed000(tmp_path, monkeypatch, idle_latency_us="host")
    assert (held, during) == (None, [before])
    assert said == ["CPU wake-up latency: the host's (--idle-latency-us host)"]


def test_auto_where_the_host_refuses_runs_with_the_hosts_limit_and_names_why(tmp_path: Path, monkeypatch,
                                                                            capsys: pytest.CaptureFixture[str]) -> None:
    """As for a user who is not root: the run goes on, and its events and the line it starts with say why."""
    monkeypatch.setattr(idle_latency, "CPU_LATENCY_FILE", tmp_path / "no_pm_qos")
    held, _during, said = _run_seed000(tmp_path, monkeypatch, read_limit=False, idle_latency_us="auto", progress=True)
    assert held is None
    assert len(said) == 1
    assert said[0].startswith("CPU wake-up latency: the host's (auto could not hold 0 µs: cannot open")
    assert "no_pm_qos" in said[0]
    started = [line for line in capsys.readouterr().err.splitlines() if "node processes, pace 1" in line]
    assert len(started) == 1 and said[0] in started[0]


@pytest.mark.parametrize("text, value", [("auto", "auto"), ("host", "host"), ("0", 0), ("2147483647", 2**31 - 1)])
def test_the_option_takes_auto_host_or_microseconds(text: str, value) -> None:
    assert latency_us(text) == value


def test_a_bad_setting_is_refused_before_anything_runs(tmp_path: Path) -> None:
    from hil.runtime.realtime.orchestrator import run_realtime
    from hil.scenario import load_scenario

    with pytest.raises(ValueError, match="idle_latency_us='always' must be a whole number .*, or 'auto' or 'host'"):
        run_realtime(load_scenario("seed000"), tmp_path / "rt", duration_s=0.5, record=False,
                     idle_latency_us="always")  # type: ignore[arg-type]
    assert not (tmp_path / "rt").exists()


@needs_pm_qos
def test_auto_faster_than_real_time_leaves_the_hosts_limit(tmp_path: Path, monkeypatch) -> None:
    before = current_limit_us()
    held, during, said = _run_seed000(tmp_path, monkeypatch, pace=10.0)
    assert (held, during) == (None, [before])
    assert len(said) == 1 and said[0].startswith("CPU wake-up latency: the host's (auto, faster than real time")
