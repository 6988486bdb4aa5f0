"""The real-time rig's default process layout: ECU processes from the machine's cores (issue 25)."""
from __future__ import annotations

import pytest

from hil.runtime.realtime import orchestrator
from hil.runtime.realtime.orchestrator import default_ecus_per_process, usable_cores


@pytest.mark.parametrize("n_ecus, cores, expected", [
    (12, 2, 12),   # 2 cores: the bus servers, plant and radio take one, every ECU shares the other
    (12, 1, 12),
    (12, 4, 4),    # 3 ECU processes
    (64, 2, 64),
    (64, 8, 10),   # 7 ECU processes, the last one lighter
    (1, 16, 1),
])
def test_one_ecu_process_per_core_the_rest_of_the_rig_leaves(n_ecus: int, cores: int, expected: int) -> None:
    assert default_ecus_per_process(n_ecus, cores) == expected


def test_the_cores_are_this_process_s_affinity(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(orchestrator.os, "sched_getaffinity", lambda _pid: {0, 3, 5}, raising=False)
    assert usable_cores() == 3
    assert default_ecus_per_process(12) == 6


def test_ecu_processes_are_started_in_groups_of_the_layout(tmp_path, monkeypatch: pytest.MonkeyPatch) -> None:
    started: list[list[str]] = []

    def fake_launch(name, kind, argv, stderr_path, env):
        started.append([kind, *argv])
        return name

    monkeypatch.setattr(orchestrator, "launch_node", fake_launch)
    from hil.scenario import load_scenario
    from hil.scenario.layout import TrainLayout

    layout = TrainLayout.from_config(load_scenario("seed000").trains)
    per_process = default_ecus_per_process(layout.n_units, cores=2)
    orchestrator._start_nodes("run", layout, tmp_path, 0, 1.0, 1.0, per_process, 0.0)
    ecu_groups = [argv.count("--unit") for kind, *argv in started if kind == "ecu"]
    assert ecu_groups == [layout.n_units]  # 2 cores: one ECU process for every unit
    assert [kind for kind, *_ in started][:2] == ["plant", "radio"]
