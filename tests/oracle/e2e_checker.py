"""The engine's oracle (test code) for the receiver-side E2E check (engine/src/e2e.rs: ``Checker``)."""
from __future__ import annotations

from ecu_sim.e2e import COUNTER_MASK, COUNTER_MODULO, HEADER_BYTES, E2EStatus, e2e_crc


def next_counter(counter: int) -> int:
    """The alive counter value of the next transmission."""
    return (counter + 1) % COUNTER_MODULO


class E2EChecker:
    """Receiver-side check of one message stream: CRC, then alive-counter sequence.

    Profile-1 semantics with counter modulo 16: delta 1 -> OK, 0 -> REPEATED,
    2..max_delta+1 -> OK_SOME_LOST (max_delta frames may be lost in a row), larger -> WRONG_SEQUENCE.
    Deviation from AUTOSAR (which widens the window on every call): a WRONG_SEQUENCE frame becomes
    the new reference, so after a long outage exactly one frame is rejected before the stream is OK.
    """

    __slots__ = ("data_id", "max_delta", "name", "last_counter", "counts", "lost", "timeouts")

    def __init__(self, data_id: int, max_delta: int = 1, name: str = "") -> None:
        if not 0 <= data_id <= 0xFF:
            raise ValueError(f"E2EChecker {name!r}: data ID {data_id!r} is not in 0..255")
        if not 0 <= max_delta <= COUNTER_MODULO - 2:
            raise ValueError(f"E2EChecker {name!r}: max_delta {max_delta!r} is not in 0..{COUNTER_MODULO - 2}")
        self.data_id = data_id
        self.max_delta = max_delta
        self.name = name
        self.last_counter: int | None = None
        self.counts = [0] * len(E2EStatus)  # indexed by E2EStatus
        self.lost = 0  # frames known lost from OK_SOME_LOST gaps
        self.timeouts = 0  # times the stream went stale (counted by the receiver's freshness check)

    def reset(self) -> None:
        """Forget the sequence (next valid frame is INITIAL); keeps the statistics."""
        self.last_counter = None

    def check(self, data: bytes | bytearray | memoryview) -> E2EStatus:
        """Classify one received frame and update the sequence state and the counts."""
        if len(data) < HEADER_BYTES:
            raise ValueError(f"E2E stream {self.name!r}: frame of {len(data)} bytes has no E2E header")
        status = self._classify(data)
        self.counts[status] += 1
        return status

    def _classify(self, data: bytes | bytearray | memoryview) -> E2EStatus:
        if data[0] != e2e_crc(self.data_id, data):
            return E2EStatus.CRC_ERROR
        counter = data[1] & COUNTER_MASK
        last = self.last_counter
        self.last_counter = counter
        if last is None:
            return E2EStatus.INITIAL
        delta = (counter - last) % COUNTER_MODULO
        if delta == 1:
            return E2EStatus.OK
        if delta == 0:
            return E2EStatus.REPEATED
        if delta <= self.max_delta + 1:
            self.lost += delta - 1
            return E2EStatus.OK_SOME_LOST
        return E2EStatus.WRONG_SEQUENCE

    def count(self, status: E2EStatus) -> int:
        """Frames classified with ``status`` so far."""
        return self.counts[status]

    def summary(self) -> dict[str, int]:
        """Non-zero counts by status name, plus the number of lost frames and of timeouts."""
        out = {s.name: self.counts[s] for s in E2EStatus if self.counts[s]}
        if self.lost:
            out["LOST"] = self.lost
        if self.timeouts:
            out["TIMEOUT"] = self.timeouts
        return out
