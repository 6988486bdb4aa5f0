"""The radio in the real-time bus servers (issue 25, engine/src/radio_hub.rs): a routed frame that ends on one
train's bus is queued on the next train's bus by the engine itself, at its end plus the link's latency, exactly,
with no radio process; injected faults drop frames there and are counted as in virtual time."""
from __future__ import annotations

import time

import can
import numpy as np
import pytest

from hil.can.bus_log import BusLog
from hil.can.frame import frame_bits
from hil.faults.radio import RadioFaults
from hil.runtime.realtime.engine_radio import EngineRadio
from hil.runtime.realtime.native_server import NativeBusServer
from hil.runtime.realtime.pycan_bus import TrainhilBus
from hil.runtime.train_db import load_train_db
from hil.scenario import load_scenario
from hil.scenario.model import RadioBlackoutFault

LATENCY_S = 0.005


@pytest.fixture
def rig(rt, tmp_path):
    """seed000's three train buses with the engine's radio (5 ms latency, no jitter or loss), saving its counters
    to ``tmp_path``."""
    sc = load_scenario("seed000", {"radio.latency_s": LATENCY_S})
    db = load_train_db(sc)
    radio = EngineRadio(sc, db, seed=1, pace=1.0, packing=None, save_to=tmp_path)
    servers = [NativeBusServer("er", f"bus{i + 1}", sc.can.bitrate, log=BusLog(f"bus{i + 1}", sc.can.bitrate),
                               radio=radio.port(i)).start() for i in range(3)]
    try:
        yield sc, db, radio
    finally:
        for s in servers:
            s.close()
        radio.close()


def tail_state(db, x_m: float) -> tuple[int, bytes]:
    """Train 1's tail unit's AgentState (routed over link 1>2 as the 'train ahead' frame)."""
    msg = db.agent_state(3)
    return msg.frame_id, msg.encode((x_m, 80.0), 1)


def test_a_routed_frame_is_queued_on_the_next_bus_at_its_end_plus_the_latency(rig):
    sc, db, radio = rig
    sender = TrainhilBus("er/bus1", node_name="T1U4", receive_own_messages=True)
    receiver = TrainhilBus("er/bus2", node_name="T2U1",
                           can_filters=[{"can_id": db.radio_ahead_state.frame_id, "can_mask": 0x7FF}])
    try:
        frame_id, data = tail_state(db, 200_000.0)
        sender.send(can.Message(arbitration_id=frame_id, data=data, is_extended_id=False))
        own = sender.recv(1.0)
        got = receiver.recv(1.0)
        assert own is not None and got is not None, "the frame did not cross the radio"
        assert got.arbitration_id == db.radio_ahead_state.frame_id and bytes(got.data) == data
        # queued on the idle bus 2 at (end on bus 1) + latency, then on the wire for one frame time
        duration = frame_bits(got.arbitration_id, bytes(got.data), False) / sc.can.bitrate
        assert got.timestamp - own.timestamp == pytest.approx(LATENCY_S + duration, abs=3e-6)
        time.sleep(0.05)
        assert radio.stats()["1>2"] == {"offered": 1, "delivered": 1, "out_of_range": 0, "blackout": 0, "lost": 0,
                                        "rate_capped": 0}
        assert radio.stats()["2>1"]["offered"] == 0 and radio.starved == 0
    finally:
        sender.shutdown()
        receiver.shutdown()


def test_a_lazy_reader_on_the_next_bus_gets_the_delivery_at_its_exact_time_without_a_wake_up_for_it(rig):
    """Only lazy readers on bus 2: its server is not woken for the delivery, it takes it at its next wake-up
    (before the reader's read time) and the frame still goes on the wire at end + latency."""
    import trainhil_engine as engine

    sc, db, radio = rig
    sender = TrainhilBus("er/bus1", node_name="T1U4", receive_own_messages=True)
    reader_bus = TrainhilBus("er/bus2", node_name="T2U1", lazy_reader=True,
                             can_filters=[{"can_id": db.radio_ahead_state.frame_id, "can_mask": 0x7FF}])
    reader = engine.FrameLink(reader_bus.fileno(), 0.0, 1.0, keep=True, lazy=True)
    try:
        t_read = time.time() + 0.05
        reader.read_every(t_read, 0.0)
        time.sleep(0.01)
        frame_id, data = tail_state(db, 200_000.0)
        sender.send(can.Message(arbitration_id=frame_id, data=data, is_extended_id=False))
        own = sender.recv(1.0)
        assert own is not None
        assert reader.sync_to(t_read, 1.0), "no SYNC of the read time"
        got = reader.take()
        assert [(fid, d) for fid, d, _ in got] == [(db.radio_ahead_state.frame_id, data)]
        duration = frame_bits(db.radio_ahead_state.frame_id, data, False) / sc.can.bitrate
        assert got[0][2] - own.timestamp == pytest.approx(LATENCY_S + duration, abs=3e-6)
    finally:
        sender.shutdown()
        reader_bus.shutdown()


