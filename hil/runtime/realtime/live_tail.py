"""The live view of a real-time run: the orchestrator follows the plant's signal stream and sends it to a viewer.

The plant node appends its new signal rows to ``nodes/signals.bin`` every few hundred milliseconds of wall time
(plant_node.SignalStream); :class:`LiveTail` reads whole rows from it as they come and streams them with both
timelines (``sim_time`` and ``wall_time``), so the view follows the wall clock. The buses, events and timing
series come at the end of the run, as they do into run.rrd.
"""
from __future__ import annotations

import time
from pathlib import Path

from hil.scenario.layout import TrainLayout
from hil.record.live import LIVE_FLUSH_WALL_S, LiveTarget
from hil.record.runlog import RunLog

SIGNAL_STREAM = "signals.bin"  # in the nodes directory


class LiveTail:
    """Streams a running real-time rig's signals to a live target, read from the plant's signal stream."""

    def __init__(self, target: LiveTarget, sc, layout: TrainLayout, nodes_dir: Path, wall_clock: tuple[float, float],
                 recording_id: str) -> None:
        from hil.record.rerun_writer import RerunWriter  # rerun: not in the plant node, which imports SIGNAL_STREAM

        self.writer = RerunWriter(None, layout, sc.name, sc.plant.coupler_band_m, sc.trains.spacing_m,
                                  sc.trains.emergency_gap_m, realtime=True, wall_clock=wall_clock, live=target,
                                  recording_id=recording_id)
        self.path = nodes_dir / SIGNAL_STREAM
        self.log = RunLog(layout)
        self.row_bytes = 8 * self.log.signals.width
        self.offset = 0  # bytes of the stream read so far (whole rows)
        self.sent = 0  # rows sent to the viewer
        self.next_wall = 0.0

    def poll(self, _sim_now: float = 0.0) -> None:
        """Send the rows the plant streamed since the last call (at most every LIVE_FLUSH_WALL_S)."""
        now = time.monotonic()
        if now < self.next_wall:
            return
        self.next_wall = now + LIVE_FLUSH_WALL_S
        self._read()
        n = len(self.log.signals)
        if n > self.sent:
            self.writer.write_signals(self.log, self.sent, n)
            self.writer.flush()
            self.sent = n
            self.log.signals.release_before(n)  # the viewer has them

    def _read(self) -> None:
        try:
            with open(self.path, "rb") as f:
                f.seek(self.offset)
                data = f.read()
        except OSError:
            return  # not there yet
        whole = len(data) - len(data) % self.row_bytes
        if whole:
            self.log.signals.extend_bytes(data[:whole])
            self.offset += whole

    def close(self) -> None:
        self.writer.close()

