"""Not firmware: a bound for the benches. ``NullFirmware`` sends each cycle the frames the standard firmware sends
(TractionCmd, AgentState, AgentAux: the same load on the bus, encoded by the engine in one call) without reading a
frame or running its law, so a run with it costs what the rig around the firmware costs: the wake-ups and SYNCs,
the bus servers, the plant and the orchestrator. ``bench/bench_realtime_scale.py --firmware standard null``.

Used as an ECU program by reference (``ecu.program = "bench.null_firmware:NullFirmware"``); the trains coast (no
force), so the loop is not the standard one's.
"""
from __future__ import annotations

from ecu_sim.runtime import Ecu, Output
from ecu_sim.view import BrakeMode

REFERENCE = "bench.null_firmware:NullFirmware"


class NullFirmware(Ecu):
    """The standard three frames a cycle, no force, all three numbered by the cycle (the standard firmware numbers
    AgentState and AgentAux by its sensor's sample, which this one never reads); nothing read or run."""

    def cycle_outputs(self, t: float) -> list[Output]:
        self.counters.cycles += 1
        self._cmd_counter = c = (self._cmd_counter + 1) & 0xF
        cmd, state, aux = self.sent_messages()
        return [(cmd, (int(BrakeMode.NORMAL), 0.0), c), (state, (0.0, 0.0), c), (aux, (0.0, 0.0), c)]
