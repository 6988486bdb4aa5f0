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


@pytest.mark.parametrize("n_ecus, cores, units_per_train, expected", [
    (12, 2, 4, 12),    # seed000 on 2 cores in real time: one process, its units share the wake-ups
    (64, 2, 16, 64),
    (12, 8, 12, 2),    # many cores: a train spread over processes
])
def test_in_real_time_a_process_hosts_units_of_several_trains(n_ecus: int, cores: int, units_per_train: int,
                                                               expected: int) -> None:
    assert default_ecus_per_process(n_ecus, cores, units_per_train, pace=1.0) == expected


@pytest.mark.parametrize("n_ecus, cores, units_per_train, expected", [
    (12, 2, 4, 4),     # seed000 on 2 cores at pace 10: one process per train
    (12, 2, 12, 12),   # one train of 12: one process
    (64, 2, 16, 16),   # four trains of 16
    (12, 8, 12, 2),    # many cores: a train spread over processes
])
def test_faster_than_real_time_no_process_hosts_units_of_two_trains(n_ecus: int, cores: int, units_per_train: int,
                                                                     expected: int) -> None:
    assert default_ecus_per_process(n_ecus, cores, units_per_train, pace=10.0) == expected


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

    sc = load_scenario("seed000")
    layout = TrainLayout.from_config(sc.trains)
    per_process = default_ecus_per_process(layout.n_units, cores=2, units_per_train=sc.trains.units, pace=10.0)
    common = orchestrator._node_arguments("run", tmp_path, 0, 1.0, 10.0, fifo=False)
    processes = orchestrator.ecu_process_units(layout, per_process)
    orchestrator._start_nodes(layout, tmp_path, common, processes, 0.0)
    groups = [[int(argv[k + 1]) for k, a in enumerate(argv) if a == "--unit"] for kind, *argv in started if kind == "ecu"]
    assert groups == [[0, 1, 2, 3], [4, 5, 6, 7], [8, 9, 10, 11]]  # at pace 10, one ECU process per train
    assert [kind for kind, *_ in started] == ["plant", "ecu", "ecu", "ecu"]  # the radio is in the bus servers
    started.clear()
    orchestrator._start_nodes(layout, tmp_path, common, processes, 0.0, radio_node=True)  # SocketCAN
    assert [kind for kind, *_ in started][:2] == ["plant", "radio"]
    assert not any("--fifo" in argv for _, *argv in started)


def test_under_sched_fifo_every_node_is_told_so_restarted_ones_too(tmp_path, monkeypatch: pytest.MonkeyPatch) -> None:
    started: list[list[str]] = []
    monkeypatch.setattr(orchestrator, "launch_node", lambda name, kind, argv, stderr_path, env: started.append(argv))
    from hil.scenario import load_scenario
    from hil.scenario.layout import TrainLayout

    layout = TrainLayout.from_config(load_scenario("seed000").trains)
    common = orchestrator._node_arguments("run", tmp_path, 0, 1.0, 1.0, fifo=True)
    orchestrator._start_nodes(layout, tmp_path, common, orchestrator.ecu_process_units(layout, 4), 0.0)
    orchestrator._respawn(tmp_path, common, layout, {})(5)
    assert len(started) == 5 and all("--fifo" in argv for argv in started)
    assert started[-1][-3:] == ["--unit", "5", "--join-late"]


def test_each_node_is_told_the_cores_of_its_kind_restarted_ones_too(tmp_path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The CPU layout (hil/runtime/realtime/cpu_layout.py): the plant and the radio on the rig's cores, every ECU
    process, a restarted one too, on the ECUs'; without a layout no node is told any."""
    from hil.runtime.realtime.cpu_layout import CpuLayout
    from hil.scenario import load_scenario
    from hil.scenario.layout import TrainLayout

    started: list[tuple[str, list[str]]] = []
    monkeypatch.setattr(orchestrator, "launch_node",
                        lambda name, kind, argv, stderr_path, env: started.append((kind, argv)))
    layout = TrainLayout.from_config(load_scenario("seed000").trains)
    common = orchestrator._node_arguments("run", tmp_path, 0, 1.0, 1.0, fifo=False)
    cpus = CpuLayout(rig=(0,), ecus=(1, 2))
    orchestrator._start_nodes(layout, tmp_path, common, orchestrator.ecu_process_units(layout, 6), 0.0,
                              radio_node=True, cpus=cpus)
    orchestrator._respawn(tmp_path, common, layout, {}, cpus)(5)
    told = [(kind, argv[argv.index("--cpus") + 1]) for kind, argv in started]
    assert told == [("plant", "0"), ("radio", "0"), ("ecu", "1,2"), ("ecu", "1,2"), ("ecu", "1,2")]
    started.clear()
    orchestrator._start_nodes(layout, tmp_path, common, orchestrator.ecu_process_units(layout, 6), 0.0)
    assert started and not any("--cpus" in argv for _, argv in started)


def test_the_progress_bar_redraws_rarely_into_a_file(tmp_path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Redirected to a file, the real-time progress bar wrote a line a hundred times a second; now every 5 s."""
    with open(tmp_path / "err.log", "w") as fh:
        monkeypatch.setattr(orchestrator.sys, "stderr", fh)
        bar = orchestrator._progress_bar(10.0)
        for _ in range(100):  # half the run, in 100 ticks
            bar.update(0.05)
        bar.close()
    assert bar.mininterval == 5.0
    assert (tmp_path / "err.log").read_text().count("real time (sim s)") <= 3