def test_the_counters_are_saved_as_the_run_goes_for_hil_recover(rig, tmp_path):
    import json

    from hil.runtime.realtime.engine_radio import SAVE_EVERY_S

    sc, db, radio = rig
    sender = TrainhilBus("er/bus1", node_name="T1U4")
    try:
        frame_id, data = tail_state(db, 200_000.0)
        sender.send(can.Message(arbitration_id=frame_id, data=data, is_extended_id=False))
        deadline = time.monotonic() + 10 * SAVE_EVERY_S
        while time.monotonic() < deadline:
            saved = json.loads((tmp_path / "radio.json").read_text()) if (tmp_path / "radio.json").exists() else {}
            if saved.get("links", {}).get("1>2", {}).get("offered"):
                break
            time.sleep(0.1)
        assert saved["links"]["1>2"]["offered"] == 1 and saved["starved"] == 0
    finally:
        sender.shutdown()


def test_an_injected_blackout_drops_the_frames_and_counts_them(rig):
    sc, db, radio = rig
    rng = np.random.default_rng(0)
    faults = RadioFaults(radio.links, 3, rng, radio.impairment_setter(rng))
    spec = RadioBlackoutFault(kind="radio_blackout", pair=1, at_s=0.0, duration_s=1.0)
    sender = TrainhilBus("er/bus1", node_name="T1U4")
    receiver = TrainhilBus("er/bus2", node_name="T2U1",
                           can_filters=[{"can_id": db.radio_ahead_state.frame_id, "can_mask": 0x7FF}])
    try:
        faults.start(spec, 0)
        frame_id, data = tail_state(db, 200_000.0)
        sender.send(can.Message(arbitration_id=frame_id, data=data, is_extended_id=False))
        assert receiver.recv(0.1) is None
        faults.end(spec, 0)
        sender.send(can.Message(arbitration_id=frame_id, data=data, is_extended_id=False))
        assert receiver.recv(1.0) is not None
        time.sleep(0.05)
        stats = radio.stats()["1>2"]
        assert (stats["offered"], stats["delivered"], stats.get("fault")) == (2, 1, 1)
    finally:
        sender.shutdown()
        receiver.shutdown()


def test_the_radio_hub_refuses_what_the_virtual_network_refuses(rig):
    """Routes and impairments are checked by the engine's gateway itself, the same for both runtimes."""
    import trainhil_engine as engine

    _, _, radio = rig
    for target in (radio.hub, engine.Network()):
        with pytest.raises(IndexError, match="no radio link 99"):
            target.add_route(0, 0x100, 1, 0x300, 99, None)
        with pytest.raises(IndexError, match="no radio link 99"):
            target.set_impairment(99, True, [], 0, lambda: [0.5])
    with pytest.raises(ValueError, match=r"radio link 1>2: loss probability 1.5 is not in \[0, 1\]"):
        radio.hub.set_impairment(0, False, [1.5], 0, lambda: [0.5])


def test_a_top_up_says_how_many_blocks_the_busiest_link_used_and_refills_them(rig):
    """``top_up`` returns the blocks the busiest link drew since the last one (the top-up thread's measure of how
    soon to come back): 1,100 routed frames take two blocks of 1,024 draws; none are starved."""
    sc, db, radio = rig
    radio.close()  # the top-up thread stops: this test tops up itself
    assert radio.hub.top_up() == 0
    sender = TrainhilBus("er/bus1", node_name="T1U4")
    try:
        frame_id, data = tail_state(db, 200_000.0)
        for sent in range(50, 1_101, 50):  # 50 at a time, under the TX queue's depth, each batch on the wire first
            for _ in range(50):
                sender.send(can.Message(arbitration_id=frame_id, data=data, is_extended_id=False))
            deadline = time.monotonic() + 10.0
            while radio.stats()["1>2"]["offered"] < sent and time.monotonic() < deadline:
                time.sleep(0.01)
        assert radio.stats()["1>2"]["offered"] == 1_100 and radio.starved == 0
        assert radio.hub.top_up() == 2
        assert radio.hub.top_up() == 0  # refilled
    finally:
        sender.shutdown()


@pytest.mark.parametrize("used, waited, pace, expected", [
    (0, 0.1, 1.0, 0.5),  # quiet: the longest wait
    (1, 0.5, 1.0, 0.5),  # one block in half a second: 2 s to half the reserve, capped
    (2, 0.1, 1.0, 0.2),  # two blocks in 0.1 s: half the reserve (4) in 0.2 s
    (8, 0.1, 1.0, 0.1),  # the whole reserve in 0.1 s: never shorter than TOP_UP_S
    (0, 0.1, 10.0, 0.1),  # pace 10: ten times the frames per wall second, so the shortest wait
    (0, 0.1, 2.0, 0.25),
    (0, 0.1, 0.5, 0.5),  # slower than real time: no longer than at pace 1
])
def test_the_top_up_wait_keeps_half_the_reserve_at_the_busiest_links_rate(used, waited, pace, expected):
    from hil.runtime.realtime.engine_radio import next_top_up_wait

    assert next_top_up_wait(used, waited, 8, pace) == pytest.approx(expected)
