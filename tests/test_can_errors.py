"""CAN errors (the oracle tests/oracle/bus_errors.py; the engine has the same model): the receiver's bit-level checks, fault confinement against ISO 11898-1,
bus-off and its recovery timing, retransmission, and the babbling idiot against the WCRT analysis."""
from __future__ import annotations

import random

import numpy as np
import pytest

from tests.oracle.python_bus import VirtualCanBus
from tests.oracle.bus_errors import (ERROR_TAIL_BITS, BusErrors, Corruption, ErrorCounters, ErrorState, FrameSelection,
                            corrupt, receive, wire_bits)
from hil.can.frame import frame_bits
from hil.can.wcrt import CanMessage, response_times
from hil.runtime.kernel import Kernel

BIT_NS = 2000  # 500 kbit/s


def make_bus() -> tuple[Kernel, VirtualCanBus, BusErrors, list]:
    kernel = Kernel()
    bus = VirtualCanBus(kernel, "bus1", 500_000)
    events: list[tuple[int, str, str]] = []
    errors = BusErrors(bus, lambda t, level, text: events.append((t, level, text)), np.random.default_rng(1))
    return kernel, bus, errors, events


# --------------------------------------------------------------------------- the receiver


def test_clean_frames_decode_and_match_the_exact_frame_length():
    rng = random.Random(3)
    for _ in range(500):
        ext = rng.random() < 0.3
        cid = rng.randrange(1 << (29 if ext else 11))
        data = bytes(rng.randrange(256) for _ in range(rng.randint(0, 8)))
        wire = wire_bits(cid, data, ext)
        assert len(wire) + 3 == frame_bits(cid, data, ext)  # + intermission
        got = receive(wire)
        assert (got.error, got.can_id, got.extended, got.data) == (None, cid, ext, data)


def test_every_single_bit_flip_is_detected_and_each_check_fires():
    """CAN detects any single bit error (CRC-15 has Hamming distance 6; stuffing and form checks add to it)."""
    found = set()
    for cid, data in ((0x0C1, bytes.fromhex("5a01020304050607")), (0x000, bytes(8)), (0x7FF, b"\xff" * 8), (0x123, b"")):
        wire = wire_bits(cid, data)
        for p in range(1, len(wire) - 9):  # after SOF up to the CRC delimiter
            got = receive(corrupt(wire, [p]))
            assert got.error is not None, f"flip of bit {p} in 0x{cid:03X} went undetected"
            # by the ACK delimiter, or (a flipped DLC makes the frame look longer) by six recessive EOF bits
            assert 0 < got.at <= len(wire) - 8 or (got.error == "stuff" and got.at < len(wire) + 6)
            found.add(got.error)
    assert found == {"stuff", "form", "crc"}


def test_crc_error_is_signalled_after_the_ack_delimiter():
    data = bytes.fromhex("0011223344556677")
    wire = wire_bits(0x100, data)
    crc_errors = [receive(corrupt(wire, [p])) for p in range(20, 80)]
    crc_errors = [r for r in crc_errors if r.error == "crc"]
    assert crc_errors and all(r.at == len(wire) - 8 for r in crc_errors)


# --------------------------------------------------------------------------- fault confinement


def test_error_counters_follow_the_can_rules():
    c = ErrorCounters()
    states = [c.tx_error() for _ in range(32)]  # rule 3: +8 per destroyed own frame
    assert states[15] == ErrorState.ERROR_PASSIVE and c.passive_count == 1  # TEC = 128
    assert all(s is None for s in states[:15] + states[16:31])
    assert states[31] == ErrorState.BUS_OFF and c.tec == 256  # TEC > 255
    assert c.tx_ok() is None and c.state == ErrorState.BUS_OFF  # only recovery leaves bus-off
    assert c.recover() == ErrorState.ERROR_ACTIVE and (c.tec, c.rec) == (0, 0)

    c = ErrorCounters()
    for _ in range(16):
        c.tx_error()
    assert c.state == ErrorState.ERROR_PASSIVE
    assert c.tx_ok() == ErrorState.ERROR_ACTIVE and c.tec == 127  # -1 per successful transmission
    r = ErrorCounters()
    states = [r.rx_error() for _ in range(130)]  # rule 1: +1 per detected error as a receiver
    assert states[127] == ErrorState.ERROR_PASSIVE and r.rec == 130 and r.state == ErrorState.ERROR_PASSIVE
    assert r.rx_ok() == ErrorState.ERROR_ACTIVE and r.rec == 127  # REC > 127 goes back to 127 (119..127 allowed)
    assert r.rx_ok() is None and r.rec == 126


