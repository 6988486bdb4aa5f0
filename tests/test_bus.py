"""The CAN bus model: arbitration, queue policies, timing, filters, load and drops."""
from __future__ import annotations

import pytest

from tests.oracle.python_bus import VirtualCanBus
from hil.can.frame import frame_bits
from hil.runtime.kernel import Kernel

BIT_NS = 2000  # 500 kbit/s


def make_bus(policy: str = "priority", depth: int = 64) -> tuple[Kernel, VirtualCanBus, list]:
    kernel = Kernel()
    bus = VirtualCanBus(kernel, "bus1", 500_000, policy, depth)
    received: list[tuple[str, int, int]] = []
    return kernel, bus, received


def listener(name: str, received: list):
    return lambda fid, data, t: received.append((name, fid, t))


def test_lowest_id_wins_and_frames_follow_back_to_back():
    kernel, bus, rx = make_bus()
    a, b, c = (bus.attach(n) for n in "abc")
    bus.attach("sniffer", listener("sniffer", rx))
    data = bytes(8)
    kernel.at(0, lambda _: (bus.send(a, 0x300, data), bus.send(b, 0x100, data), bus.send(c, 0x200, data)))
    kernel.run(10_000_000)
    assert [fid for _, fid, _ in rx] == [0x100, 0x200, 0x300]
    t1 = frame_bits(0x100, data) * BIT_NS
    t2 = t1 + frame_bits(0x200, data) * BIT_NS
    t3 = t2 + frame_bits(0x300, data) * BIT_NS
    assert [t for _, _, t in rx] == [t1, t2, t3]


def test_fifo_queue_shows_priority_inversion():
    """Node A queues 0x300 then 0x050. Under FIFO its 0x050 waits behind 0x300 and loses to B's 0x100."""
    orders = {}
    for policy in ("priority", "fifo"):
        kernel, bus, rx = make_bus(policy)
        a, b = bus.attach("a"), bus.attach("b")
        bus.attach("sniffer", listener("s", rx))
        kernel.at(0, lambda _: (bus.send(a, 0x300, b"\x01"), bus.send(a, 0x050, b"\x02"), bus.send(b, 0x100, b"\x03")))
        kernel.run(10_000_000)
        orders[policy] = [fid for _, fid, _ in rx]
    assert orders["priority"] == [0x050, 0x100, 0x300]
    assert orders["fifo"] == [0x100, 0x300, 0x050]


def test_frame_queued_while_busy_waits_and_latency_is_logged():
    kernel, bus, rx = make_bus()
    a, b = bus.attach("a"), bus.attach("b")
    bus.attach("sniffer", listener("s", rx))
    kernel.at(0, lambda _: bus.send(a, 0x400, bytes(8)))
    kernel.at(10_000, lambda _: bus.send(b, 0x001, bytes(8)))  # arrives mid-frame: must wait
    kernel.run(10_000_000)
    first_end = frame_bits(0x400, bytes(8)) * BIT_NS
    second_end = first_end + frame_bits(0x001, bytes(8)) * BIT_NS
    assert [t for _, _, t in rx] == [first_end, second_end]
    frames = bus.log.frames.array
    assert frames[1, 1] == 0x001
    assert frames[1, 2] == pytest.approx((second_end - 10_000) * 1e-9)  # latency: queued -> end of transmission
    assert frames[1, 3] == pytest.approx((first_end - 10_000) * 1e-9)  # queueing part


def test_same_instant_as_bus_idle_still_competes():
    """A frame queued at exactly the end of a transmission joins the next arbitration."""
    kernel, bus, rx = make_bus()
    a, b, c = bus.attach("a"), bus.attach("b"), bus.attach("c")
    bus.attach("sniffer", listener("s", rx))
    end = frame_bits(0x010, bytes(1)) * BIT_NS
    kernel.at(0, lambda _: (bus.send(a, 0x010, bytes(1)), bus.send(b, 0x500, bytes(1))))
    kernel.at(end, lambda _: bus.send(c, 0x020, bytes(1)))  # scheduled before the end event exists
    kernel.run(10_000_000)
    assert [fid for _, fid, _ in rx] == [0x010, 0x020, 0x500]


def test_acceptance_filters_and_own_frames():
    kernel, bus, rx = make_bus()
    a = bus.attach("a", listener("a", rx), rx_ids={0x100, 0x200})
    bus.attach("b", listener("b", rx), rx_ids={0x300})
    c = bus.attach("c", listener("c", rx), receive_own=True)
    kernel.at(0, lambda _: (bus.send(a, 0x100, b""), bus.send(c, 0x300, b"")))
    kernel.run(1_000_000)
    got = sorted((name, fid) for name, fid, _ in rx)
    # a does not hear its own 0x100; b only 0x300; c (no filter, receive_own) hears both
    assert got == [("b", 0x300), ("c", 0x100), ("c", 0x300)]


def test_queue_overflow_drops_and_counts():
    kernel, bus, _ = make_bus(depth=2)
    a = bus.attach("a")
    results = []
    kernel.at(0, lambda _: results.extend(bus.send(a, 0x100 + k, bytes(8)) for k in range(5)))
    kernel.run(10_000_000)
    bus.finish(kernel.now)
    # The first frame starts at once only after the same-instant arbitration, so the queue holds 2 at send time.
    assert results == [True, True, False, False, False]
    assert bus.log.frames_dropped == 3
    assert bus.log.frames_sent == 2


def test_bus_load_per_window():
    kernel, bus, _ = make_bus()
    a = bus.attach("a")
    data = bytes(8)
    kernel.every(0, 1_000_000, lambda t: bus.send(a, 0x123, data))  # one frame per ms
    kernel.run(300_000_000)
    bus.finish(kernel.now)
    load = bus.log.load.array
    assert len(load) == 3
    expected = 100 * frame_bits(0x123, data) * BIT_NS / 100_000_000  # 100 frames per 100 ms window
    assert load[:, 1] == pytest.approx([expected] * 3)


def test_bad_policy_and_bitrate_are_rejected():
    with pytest.raises(ValueError, match="queue policy"):
        VirtualCanBus(Kernel(), "x", 500_000, "lifo")
    with pytest.raises(ValueError, match="bitrate"):
        VirtualCanBus(Kernel(), "x", 300_000)
