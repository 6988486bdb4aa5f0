"""How far ahead a bus server may SYNC a read (protocol LEAST_DATA): no frame is shorter than an empty one without
stuff bits, unless every connection said its frames carry more, as the rig's ECU and plant nodes say from their
DBC messages. A frame shorter than its connection said is refused."""
from __future__ import annotations

import time
from pathlib import Path

import cantools
import pytest

from hil.can.bus_log import BusLog
from hil.runtime.realtime.ecu_node import least_sent_bytes
from hil.runtime.realtime.frame_io import EngineFrames
from hil.runtime.realtime.native_server import NativeBusServer
from hil.runtime.realtime.pacing import SimClock
from hil.runtime.realtime.pycan_bus import TrainhilBus
from hil.runtime.virtual import VirtualRig
from hil.scenario import load_scenario

BITRATE = 5_000  # 200 µs bits: an empty frame lasts at least 9.4 ms, one of 8 bytes 22.2 ms (wide margins)
EMPTY_S = 47 * 2e-4
DBC = Path(__file__).resolve().parents[1] / "dbc" / "train.dbc"


def sync_lead(link, ahead_s: float = 0.020) -> float:
    """Ask for a read ``ahead_s`` from now; how long before that read time its SYNC came."""
    t_read = time.time() + ahead_s
    link.read_every(t_read, 0.0)
    assert link.sync_to(t_read, 1.0)
    return t_read - time.time()


def test_a_node_that_says_its_least_frame_is_synced_that_far_ahead_and_its_shorter_frames_are_refused(rt):
    with NativeBusServer("ld", "bus1", BITRATE, log=BusLog("bus1", BITRATE)) as server:
        node = TrainhilBus("ld/bus1", node_name="N", lazy_reader=True)
        frames = EngineFrames(SimClock(time.time(), 1.0), [node], extended=False, lazy=True)
        others: list[TrainhilBus] = []
        try:
            frames.sends_at_least(0, 8)
            time.sleep(0.02)
            assert sync_lead(frames.links[0]) > EMPTY_S + 0.004  # within one of its 8-byte frames: at once
            others.append(TrainhilBus("ld/bus1", node_name="E"))  # an eager python-can node says nothing
            time.sleep(0.02)
            assert sync_lead(frames.links[0]) <= EMPTY_S + 0.0005  # it may send an empty frame
            frames.send(0, [(0x100, bytes(2))])  # fewer bytes than it said
            frames.send(0, [(0x101, bytes(8))])
            heard = [m.arbitration_id for m in iter(lambda: others[0].recv(0.1), None)]
            assert heard == [0x101]
            assert server.stats.frames_rejected == 1
        finally:
            for bus in [node, *others]:
                bus.shutdown()


def test_the_ecus_say_the_fewest_bytes_of_their_dbc_messages_and_a_program_of_its_own_says_nothing():
    rig = VirtualRig(load_scenario("seed000"))
    sent = [m for m in cantools.database.load_file(DBC).messages
            if m.name.startswith(("TractionCmd", "AgentState", "AgentAux"))]
    assert least_sent_bytes(rig.ecus) == min(m.length for m in sent) == 5
    own = rig.ecus[1]
    own.cycle = lambda t: [(0x7FF, b"")]  # replaces the standard cycle: it may send anything
    assert least_sent_bytes(rig.ecus) is None


@pytest.mark.parametrize("bytes_said", [0, 8])
def test_a_read_within_an_empty_frame_is_synced_at_once_whatever_was_said(rt, bytes_said):
    with NativeBusServer("ld", "bus1", BITRATE, log=BusLog("bus1", BITRATE)):
        node = TrainhilBus("ld/bus1", node_name="N", lazy_reader=True)
        frames = EngineFrames(SimClock(time.time(), 1.0), [node], extended=False, lazy=True)
        try:
            frames.sends_at_least(0, bytes_said)
            time.sleep(0.02)
            assert sync_lead(frames.links[0], 0.008) > 0.004  # 8 ms ahead: no frame can end by then
        finally:
            node.shutdown()
