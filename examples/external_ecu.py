"""A reference external ECU: one power unit's controller as a plain python-can program, for the rig's
device-under-test slot (``hil run ... --realtime --external train2/unit3``).

It knows the rig only through the DBC: frame layouts from cantools, the E2E rule from the DBC's own comments and
``E2EDataID`` attributes, the cycle from ``GenMsgCycleTime``. It imports nothing of trainhil, so it is what a
board, or firmware in another language, would have to do too:

* receive its unit's ``Sensor_Uk`` (own position and speed) and the wayside's ``Reference`` (x_r, v_r) and
  ``ReferenceAux`` (a_r); drop frames whose E2E CRC is wrong;
* on every Sensor frame, run a PI speed law with acceleration feed-forward,
  ``a = a_r + kp (v_r - v) + ki * integral(v_r - v)``, ``F = m a``, and send ``TractionCmd_Uk`` (Mode 0, Force),
  then ``AgentState_Uk`` and ``AgentAux_Uk`` numbered with the Sensor sample's alive counter, which is how the
  DBC's neighbours match states sample by sample.

Run it once the rig prints its channels::

    hil run examples/cruise.toml --realtime --external train2/unit3 --run dut --duration 60
    python examples/external_ecu.py --channel dut/bus2 --unit 3

``--unit`` is the unit's slot in its train (1-based: ``U03``); ``--channel`` the train's bus. With a SocketCAN
board: ``--interface socketcan --channel can0``. On a packed CAN FD bus (a scenario with ``can.dbc =
"train_fd.dbc"``), give ``--dbc dbc/train_fd.dbc``: the containers it names (``ContainedMessages``) are unpacked
on receipt, and the three frames go as the unit's container, an FD frame.
"""
from __future__ import annotations

import argparse
import re
import sys
import time
from pathlib import Path

import can
import cantools

DEFAULT_DBC = Path(__file__).resolve().parents[1] / "dbc" / "train.dbc"


class E2E:
    """The DBC's end-to-end rule: a CRC-8 in byte 0 over [E2EDataID] + bytes 1.., the alive counter in byte 1."""

    RULE = re.compile(r"CRC-8 .*poly (0x[0-9A-Fa-f]+), init (0x[0-9A-Fa-f]+), xor-out (0x[0-9A-Fa-f]+)")

    def __init__(self, db: cantools.database.Database, example: str) -> None:
        comment = db.get_message_by_name(example).get_signal_by_name("CRC").comment or ""
        m = self.RULE.search(comment)
        if m is None:
            raise SystemExit(f"the DBC's CRC comment of {example} does not state the CRC rule: {comment!r}")
        self.poly, self.init, self.xor_out = (int(g, 16) for g in m.groups())

    def crc(self, data_id: int, data: bytes) -> int:
        crc = self.init
        for byte in bytes([data_id]) + bytes(data[1:]):
            crc ^= byte
            for _ in range(8):
                crc = ((crc << 1) ^ self.poly) & 0xFF if crc & 0x80 else (crc << 1) & 0xFF
        return crc ^ self.xor_out

    @staticmethod
    def data_id(msg) -> int:
        return int(msg.dbc.attributes["E2EDataID"].value)

    def ok(self, msg, data: bytes) -> bool:
        return len(data) == msg.length and data[0] == self.crc(self.data_id(msg), data)

    def encode(self, msg, values: dict[str, float], counter: int) -> bytes:
        """Encode with the signals clamped to their DBC ranges (never wrapped), then fill in the CRC."""
        clamped = {s.name: min(max(values.get(s.name, 0), s.minimum), s.maximum) for s in msg.signals}
        clamped.update(CRC=0, AliveCounter=counter & 0xF)
        data = bytearray(msg.encode(clamped, scaling=True, strict=False))
        data[0] = self.crc(self.data_id(msg), data)
        return bytes(data)


class Containers:
    """The DBC's CAN FD containers: messages whose ``ContainedMessages`` attribute lists the messages they carry,
    each at the byte offset where the previous one ends."""

    def __init__(self, db: cantools.database.Database) -> None:
        self.parts: dict[int, list[tuple[object, int]]] = {}  # container id -> [(part message, byte offset)]
        for msg in db.messages:
            attr = msg.dbc.attributes.get("ContainedMessages") if msg.dbc else None
            if attr is None or not str(attr.value).strip():
                continue
            offset, parts = 0, []
            for name in str(attr.value).split():
                part = db.get_message_by_name(name)
                parts.append((part, offset))
                offset += part.length
            self.parts[msg.frame_id] = parts
        self.length = {m.frame_id: m.length for m in db.messages if m.frame_id in self.parts}

    def carrying(self, ids: list[int]) -> list[int]:
        """The containers that carry any of ``ids`` (a receiver of ``ids`` must accept them too)."""
        return [c for c, parts in self.parts.items() if any(m.frame_id in ids for m, _ in parts)]

    def unpack(self, frame_id: int, data: bytes) -> list[tuple[int, bytes]]:
        """A container's parts that lie within ``data``; any other frame as it is."""
        if frame_id not in self.parts:
            return [(frame_id, data)]
        return [(m.frame_id, data[o:o + m.length]) for m, o in self.parts[frame_id] if o + m.length <= len(data)]

    def pack(self, frames: list[tuple[int, bytes]]) -> list[tuple[int, bytes]]:
        """The frames as one container when some container holds exactly these, in this order; else as they are."""
        ids = [fid for fid, _ in frames]
        for c, parts in self.parts.items():
            if [m.frame_id for m, _ in parts] == ids:
                data = bytearray(self.length[c])
                for (m, o), (_, part) in zip(parts, frames):
                    data[o:o + len(part)] = part
                return [(c, bytes(data))]
        return frames


