"""The plant's and the wayside's side of the train buses, shared by the virtual and the real-time runtime.

Sensor frames out (one per unit, numbered by sample), Reference/ReferenceAux frames out, TractionCmd frames in: the
engine checks (length, CRC, Mode) and decodes them on receipt (``Network.attach_commands`` in virtual time, a
``CommandInbox`` in real time, both with ``command_table``); here each valid one has its stream's alive-counter
sequence checked and is applied to the plant as a zero-order hold (``apply``), and each refused one is counted and
logged (``refuse``). It has no transport: callers send the frames it returns.
"""
from __future__ import annotations

import trainhil_engine as engine

from ecu_sim.codec import TrainDb
from ecu_sim.runtime import Output
from ecu_sim.view import BrakeMode
from hil.scenario.layout import TrainLayout
from hil.plant.command_streams import CommandStreams
from hil.plant.dynamics import Plant
from hil.record.runlog import RunLog
from hil.reference_profile import ReferenceProfile

VALID_MODES = sorted(int(m) for m in BrakeMode)  # a TractionCmd's Mode must be one of them


class PlantCanNode:
    """Encodes what the plant and the wayside publish; applies the commands they receive (decoded by the engine)."""

    def __init__(self, db: TrainDb, layout: TrainLayout, plant: Plant, reference: ReferenceProfile, log: RunLog) -> None:
        self.db, self.layout, self.plant, self.reference, self.log = db, layout, plant, reference, log
        per_train = [range(layout.index(i, 0), layout.index(i, 0) + layout.units_per_train) for i in range(layout.n_trains)]
        #: per train bus: TractionCmd frame id -> flat unit index (the plant's acceptance filter)
        self.cmd_unit = [{db.traction_cmd(layout.train_unit(u)[1]).frame_id: u for u in units} for units in per_train]
        self.sensor_counter = [0] * layout.n_units  # alive counter = sample number of each unit's Sensor frames
        self._sensor_out = [(layout.train_unit(u)[0], db.sensor(layout.train_unit(u)[1])) for u in range(layout.n_units)]
        self.ref_counter = 0
        self.e2e_errors = 0
        self.malformed_frames = 0  # TractionCmd frames of the wrong length
        self.streams = CommandStreams(layout.n_units)  # each unit's command stream in sequence (hil/plant/command_streams.py)

    def sensor_bytes(self, train: int) -> int:
        """The fewest data bytes of the Sensor frames it sends on train ``train``'s bus (its server's horizon)."""
        return min(codec.dlc for i, codec in self._sensor_out if i == train)

    def reference_bytes(self) -> int:
        """The fewest data bytes of the wayside's frames (Reference, ReferenceAux)."""
        return min(self.db.reference.dlc, self.db.reference_aux.dlc)

    def command_table(self, train: int) -> list[tuple[int, engine.MessageCodec, int]]:
        """(frame id, codec, unit) of a train's TractionCmd frames: what the engine checks and decodes."""
        return [(fid, self.db.by_id[fid], u) for fid, u in self.cmd_unit[train].items()]

    def apply(self, u: int, force: float, mode: int, t: float, counter: int) -> bool:
        """A TractionCmd the engine checked and decoded on receipt, received at t: applied to
        the plant if it continues unit u's command stream. Whether it was applied."""
        if not self.in_sequence(u, counter, t):
            return False
        self.plant.command(u, force, mode, t)
        return True

    def refuse(self, train: int, frame_id: int, data: bytes, t: float) -> None:
        """Count and log why the engine refused a TractionCmd on receipt: its length, its CRC or its Mode."""
        if frame_id not in self.cmd_unit[train]:
            raise KeyError(f"frame 0x{frame_id:X} is not a TractionCmd of train {train + 1}")
        codec, source = self.db.by_id[frame_id], f"bus{train + 1}/plant"
        if len(data) != codec.dlc:  # a foreign or broken node: counted and logged, never decoded
            self.malformed_frames += 1
            self.log.event(t, "WARN", source, f"{codec.name}: {len(data)} bytes, DLC is {codec.dlc}: frame ignored")
        elif not codec.crc_ok(data):
            self.e2e_errors += 1
            self.log.event(t, "WARN", source, f"{codec.name}: CRC error, frame ignored")
        else:  # CRC-valid but meaningless: a firmware fault, not a command
            mode = codec.decode(data)[0]
            self.log.event(t, "WARN", source, f"{codec.name}: unknown Mode {mode:g}, frame ignored")

    def in_sequence(self, u: int, counter: int, t: float) -> bool:
        """Whether unit u's command with alive counter ``counter`` continues its stream; a rejection is counted
        and logged (the first, then at most one a second per stream)."""
        why = self.streams.accept(u, counter)
        if why is None:
            return True
        if self.streams.should_log(u, t):
            train, unit = self.layout.train_unit(u)
            what = "repeated" if why == "REPEATED" else "out of sequence"
            self.log.event(t, "WARN", f"bus{train + 1}/plant",
                           f"{self.db.traction_cmd(unit).name}: alive counter {counter} {what} (stream at "
                           f"{self.streams.held[u]}): commands lost, or a second sender on this stream? command ignored "
                           f"({self.streams.rejected[why][u]} so far)")
        return False

    def command_rejects(self) -> dict[str, dict[str, int]]:
        """Commands refused for their sequence, per unit name (metrics.json ``plant_command_rejects``)."""
        return self.streams.report([self.layout.unit_name(u) for u in range(self.layout.n_units)])

    def sensor_outputs(self) -> list[list[Output]]:
        """Sample every unit now: per train bus, its units' Sensor frames in unit order, not yet encoded (message,
        (x, v), sample number), which the engine encodes and sends in one call per bus, as it does an ECU's."""
        xs, vs = self.plant.measure()
        counters = self.sensor_counter
        out: list[list[Output]] = [[] for _ in range(self.layout.n_trains)]
        for u, ((train, codec), x, v) in enumerate(zip(self._sensor_out, xs.tolist(), vs.tolist())):
            counters[u] = c = (counters[u] + 1) & 0xF
            out[train].append((codec, (x, v), c))
        return out

    def reference_frames(self, t: float) -> list[tuple[int, bytes]]:
        """The wayside's Reference (x_r, v_r) and ReferenceAux (a_r) at time t (the same pair goes on every train bus)."""
        x_r, v_r, a_r = self.reference.state(t)  # a_r = 0 for step profiles, the ramp's slope otherwise
        self.ref_counter = c = (self.ref_counter + 1) & 0xF
        ref, aux = self.db.reference, self.db.reference_aux
        return [(ref.frame_id, ref.encode((x_r, v_r), c)), (aux.frame_id, aux.encode((a_r,), c))]
