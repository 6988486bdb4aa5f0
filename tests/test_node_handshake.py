"""A real-time node's start (hil.runtime.realtime.pacing.handshake): it reports "ready" with its set-up heap frozen
(left out of later garbage collections) and takes T0 from the orchestrator's "go"."""
from __future__ import annotations

import subprocess
import sys

NODE = """
import gc
from hil.runtime.realtime.pacing import StopFlag, handshake
setup = [[k] for k in range(5000)]  # objects made while setting up
before = gc.get_freeze_count()
t0 = handshake(StopFlag())
print(t0, before, gc.get_freeze_count() - before >= len(setup))
"""


def run_node(stdin: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-c", NODE], input=stdin, capture_output=True, text=True, timeout=60)


def test_a_node_is_ready_with_its_set_up_objects_frozen_and_takes_t0_from_go() -> None:
    done = run_node("go 1796373335.25\n")
    assert done.returncode == 0, done.stderr
    assert done.stdout.split("\n")[:2] == ["ready", "1796373335.25 0 True"]


def test_a_node_told_to_stop_before_go_exits_quietly() -> None:
    done = run_node("stop\n")
    assert (done.returncode, done.stdout, done.stderr) == (0, "ready\n", "")