class PiSpeedEcu:
    """Unit slot k's firmware: PI on the reference speed, sent on every Sensor frame."""

    def __init__(self, db, unit: int, mass_kg: float, kp: float, ki: float) -> None:
        k = f"U{unit:02d}"
        self.db, self.e2e = db, E2E(db, f"TractionCmd_{k}")
        self.sensor = db.get_message_by_name(f"Sensor_{k}")
        self.ref, self.ref_aux = db.get_message_by_name("Reference"), db.get_message_by_name("ReferenceAux")
        self.cmd = db.get_message_by_name(f"TractionCmd_{k}")
        self.state, self.aux = db.get_message_by_name(f"AgentState_{k}"), db.get_message_by_name(f"AgentAux_{k}")
        self.mass_kg, self.kp, self.ki = mass_kg, kp, ki
        self.period_s = self.cmd.cycle_time / 1000.0  # GenMsgCycleTime
        self.v_ref = self.a_ref = None
        self.integral = 0.0
        self.cmd_counter = 0
        self.sent = self.dropped = 0

    def receive_ids(self) -> list[int]:
        return [self.sensor.frame_id, self.ref.frame_id, self.ref_aux.frame_id]

    def on_frame(self, frame_id: int, data: bytes) -> list[tuple[int, bytes]]:
        """Handle one received frame; the frames to send (on a Sensor frame)."""
        msg = self.db.get_message_by_frame_id(frame_id)
        if not self.e2e.ok(msg, data):
            self.dropped += 1
            return []
        values = msg.decode(data)
        if msg is self.ref:
            self.v_ref = values["Speed"]
        elif msg is self.ref_aux:
            self.a_ref = values["Accel"]
        elif msg is self.sensor:
            return self.cycle(values["Position"], values["Speed"], data[1] & 0xF)
        return []

    def cycle(self, x: float, v: float, sample: int) -> list[tuple[int, bytes]]:
        if self.v_ref is None:  # no reference yet: hold (the plant's fail-safe brakes if we stay silent)
            accel, force, mode = 0.0, 0.0, 1
        else:
            err = self.v_ref - v
            self.integral += err * self.period_s
            accel = (self.a_ref or 0.0) + self.kp * err + self.ki * self.integral
            force, mode = self.mass_kg * accel, 0
        self.cmd_counter = (self.cmd_counter + 1) & 0xF
        return [(self.cmd.frame_id, self.e2e.encode(self.cmd, {"Mode": mode, "Force": force}, self.cmd_counter)),
                (self.state.frame_id, self.e2e.encode(self.state, {"Position": x, "Speed": v}, sample)),
                (self.aux.frame_id, self.e2e.encode(self.aux, {"Accel": accel, "Force": force}, sample))]


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description="A reference external ECU for the trainhil device-under-test slot.")
    p.add_argument("--channel", required=True, help="python-can channel of the unit's train bus, e.g. dut/bus2")
    p.add_argument("--interface", default="trainhil", help="python-can interface (default trainhil; or socketcan)")
    p.add_argument("--unit", type=int, required=True, help="the unit's slot in its train, 1-based (U03: 3)")
    p.add_argument("--dbc", type=Path, default=DEFAULT_DBC, help="the train DBC (default: the rig's dbc/train.dbc)")
    p.add_argument("--mass-kg", type=float, default=80e3, help="the unit's mass (default 80 t, as examples/cruise.toml)")
    p.add_argument("--kp", type=float, default=0.5, help="speed gain (1/s)")
    p.add_argument("--ki", type=float, default=0.05, help="integral gain (1/s^2)")
    p.add_argument("--duration", type=float, default=None, help="stop after this many wall seconds (default: "
                   "when the bus goes away)")
    args = p.parse_args(argv)
    db = cantools.database.load_file(args.dbc)
    ecu, containers = PiSpeedEcu(db, args.unit, args.mass_kg, args.kp, args.ki), Containers(db)
    ids = ecu.receive_ids()
    wanted = set(ids)
    filters = [{"can_id": i, "can_mask": 0x7FF, "extended": False} for i in ids + containers.carrying(ids)]
    end = None if args.duration is None else time.monotonic() + args.duration
    fd = bool(containers.parts)  # a packed DBC is for CAN FD buses
    with can.Bus(interface=args.interface, channel=args.channel, can_filters=filters, fd=fd) as bus:
        print(f"external ECU U{args.unit:02d} on {args.channel}", flush=True)
        while end is None or time.monotonic() < end:
            try:
                msg = bus.recv(timeout=1.0)
            except can.CanOperationError:  # the run ended: the bus server went away
                break
            if msg is None or msg.is_error_frame or msg.is_remote_frame:
                continue
            for part_id, part in containers.unpack(msg.arbitration_id, bytes(msg.data)):
                if part_id not in wanted:  # a container's other parts (absent units' slots are zero): not ours
                    continue
                out = ecu.on_frame(part_id, part)
                for frame_id, data in containers.pack(out):
                    bus.send(can.Message(arbitration_id=frame_id, data=data, is_extended_id=False, is_fd=len(data) > 8,
                                         bitrate_switch=len(data) > 8))
                ecu.sent += len(out)
    print(f"sent {ecu.sent} frames, dropped {ecu.dropped} with a bad E2E CRC", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
