"""Frame-level recording (``[recording] frames = true``): every CAN frame as a text row with its ID, name, decoded
signals, alive counter, CRC verdict and latency, on ``/buses/<bus>/frames/<ID>_<name>``.

The recorder listens on the buses' ``frame_listeners`` (one tuple appended per frame, nothing decoded on the hot
path) and formats the rows only when the recording is flushed: 15-19 µs per frame at flush time (decode, CRC
check, text; measured on seed000 on the loaded 2-core VM), and the .rrd grows several times (seed000: 1.7 MB for
5 s, about 55 bytes per frame), hence off by default. Virtual-time runs only (the real-time bus servers run
in other threads and keep no payloads).
"""
from __future__ import annotations

from collections import defaultdict
from typing import TYPE_CHECKING

import numpy as np

from hil.record.paths import frames_path

if TYPE_CHECKING:
    from ecu_sim.codec import TrainDb
    from hil.can.transmission import Transmission
    from hil.can.train_bus import TrainBus
    from hil.record.rerun_writer import RerunWriter


class FrameRecorder:
    """Collects (t_end ns, ID, data, latency ns) per bus; :meth:`write` turns the new ones into text rows."""

    def __init__(self, buses: list["TrainBus"], db: "TrainDb") -> None:
        self.db = db
        self.rows: dict[str, list[tuple[int, int, bytes, int]]] = {}  # not yet written, per bus
        for bus in buses:
            rows: list[tuple[int, int, bytes, int]] = []
            self.rows[bus.name] = rows

            def listener(tx: "Transmission", append=rows.append) -> None:
                append((tx.t_end, tx.frame_id, tx.data, tx.t_end - tx.t_enqueue))

            bus.frame_listeners.append(listener)

    def format(self, frame_id: int, data: bytes, latency_ns: int) -> tuple[str, str]:
        """(text, level) of one frame: "0x0C1 Sensor_U02 Position=108800.001 m Speed=81.9445 m/s | alive 5 | latency
        0.254 ms"; a frame not in the DBC shows its bytes; a CRC mismatch is a WARN row."""
        codec = self.db.by_id.get(frame_id)
        latency = f"latency {latency_ns * 1e-6:.3f} ms"
        container = self.db.container_by_id.get(frame_id)
        if container is not None:  # a CAN FD container: each part it carries, as its own row would say it
            rows = [self.format(p.frame_id, data[p.offset:p.offset + p.length], latency_ns)
                    for p in container.parts if p.offset + p.length <= len(data)]
            parts = " || ".join(text.rsplit(" | latency", 1)[0] for text, _ in rows)
            return f"0x{frame_id:03X} {container.name} [{parts}] | {latency}", \
                ("WARN" if any(level == "WARN" for _, level in rows) else "DEBUG")
        if codec is None or len(data) != codec.dlc:
            return f"0x{frame_id:03X} (not in the DBC) data {data.hex(' ')} | {latency}", "WARN"
        values = codec.decode(data)
        fields = " ".join(f"{s}={v:.9g}{' ' + u if u else ''}" for s, v, u in zip(codec.signals, values, codec.units))
        crc = "" if codec.crc_ok(data) else " | CRC ERROR"
        return f"0x{frame_id:03X} {codec.name} {fields} | alive {data[1] & 0xF}{crc} | {latency}", \
            ("WARN" if crc else "DEBUG")

    def write(self, writer: "RerunWriter") -> int:
        """Send the rows collected since the last call, one batched call per (bus, ID), and forget them (memory
        stays bounded by one flush interval); returns how many."""
        sent = 0
        for bus, rows in self.rows.items():
            stop = len(rows)
            by_id: dict[int, list[tuple[int, int, bytes, int]]] = defaultdict(list)
            for row in rows[:stop]:
                by_id[row[1]].append(row)
            for frame_id, group in by_id.items():
                codec = self.db.by_id.get(frame_id) or self.db.container_by_id.get(frame_id)
                texts, levels = zip(*(self.format(fid, data, lat) for _, fid, data, lat in group))
                t = np.fromiter((r[0] for r in group), dtype=np.int64, count=len(group)) * 1e-9
                writer.write_text_rows(frames_path(bus, frame_id, codec.name if codec else "unknown"), t,
                                       list(texts), list(levels))
                sent += len(group)
            del rows[:stop]
        return sent
