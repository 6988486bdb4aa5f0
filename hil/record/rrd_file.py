"""What an .rrd file holds before rerun reads it: a recording at all, whole, or cut short (a run killed, a disk
that filled), and the bytes of its complete messages.

The framing (rerun's RRD stream, as written by rerun-sdk 0.41): a 12-byte header starting "RRF2", then messages of
a 16-byte header (kind, payload length: two little-endian u64) and the payload; kind 0 ends the stream (a footer
follows). rerun's reader refuses a file whose last message is cut; the complete ones before it are still good.
"""
from __future__ import annotations

import struct
from pathlib import Path
from typing import NamedTuple

MAGIC = b"RRF2"
FILE_HEADER_BYTES = 12
MESSAGE_HEADER = struct.Struct("<QQ")
END_KIND = 0


class RrdCheck(NamedTuple):
    """``ok``: a recording; ``whole``: it reaches its end marker; ``complete_bytes``: the length of its header and
    complete messages; ``messages``: how many; ``why``: what is wrong, for one line."""

    ok: bool
    whole: bool
    complete_bytes: int
    messages: int
    why: str = ""


def check_rrd(path: Path) -> RrdCheck:
    """Walk the file's message framing (reading headers only)."""
    try:
        size = path.stat().st_size
        with open(path, "rb") as f:
            if f.read(4) != MAGIC or size < FILE_HEADER_BYTES:
                return RrdCheck(False, False, 0, 0, "empty" if size == 0 else "not a rerun recording (no RRF2 header)")
            offset, messages = FILE_HEADER_BYTES, 0
            while offset + MESSAGE_HEADER.size <= size:
                f.seek(offset)
                kind, length = MESSAGE_HEADER.unpack(f.read(MESSAGE_HEADER.size))
                if kind == END_KIND:
                    return RrdCheck(True, True, offset, messages)
                if offset + MESSAGE_HEADER.size + length > size:
                    break
                offset += MESSAGE_HEADER.size + length
                messages += 1
    except OSError as exc:
        return RrdCheck(False, False, 0, 0, exc.strerror or str(exc))
    if messages == 0:
        return RrdCheck(False, False, offset, 0, "cut before its first message")
    return RrdCheck(True, False, offset, messages, "cut short")
