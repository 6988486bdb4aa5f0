"""The plant's check of each unit's command stream: the E2E alive counter of every TractionCmd must follow the one
before it, as the ECUs already check the streams they read.

A second sender on a stream (an external device sending another unit's TractionCmd, a babbling or misconfigured
node) shows on a shared bus only as counters out of sequence: CAN frames carry no sender. The plant therefore
holds each stream at its last accepted counter and applies a command only when its counter advances it by 1 to
``MAX_DELTA + 1``. Anything else is rejected and counted: a repeated counter (``REPEATED``), or one out of
sequence (``WRONG_SEQUENCE``). ``MAX_DELTA`` is 0: an ECU sends its command every cycle, so a command lost on the
bus costs one more cycle of the previous command (the next one is out of sequence, the one after resynchronises),
while a second sender with random counters gets one frame in 16 through, against 3 in 16 with a window of 2. A stream that restarted (an ECU restart, a new
device) is taken up again after two consecutive frames in sequence with each other, so a sender with random
counters is almost never accepted, while a sender that keeps its own consistent sequence beside the held one is
rejected whenever the two interleave. What the plant cannot tell apart: a second sender that takes over a stream
whose rightful sender has fallen silent, with counters in sequence; that needs the bus's own view of who sent what.
"""
from __future__ import annotations

from ecu_sim.e2e import COUNTER_MODULO

MAX_DELTA = 0  # commands that may be lost in a row on the bus and the stream still be in sequence
EVENT_EVERY_S = 1.0  # at most one event per stream and second of simulated time (the rest are counted)


class CommandStreams:
    """Per unit: the held alive counter, a candidate for a restarted stream, and the rejection counts."""

    def __init__(self, n_units: int) -> None:
        self.held: list[int | None] = [None] * n_units
        self.candidate: list[int | None] = [None] * n_units
        self.rejected = {"REPEATED": [0] * n_units, "WRONG_SEQUENCE": [0] * n_units}
        self._last_event = [-float("inf")] * n_units

    def accept(self, u: int, counter: int) -> str | None:
        """None when unit ``u``'s command with ``counter`` may be applied (the stream advances); else why not
        ("REPEATED" or "WRONG_SEQUENCE"), counted."""
        held = self.held[u]
        if held is None or 1 <= (counter - held) % COUNTER_MODULO <= MAX_DELTA + 1:
            self.held[u], self.candidate[u] = counter, None
            return None
        candidate = self.candidate[u]
        if candidate is not None and (counter - candidate) % COUNTER_MODULO == 1:  # a restarted stream, confirmed
            self.held[u], self.candidate[u] = counter, None
            return None
        why = "REPEATED" if counter == held else "WRONG_SEQUENCE"
        self.candidate[u] = counter
        self.rejected[why][u] += 1
        return why

    def should_log(self, u: int, t: float) -> bool:
        """Whether a rejection at ``t`` gets an event (the first, then at most one per EVENT_EVERY_S)."""
        if t - self._last_event[u] >= EVENT_EVERY_S:
            self._last_event[u] = t
            return True
        return False

    def report(self, names: list[str]) -> dict[str, dict[str, int]]:
        """Non-zero rejection counts per unit name, for metrics.json (``plant_command_rejects``)."""
        out: dict[str, dict[str, int]] = {}
        for why, per_unit in self.rejected.items():
            for name, n in zip(names, per_unit):
                if n:
                    out.setdefault(name, {})[why] = n
        return out