def test_a_sender_whose_frames_are_all_destroyed_goes_bus_off_after_32_tries_and_recovers_on_time():
    kernel, bus, errors, events = make_bus()
    a = bus.attach("A")
    rx: list = []
    bus.attach("B", lambda fid, data, t: rx.append((fid, t)))
    errors.error_flags.append(FrameSelection(np.random.default_rng(2), frame_ids=frozenset({0x100}), count=32))
    kernel.at(0, lambda _: bus.send(a, 0x100, bytes(8)))
    kernel.run(200_000_000)
    bus.finish(kernel.now)  # an idle bus: the recovery is found when someone looks (its time is exact)
    assert errors.stats["error_frames"] == 32 and errors.stats["retransmissions"] == 31
    assert rx == [] and a.dropped == 1 and not a.bus_off  # the 32nd try is lost with the bus-off
    c_a, c_b = errors.counters[a], errors.counters[bus.nodes[1]]
    assert (c_a.passive_count, c_a.bus_off_count, c_a.tec_max) == (1, 1, 256)
    assert c_b.rec_max == 32 and c_b.state == ErrorState.ERROR_ACTIVE
    off = [t for t, _, text in events if "bus-off (TEC" in text]
    back = [t for t, _, text in events if "recovered from bus-off" in text]
    assert len(off) == len(back) == 1
    # on an idle bus the recovery is 128 x 11 recessive bits, counted from the error delimiter
    assert back[0] - off[0] == 128 * 11 * BIT_NS - 11 * BIT_NS
    # recovered: the next frame goes through at once
    kernel.at(kernel.now, lambda _: bus.send(a, 0x100, bytes(8)))
    kernel.run(kernel.now + 1_000_000)
    assert len(rx) == 1 and errors.counters[a].tec == 0


def test_bus_off_recovery_on_a_busy_bus_counts_one_sequence_per_frame():
    """Back-to-back frames leave exactly 11 recessive bits between them: recovery takes 128 of them."""
    kernel, bus, errors, events = make_bus()
    a, b = bus.attach("A"), bus.attach("B")
    errors.error_flags.append(FrameSelection(np.random.default_rng(2), frame_ids=frozenset({0x100}), count=32))
    data = bytes(8)
    kernel.at(0, lambda _: bus.send(a, 0x100, data))
    sent_after: list[int] = []

    def flood(_):  # B keeps the bus busy from just before A goes bus-off
        if len(sent_after) < 300:
            sent_after.append(kernel.now)
            bus.send(b, 0x200, data)
            kernel.at(kernel.now + frame_bits(0x200, data) * BIT_NS, flood)

    kernel.at(0, lambda _: kernel.at(bus.busy_until, flood))
    kernel.run(500_000_000)
    off = next(t for t, _, text in events if "bus-off (TEC" in text)
    back = next(t for t, _, text in events if "recovered from bus-off" in text)
    frames_between = sum(1 for t, fid, *_ in bus.log.frames.array if fid == 0x200 and off < t * 1e9 <= back)
    assert frames_between in (127, 128)  # the 128th sequence completes within the recessive tail of a frame
    assert back - off > 100 * frame_bits(0x200, data) * BIT_NS


def test_corrupted_frames_are_rejected_counted_and_retransmitted():
    kernel, bus, errors, events = make_bus()
    senders = [bus.attach(f"S{i}") for i in range(3)]
    rx: list = []
    bus.attach("R", lambda fid, data, t: rx.append((fid, data)))
    errors.corruptions.append(Corruption(np.random.default_rng(5), probability=0.08, bits=2))
    sent = []

    def tick(_):
        for i, s in enumerate(senders):
            payload = bytes([len(sent) & 0xFF, i]) + bytes(6)
            sent.append((0x100 + i, payload))
            bus.send(s, 0x100 + i, payload)
        if len(sent) < 3000:
            kernel.at(kernel.now + 1_000_000, tick)

    kernel.at(0, tick)
    kernel.run(2_000_000_000)
    st = errors.stats
    assert st["corrupted"] > 150  # (at 8 %: TEC drifts down, +8 x 0.08 < 1 x 0.92, so no sender goes bus-off)
    assert st["corrupted"] == st["rejected"] + st["undetected"] and st["undetected"] == 0
    assert st["error_frames"] == st["rejected"] == st["retransmissions"]
    assert sorted(rx) == sorted(sent)  # every frame arrives once, intact, after its retransmissions
    assert errors.counters[bus.nodes[-1]].rec_max >= 1
    assert sum(errors.by_error.values()) == st["error_frames"] and set(errors.by_error) <= {"stuff", "form", "crc"}
    assert any("error frame:" in text for _, _, text in events)
    # a destroyed frame's latency includes its retries, and the bus time of the error frames counts in the load
    bus.finish(kernel.now)
    busy = np.sum(bus.log.load.array[:, 1]) * 0.1
    clean = sum(frame_bits(fid, data) for fid, data in sent) * BIT_NS * 1e-9
    assert busy > clean


