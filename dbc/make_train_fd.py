"""Write dbc/train_fd.dbc: dbc/train.dbc plus the CAN FD container frames that pack each sender's messages.

    python dbc/make_train_fd.py          # rewrites dbc/train_fd.dbc; tests/test_fd_dbc.py checks it is current

Every message of train.dbc stays as it is (a frame sent alone goes as itself), and three kinds of container are
added, each an FD frame whose ``ContainedMessages`` attribute lists its parts in byte order, every part a whole
message with its own E2E header (AUTOSAR's static container PDU):

* ``UnitFD_Uxx`` (0x060 + slot - 1, 20 bytes): the ECU's TractionCmd, AgentState and AgentAux of one cycle;
* ``SensorFD_A`` / ``SensorFD_B`` (0x0B8, 0x0B9, 64 bytes): the plant's Sensor frames of slots 1-8 / 9-16;
* ``ReferenceFD`` (0x0A8, 12 bytes): the wayside's Reference and ReferenceAux.

The containers' signals are their parts' signals at the parts' byte offsets, named ``<part>_<signal>``, so that
cantools (and any DBC tool) decodes a container frame on its own.
"""
from __future__ import annotations

from pathlib import Path

import cantools

from ecu_sim.codec import fd_length

HERE = Path(__file__).resolve().parent
SOURCE, TARGET = HERE / "train.dbc", HERE / "train_fd.dbc"
FD_FORMAT = 14  # VFrameFormat StandardCAN_FD
VFRAMEFORMAT = ('BA_DEF_ BO_  "VFrameFormat" ENUM  "StandardCAN","ExtendedCAN","reserved","J1939PG","reserved",'
                '"reserved","reserved","reserved","reserved","reserved","reserved","reserved","reserved","reserved",'
                '"StandardCAN_FD","ExtendedCAN_FD";')


def containers(db: cantools.database.can.Database) -> list[tuple[int, str, str, list[str]]]:
    """(frame id, name, sender, parts) of every container, from the unit slots train.dbc has."""
    names = {m.name for m in db.messages}
    slots = sum(1 for n in names if n.startswith("TractionCmd_U"))
    out = [(0x060 + u, f"UnitFD_U{u + 1:02d}", f"ECU_U{u + 1:02d}",
            [f"TractionCmd_U{u + 1:02d}", f"AgentState_U{u + 1:02d}", f"AgentAux_U{u + 1:02d}"]) for u in range(slots)]
    for k, first in enumerate(range(0, slots, 8)):
        parts = [f"Sensor_U{u + 1:02d}" for u in range(first, min(first + 8, slots))]
        out.append((0x0B8 + k, f"SensorFD_{'AB'[k]}", "Plant", parts))
    out.append((0x0A8, "ReferenceFD", "Wayside", ["Reference", "ReferenceAux"]))
    return out


def signal_line(part: cantools.database.can.Message, sig, offset: int) -> str:
    sign = "-" if sig.is_signed else "+"
    receivers = ",".join(sig.receivers) or "Vector__XXX"
    lo, hi = sig.minimum if sig.minimum is not None else 0, sig.maximum if sig.maximum is not None else 0
    return (f' SG_ {part.name}_{sig.name} : {sig.start + 8 * offset}|{sig.length}@1{sign} ({sig.scale:.12g},{sig.offset:.12g}) '
            f'[{lo:.12g}|{hi:.12g}] "{sig.unit or ""}" {receivers}')


def container_block(db, frame_id: int, name: str, sender: str, parts: list[str]) -> tuple[str, int]:
    """The BO_ block of one container and its data length."""
    lines, offset = [], 0
    for part_name in parts:
        part = db.get_message_by_name(part_name)
        lines += [signal_line(part, s, offset) for s in sorted(part.signals, key=lambda s: s.start)]
        offset += part.length
    length = fd_length(offset)
    return "\n".join([f"BO_ {frame_id} {name}: {length} {sender}", *lines]) + "\n", length


def build() -> str:
    text = SOURCE.read_text()
    db = cantools.database.load_file(SOURCE, strict=True)
    blocks, comments, attributes = [], [], []
    for frame_id, name, sender, parts in containers(db):
        block, length = container_block(db, frame_id, name, sender, parts)
        blocks.append(block)
        comments.append(f'CM_ BO_ {frame_id} "CAN FD container ({length} bytes): {", ".join(parts)}, each with its '
                        'own E2E header, sent as one frame when its sender sends them together.";')
        attributes += [f'BA_ "VFrameFormat" BO_ {frame_id} {FD_FORMAT};',
                       f'BA_ "ContainedMessages" BO_ {frame_id} "{" ".join(parts)}";',
                       f'BA_ "GenMsgCycleTime" BO_ {frame_id} {db.get_message_by_name(parts[0]).cycle_time};']
    first_cm = text.index("\nCM_ ") + 1
    text = text[:first_cm] + "\n".join(blocks) + "\n" + text[first_cm:]
    text = text.replace('CM_ "Train bus of one train', 'CM_ "CAN FD train bus of one train (dbc/make_train_fd.py '
                        'from train.dbc: its messages plus the FD containers that pack them)', 1)
    text = _after_last(text, "CM_ ", comments)
    text = _after_last(text, "BA_DEF_ ", [VFRAMEFORMAT, 'BA_DEF_ BO_  "ContainedMessages" STRING ;'])
    text = _after_last(text, "BA_DEF_DEF_ ", ['BA_DEF_DEF_  "VFrameFormat" "StandardCAN";',
                                              'BA_DEF_DEF_  "ContainedMessages" "";'])
    text = text.replace('BA_ "BusType" "CAN";', 'BA_ "BusType" "CAN FD";', 1)
    return _after_last(text, "BA_ ", attributes)


def _after_last(text: str, prefix: str, lines: list[str]) -> str:
    """Insert ``lines`` after the last line starting with ``prefix``."""
    rows = text.split("\n")
    last = max(i for i, row in enumerate(rows) if row.startswith(prefix))
    return "\n".join(rows[:last + 1] + lines + rows[last + 1:])


if __name__ == "__main__":
    TARGET.write_text(build())
    print(f"wrote {TARGET}")
