"""A real-time run's memory does not grow with its length: the bus servers' rows are spooled to files as the run
goes (hil/runtime/realtime/bus_spool.py) and the merge streams them, and the plant's signals, chunk by chunk into
the recording and the metrics; letting each chunk go gives the metrics of keeping them all."""
from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from hil.scenario.layout import TrainLayout
from hil.record.metrics import compute_metrics
from hil.record.runlog import SUMMARY_BLOCK_ROWS, BusLog
from hil.runtime.realtime import bus_spool
from hil.runtime.realtime.bus_spool import FRAME_WIDTH, BusSpool, spool_paths
from hil.sample_table import row_chunks
from hil.runtime.realtime.merge import _stream_bus, merge_nodes
from hil.runtime.realtime.orchestrator import run_realtime
from hil.scenario import load_scenario
from tests.test_realtime_rig import rt  # noqa: F401  (fixture)
from tests.test_signal_summary import assert_same


class FakeServer:
    """A bus server's log and lock, as BusSpool sees them."""

    def __init__(self, name: str) -> None:
        self.log = BusLog(name, 500_000)
        self.epoch0 = 0.0

    def with_log(self, fn):
        return fn(self.log)


def test_the_spool_moves_the_rows_to_files_and_the_server_keeps_none(tmp_path):
    server = FakeServer("bus1")
    spool = BusSpool([server], tmp_path)
    rows = np.column_stack((np.arange(5000) * 1e-4, np.full(5000, 0x80), np.full(5000, 2e-4), np.zeros(5000)))
    for k in range(0, 5000, 1000):
        server.log.frames.extend_bytes(rows[k:k + 1000].tobytes())
        server.log.load.append((k * 1e-4, 0.3))
        spool.spool()
        assert len(server.log.frames.array) == 0 and len(server.log.load.array) <= 1
    spool.close()
    frames_path, load_path = spool_paths(tmp_path, "bus1")
    back = np.concatenate(list(row_chunks(frames_path, FRAME_WIDTH, rows=777)))
    assert np.array_equal(back, rows) and len(list(row_chunks(load_path, 2))[0]) == 5


def test_the_spool_moves_a_simulated_second_at_a_time_so_a_faster_pace_spools_more_often(tmp_path, monkeypatch):
    """At pace 10 ten small spools a wall second, not one ten times larger (a burst on one of two cores)."""
    clock = [100.0]
    monkeypatch.setattr(bus_spool, "time", SimpleNamespace(monotonic=lambda: clock[0]))  # this module's clock only
    spools = {}
    for pace in (1.0, 10.0):
        (tmp_path / f"pace{pace}").mkdir()
        spools[pace] = BusSpool([FakeServer("bus1")], tmp_path / f"pace{pace}", pace)
    calls = {pace: 0 for pace in spools}
    for pace, spool in spools.items():
        monkeypatch.setattr(spool, "spool", lambda p=pace: calls.__setitem__(p, calls[p] + 1))
    for _ in range(1000):  # one wall second in 1 ms turns
        for spool in spools.values():
            spool.tick()
        clock[0] += 0.001
    assert calls[1.0] == 1 and calls[10.0] == 10


def test_a_real_time_run_merged_chunk_by_chunk_has_the_metrics_of_the_whole(rt, tmp_path):  # noqa: F811
    sc = load_scenario("seed000")
    res = run_realtime(sc, tmp_path / "rt", pace=1.0, duration_s=3.0, ecus_per_process=6, record=False,
                       keep_signals=False)
    # streamed; rows are let go a summary block (SUMMARY_BLOCK_ROWS) at a time, so 30 rows are all still held
    assert len(res.log.signals) == 30 and len(res.log.signals.array) == 30 < SUMMARY_BLOCK_ROWS
    # the rows were let go, their summary kept (about 6000 frames in 3 s; fewer when a loaded machine delays nodes)
    assert len(res.log.buses[0].frames.array) == 0 and res.log.buses[0].frames.summary()[0].n > 1000
    nodes = tmp_path / "rt" / "nodes"
    layout = TrainLayout.from_config(sc.trains)
    servers = [SimpleNamespace(log=BusLog(f"bus{i + 1}", sc.can.bitrate), epoch0=0.0) for i in range(3)]
    merged = [merge_nodes(sc, layout, nodes, servers, [], None, 1.0, 3.0, 3.0, None, keep_rows=keep)[0]
              for keep in (True, False)]
    whole, let_go = (compute_metrics(log, sc.plant.coupler_band_m) for log in merged)
    assert len(merged[0].signals.array) == len(merged[1].signals.array) == 30  # under one block: none let go yet
    assert_same(let_go, whole)
    assert whole["per_bus"]["bus1"]["latency_p99_s"] is not None


def test_the_merge_keeps_only_whole_load_windows_and_the_frames_of_the_run(tmp_path):
    """A server whose load windows are not aligned to the run's zero (one the rig did not align, as before
    ``align_load_windows``): here the first window the run sees ends 1 ms after its start and is 99 % before it
    (load 0.004). The cut keeps whole windows only, so the mean load is the run's (it read 0.41 for 0.43 over a
    3 s run of seed000 with that window in). Its frames sent are those in the run."""
    ends = 0.1 * np.arange(1, 32)  # the server's windows, in its time; the run starts at its 0.099 s
    loads = np.where(ends < 0.15, 0.004, 0.43)
    spool_paths(tmp_path, "bus1")[1].write_bytes(np.column_stack((ends, loads)).tobytes())
    frame_ends = np.array([0.05, 0.5, 1.5, 3.2, 3.3])  # in its time: one before the run, two after its end
    frames = np.column_stack((frame_ends, np.full(5, 0x80), np.full(5, 2e-4), np.zeros(5)))
    spool_paths(tmp_path, "bus1")[0].write_bytes(frames.tobytes())
    log = _stream_bus(BusLog("bus1", 500_000, frames_sent=5), tmp_path, 0.099, 3.0, (), True)
    t = log.load.array[:, 0]
    assert np.allclose(t, 0.001 + 0.1 * np.arange(1, 30)) and log.load.count == 29  # 0.101 .. 2.901: whole ones
    assert log.load.sum / log.load.count == pytest.approx(0.43)
    assert log.frames_sent == len(log.frames.array) == 2  # the run's frames: the server's count went on past it