def test_destroyed_frame_holds_the_bus_until_its_error_frame_ends():
    kernel, bus, errors, _ = make_bus()
    a = bus.attach("A")
    ends: list[int] = []
    bus.attach("B", lambda fid, data, t: ends.append(t))
    errors.corruptions.append(Corruption(np.random.default_rng(0), count=1, bits=1))
    kernel.at(0, lambda _: bus.send(a, 0x0C0, bytes(8)))
    kernel.run(10_000_000)
    first = bus.log.frames.array  # only the successful retransmission is logged as a frame
    assert len(first) == 1 and len(ends) == 1
    failed_bits = ends[0] // BIT_NS - frame_bits(0x0C0, bytes(8))
    assert ERROR_TAIL_BITS + 2 <= failed_bits <= frame_bits(0x0C0, bytes(8)) + ERROR_TAIL_BITS


# --------------------------------------------------------------------------- babbling idiot


def test_babbling_node_starves_every_lower_id_and_the_wcrt_analysis_says_so():
    kernel, bus, errors, _ = make_bus()
    ecu = bus.attach("ECU")
    rx: list = []
    bus.attach("Plant", lambda fid, data, t: rx.append((fid, t)))

    def cyclic(_):
        bus.send(ecu, 0x080, bytes(5))
        kernel.at(kernel.now + 10_000_000, cyclic)

    kernel.at(0, cyclic)
    holder = {}
    kernel.at(50_000_000, lambda _: holder.setdefault("b", errors.start_babbler(0x000, bytes(8), kernel.now)))
    kernel.at(250_000_000, lambda _: errors.stop_babbler(holder["b"]))
    kernel.run(400_000_000)
    cmd_times = [t for fid, t in rx if fid == 0x080]
    during = [t for t in cmd_times if 50e6 < t < 250e6]
    assert during == []  # starved for the whole babble
    assert len([t for t in cmd_times if t > 250e6]) >= 14  # and back afterwards
    babble_frame = frame_bits(0x000, bytes(8)) * BIT_NS
    loads = bus.log.load.array
    assert np.all(loads[(loads[:, 0] > 0.15) & (loads[:, 0] <= 0.25), 1] > 0.999)
    assert errors.stats["babbled"] >= 200e6 // babble_frame - 1
    # the analysis: a message with the babbler's ID whose period is its own frame time leaves no bound for the rest
    msgs = [CanMessage("Babble", 0x000, babble_frame * 1e-9, 8), CanMessage("TractionCmd_U01", 0x080, 0.01, 5)]
    res = response_times(msgs, 500_000)
    assert res["TractionCmd_U01"].r_s == float("inf") and not res["TractionCmd_U01"].schedulable
    assert response_times(msgs[1:], 500_000)["TractionCmd_U01"].schedulable


def test_frame_drop_removes_frames_from_the_sender_queue_and_counts_them():
    kernel, bus, errors, _ = make_bus()
    a = bus.attach("A")
    rx: list = []
    bus.attach("B", lambda fid, data, t: rx.append(fid))
    errors.drops.append(FrameSelection(np.random.default_rng(0), frame_ids=frozenset({0x101}), count=5))
    for k in range(10):
        kernel.at(k * 1_000_000, lambda _: (bus.send(a, 0x100, b"\x00"), bus.send(a, 0x101, b"\x00")))
    kernel.run(20_000_000)
    bus.finish(kernel.now)
    assert rx.count(0x100) == 10 and rx.count(0x101) == 5
    assert bus.log.frames_dropped == 5 == errors.stats["dropped_by_fault"]


@pytest.mark.parametrize("bits", [1, 3])
def test_corruption_bits_are_reproducible_for_a_seed(bits):
    def run():
        kernel, bus, errors, _ = make_bus()
        a = bus.attach("A")
        bus.attach("B", lambda *a: None)
        errors.corruptions.append(Corruption(np.random.default_rng(9), probability=0.5, bits=bits))
        for k in range(50):
            kernel.at(k * 500_000, lambda _: bus.send(a, 0x0C3, bytes(8)))
        kernel.run(100_000_000)
        return dict(errors.by_error), kernel.now, bus.log.frames.array.copy()

    r1, r2 = run(), run()
    assert r1[0] == r2[0] and np.array_equal(r1[2], r2[2])
