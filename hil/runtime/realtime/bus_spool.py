"""The bus servers' per-frame rows and load windows of a real-time run, spooled to files as the run goes.

Every SPOOL_EVERY_SIM_S of simulated time (in wall time: that over the pace) the orchestrator moves each server's
new rows into ``nodes/<bus>.frames.bin`` (rows of ``hil.can.frame_stats``: t_end, frame id, latency, queueing) and
``nodes/<bus>.load.bin`` (t_window_end, load), native float64, and lets them go from the server's BusLog; so its
memory does not grow with the frames. At the end the merge reads them back chunk by chunk
(``hil.sample_table.row_chunks``), in bus time, into the recording and the bus statistics.
"""
from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from hil.can.frame_stats import WIDTH as FRAME_WIDTH
from hil.record.runlog import BusLog

# a simulated second of rows at a time: at pace 10 ten small spools a wall second, not one ten times larger (a 2 ms
# burst of the orchestrator on one of two cores made the plant and the ECUs miss deadlines once a second)
SPOOL_EVERY_SIM_S = 1.0
LOAD_WIDTH = 2


def spool_paths(nodes_dir: Path, bus: str) -> tuple[Path, Path]:
    """(frames file, load file) of bus ``bus``."""
    return nodes_dir / f"{bus}.frames.bin", nodes_dir / f"{bus}.load.bin"


class BusSpool:
    """Moves the servers' new frame rows and load windows to their files; ``tick`` from the supervising loop."""

    def __init__(self, servers: list, nodes_dir: Path, pace: float = 1.0) -> None:
        self.servers, self.nodes_dir = servers, nodes_dir
        self.every_wall_s = SPOOL_EVERY_SIM_S / pace
        self._files = {}
        self._written: dict[str, list[int]] = {}  # bus -> [frame rows, load rows] written
        for s in servers:
            name = s.log.name
            frames, load = spool_paths(nodes_dir, name)
            self._files[name] = (open(frames, "wb"), open(load, "wb"))
            self._written[name] = [0, 0]
        self._next = 0.0
        self.lost: str | None = None  # why spooling stopped (a full disk): later rows are let go unwritten

    def tick(self, _sim_now: float = 0.0) -> None:
        if time.monotonic() >= self._next:
            self.spool()
            self._next = time.monotonic() + self.every_wall_s

    def spool(self) -> None:
        """Every server's rows so far into the files (under each server's lock)."""
        for s in self.servers:
            s.with_log(self._take)

    def _take(self, log: BusLog) -> None:
        if self.lost is not None:  # the files end at the last whole spool: let the rows go, memory stays bounded
            log.frames.hand_off(len(log.frames))
            log.load.release_before(len(log.load))
            return
        try:
            self._write(log)
        except OSError as exc:  # a full disk: stop spooling here (a half-written row must not be followed by more)
            self.lost = f"{log.name}: {exc.strerror or exc}"

    def _write(self, log: BusLog) -> None:
        frames_f, load_f = self._files[log.name]
        written = self._written[log.name]
        frames = log.frames.rows_from(written[0])
        if len(frames):
            frames_f.write(np.ascontiguousarray(frames, dtype=float).tobytes())
            written[0] += len(frames)
        log.frames.hand_off(written[0])  # the merge counts them from the file
        load = log.load.rows(written[1], len(log.load))
        if len(load):
            load_f.write(load.tobytes())
            written[1] += len(load)
        log.load.release_before(written[1])
        frames_f.flush()
        load_f.flush()

    def close(self) -> None:
        """The last rows, then the files closed (before the servers close)."""
        self.spool()
        for frames_f, load_f in self._files.values():
            for f in (frames_f, load_f):
                try:
                    f.close()
                except OSError as exc:  # its last buffered rows did not fit
                    self.lost = self.lost or f"{f.name}: {exc.strerror or exc}"
