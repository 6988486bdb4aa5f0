"""Lazy readers on the engine's bus server (issue 25): a node that says when it reads gets, at each read time,
exactly the frames that ended by then and a SYNC, while an eager python-can node on the same bus still gets every
frame at its end."""
from __future__ import annotations

import time

import can
import numpy as np
import pytest
import trainhil_engine as engine

from hil.can.bus_log import BusLog
from hil.can.frame import frame_bits
from hil.runtime.realtime.native_server import NativeBusServer
from hil.runtime.realtime.protocol import TURN_HOLD_MAX_S
from hil.runtime.realtime.pycan_bus import TrainhilBus

BITRATE = 125_000  # 8 µs bits: a frame of 8 bytes lasts about 1 ms
PERIOD_S = 0.02
LOADED_ATTEMPTS = 5  # tries of a wall-clock scene whose node the scheduler may wake too late


@pytest.fixture
def server(rt):
    with NativeBusServer("lz", "bus1", BITRATE, log=BusLog("bus1", BITRATE)) as srv:
        yield srv


def lazy_link(name: str) -> tuple[TrainhilBus, engine.FrameLink]:
    bus = TrainhilBus("lz/bus1", node_name=name, lazy_reader=True)
    return bus, engine.FrameLink(bus.fileno(), 0.0, 1.0, keep=True, lazy=True)


def test_a_lazy_reader_gets_exactly_the_frames_that_ended_by_each_read_time(server):
    sender = TrainhilBus("lz/bus1", node_name="S")
    reader_bus, reader = lazy_link("R")
    eager = TrainhilBus("lz/bus1", node_name="E")
    first = time.time() + 0.05
    reader.read_every(first, PERIOD_S)
    try:
        sent_at = []
        for k in range(6):  # one frame every half period: half of them end after a read time they precede
            time.sleep(max(0.0, first + k * PERIOD_S / 2 - 0.004 - time.time()))
            sent_at.append(time.time())  # before the send: the frame cannot end sooner than one frame after it
            sender.send(can.Message(arbitration_id=0x100 + k, data=bytes(8), is_extended_id=False))
        seen: list[tuple[int, float, float]] = []
        for j in range(4):
            t_read = first + j * PERIOD_S
            assert reader.sync_to(t_read, 1.0), f"no SYNC of read time {j}"
            assert abs(reader.synced - t_read) < 2e-6
            got = reader.take()
            assert all(stamp <= t_read + 1e-6 for _, _, stamp in got), (j, got)  # nothing from after the read time
            seen += [(fid, stamp, t_read) for fid, _, stamp in got]
        ids = [fid for fid, _, _ in seen]
        assert ids == sorted(ids) == [0x100 + k for k in range(len(ids))]  # in order, none twice, none skipped
        assert len(ids) == 6
        # each frame at the first read time after its end (not a read later)
        for fid, stamp, t_read in seen:
            assert t_read - PERIOD_S < stamp <= t_read + 1e-6, (hex(fid), stamp - t_read)
        # an eager node on the same bus still hears every frame, each within milliseconds of its end
        heard = []
        while (m := eager.recv(0.2)) is not None:
            heard.append((m.arbitration_id, m.timestamp))
        assert [fid for fid, _ in heard] == ids
        assert [round(ts, 6) for _, ts in heard] == [round(stamp, 6) for _, stamp, _ in seen]
        bits = frame_bits(0x100, bytes(8))
        for (fid, stamp), t_sent in zip(heard, sent_at):
            assert stamp - t_sent >= bits / BITRATE - 1e-4  # not before it could have ended
    finally:
        for b in (sender, reader_bus, eager):
            b.shutdown()


def test_a_read_time_nobody_foresaw_is_asked_for_once(server):
    sender = TrainhilBus("lz/bus1", node_name="S")
    reader_bus, reader = lazy_link("R")
    try:
        sender.send(can.Message(arbitration_id=0x123, data=bytes(8), is_extended_id=False))
        time.sleep(0.01)
        t_read = time.time() + 0.01
        assert not reader.sync_to(t_read, 0.05)  # no read time was given: no SYNC comes
        reader.read_every(t_read, 0.0)
        assert reader.sync_to(t_read, 1.0)
        assert [fid for fid, _, _ in reader.take()] == [0x123]
    finally:
        sender.shutdown()
        reader_bus.shutdown()


def test_a_node_on_several_buses_waits_for_each_buss_sync_and_a_second_event_there_waits_for_nothing(rt):
    """Units of two trains due at one instant nobody foresaw, in one ECU host: the first event asks both buses
    (``LinkGroup.begin_wait``) and sleeps until both SYNCs came; then each bus's frame that ended by that instant is
    handed over with its bus; a second event at the same instant finds both synced and waits for nothing."""
    from hil.runtime.realtime.frame_io import EngineFrames
    from hil.runtime.realtime.pacing import SimClock

    with NativeBusServer("lz", "bus1", BITRATE, log=BusLog("bus1", BITRATE)), \
            NativeBusServer("lz", "bus2", BITRATE, log=BusLog("bus2", BITRATE)):
        senders = [TrainhilBus(f"lz/bus{i}", node_name=f"S{i}") for i in (1, 2)]
        readers = [TrainhilBus(f"lz/bus{i}", node_name=f"R{i}", lazy_reader=True) for i in (1, 2)]
        frames = EngineFrames(SimClock(time.time(), 1.0), readers, extended=False, lazy=True)
        try:
            for i, sender in enumerate(senders):
                sender.send(can.Message(arbitration_id=0x100 + i, data=bytes(8), is_extended_id=False))
            sim_t = frames.clock.now() + 0.01  # both frames end by then (about 1 ms each)
            got: list[tuple[int, int, float]] = []
            frames.wait(sim_t, lambda bus, fid, data, t: got.append((bus, fid, t)), stop=False)
            t = frames.clock.t0 + sim_t
            assert [link.synced for link in frames.links] == [pytest.approx(t, abs=2e-6)] * 2
            # handed over in bus-time order; the two servers end their frames independently, so either may be first
            assert sorted((bus, fid) for bus, fid, _ in got) == [(0, 0x100), (1, 0x101)]
            assert all(stamp <= sim_t for _, _, stamp in got)
            assert [stamp for _, _, stamp in got] == sorted(stamp for _, _, stamp in got)
            t_second = time.perf_counter()
            assert frames.group.begin_wait(sim_t) == []  # synced already: nothing asked, nothing to wait for
            assert frames.group.finish(sim_t) == []
            assert time.perf_counter() - t_second < 0.005
        finally:
            for b in senders + readers:
                b.shutdown()


def test_a_wait_at_a_read_time_one_bus_foresaw_waits_for_that_bus_only(rt):
    """Read times given on bus 1 only (a unit of train 1 in a host of two trains): a wait at one of them waits for
    bus 1's SYNC and does not ask bus 2, which gives nothing then."""
    from hil.runtime.realtime.frame_io import EngineFrames
    from hil.runtime.realtime.pacing import SimClock

    with NativeBusServer("lz", "bus1", BITRATE, log=BusLog("bus1", BITRATE)), \
            NativeBusServer("lz", "bus2", BITRATE, log=BusLog("bus2", BITRATE)):
        readers = [TrainhilBus(f"lz/bus{i}", node_name=f"R{i}", lazy_reader=True) for i in (1, 2)]
        frames = EngineFrames(SimClock(time.time(), 1.0), readers, extended=False, lazy=True)
        try:
            first = frames.clock.now() + 0.02
            frames.read_every(first, PERIOD_S, [0])
            assert frames.group.begin_wait(first - 0.005) == [0, 1]  # not a read time: both asked
            frames.group.finish(first - 0.005)
            frames.wait(first + PERIOD_S, None, stop=False)
            assert frames.links[0].synced == pytest.approx(frames.clock.t0 + first + PERIOD_S, abs=2e-6)
            assert frames.links[1].synced < frames.clock.t0 + first  # never asked for that read time
        finally:
            for b in readers:
                b.shutdown()


def quiet_link(name: str) -> tuple[TrainhilBus, engine.FrameLink]:
    bus = TrainhilBus("lz/bus1", node_name=name, lazy_reader=True, quiet=True)
    assert bus.bell_fileno() is not None  # the engine's server has a bell
    return bus, engine.FrameLink(bus.fileno(), 0.0, 1.0, keep=True, lazy=True, bell=bus.bell_fileno())


def test_a_quiet_nodes_frames_do_not_wake_the_server_and_end_as_if_they_had(server):
    """The server reads a quiet node's frames at its next wake-up (here a reader's SYNC), queued at the instants
    they carry, so the reader gets them with the ends they would have had; the sends woke the server at most at
    its load windows, not once each."""
    quiet_bus, quiet = quiet_link("Q")
    reader_bus, reader = lazy_link("R")
    try:
        t0 = time.time() + 0.02
        quiet.read_every(t0, 0.0)
        assert quiet.sync_to(t0, 1.0)  # the node has read the server's BELL record: nothing to ring for
        time.sleep(0.01)
        before = server.stats.wake_ups
        sent_at = []
        for k in range(8):
            sent_at.append(time.time())
            quiet.send([(0x100 + k, bytes(8))])
            time.sleep(0.002)
        woke = server.stats.wake_ups - before
        assert woke <= 2, f"{woke} wake-ups for 8 quiet sends (load windows only: at most 2 in 16 ms)"
        t_read = time.time() + 0.01
        reader.read_every(t_read, 0.0)
        assert reader.sync_to(t_read, 1.0)
        got = reader.take()
        assert [fid for fid, _, _ in got] == [0x100 + k for k in range(8)]
        one_frame = frame_bits(0x100, bytes(8)) / BITRATE  # about 1 ms: each ends before the next is sent
        for (_, _, stamp), t_sent in zip(got, sent_at):
            # from its own instant (the server's epoch clock is the monotonic one: 0.1 ms for the two clocks' drift)
            assert -1e-4 <= stamp - (t_sent + one_frame) < 3e-4, stamp - t_sent
    finally:
        quiet_bus.shutdown()
        reader_bus.shutdown()


def test_an_eager_node_on_the_bus_makes_quiet_nodes_ring_for_every_frame(server):
    """An eager node takes frames as they end, so quiet nodes are told to ring for every frame: the eager node
    hears a quiet node's frame at its end, not at the server's next wake-up."""
    quiet_bus, quiet = quiet_link("Q")
    eager = TrainhilBus("lz/bus1", node_name="E")
    try:
        t0 = time.time() + 0.02
        quiet.read_every(t0, 0.0)
        assert quiet.sync_to(t0, 1.0)  # takes in the BELL record sent when the eager node joined
        quiet.send([(0x123, bytes(8))])
        msg = eager.recv(1.0)
        assert msg is not None and msg.arbitration_id == 0x123
        assert time.time() - msg.timestamp < 0.02  # at its end, not at the server's next load window (0.1 s)
    finally:
        quiet_bus.shutdown()
        eager.shutdown()


def test_each_ecu_a_process_hosts_sends_from_its_own_tx_queue(rt):
    """Frames sent as two senders of one connection wait in two TX queues, as two controllers' frames would: on a
    FIFO bus the second sender's frame goes before the first sender's queued one."""
    with NativeBusServer("lzf", "bus1", BITRATE, policy="fifo", log=BusLog("bus1", BITRATE)):
        host_bus = TrainhilBus("lzf/bus1", node_name="H")
        host = engine.FrameLink(host_bus.fileno(), 0.0, 1.0)
        listener = TrainhilBus("lzf/bus1", node_name="L")
        try:
            host.send([(0x400, bytes(8))])  # on the wire for about 1 ms
            time.sleep(0.0003)
            host.send([(0x300, bytes(8))], sender=0)
            host.send([(0x100, bytes(8))], sender=1)
            order = [m.arbitration_id for m in iter(lambda: listener.recv(0.5), None)]
            assert order == [0x400, 0x100, 0x300]
            with pytest.raises(ValueError, match="sender 64"):
                host.send([(0x100, bytes(8))], sender=64)
            for sender, name in ((1, ""), (1, "E" * 21), (64, "ECU_U02")):  # names: 1 to 20 bytes, senders 0..63
                with pytest.raises(ValueError, match="sender"):
                    host.name_sender(sender, name)
        finally:
            host_bus.shutdown()
            listener.shutdown()


def test_a_reader_synced_before_its_read_time_acts_at_it(rt):
    """While a frame is on the wire no other can end, so the server syncs a read time before that frame's end at
    once, milliseconds early here (a slow bus); the reader acts then, as at its read time (``act_at``): the frame
    it sends is queued at the read time exactly, not at the instant it was written, and waits for the wire. The
    first frame must be on the wire by the read time: where the host held the test past it (the sync then comes
    late, as it should), the exchange is tried again, up to three times."""
    bitrate = 20_000  # 50 µs bits: an 8-byte frame lasts about 5.5 ms
    with NativeBusServer("lze", "bus1", bitrate, log=BusLog("bus1", bitrate)) as srv:
        for _ in range(3):
            t_read, synced_at, rows = _sync_early_once(srv)
            if synced_at < t_read - 0.001:
                break
        assert synced_at < t_read - 0.001, f"synced {t_read - synced_at:.4f} s before the read time, three times"
    (end1, id1, _, _), (end2, id2, latency2, queueing2) = rows
    assert (int(id1), int(id2)) == (0x100, 0x200)
    queued_at = srv.epoch0 + end2 - latency2  # the frame's enqueue instant, in epoch seconds
    assert abs(queued_at - t_read) < 2e-6, queued_at - t_read
    assert abs(queueing2 - (end1 + srv.epoch0 - t_read)) < 2e-6  # it waited for the wire, from the read time


def _sync_early_once(srv: NativeBusServer) -> tuple[float, float, np.ndarray]:
    """A sender puts a frame on the wire 4 ms before a reader's read time; the reader syncs, acts at its read time
    and sends. (The read time, when the sync returned, this exchange's two frame rows: those that ended after the
    first was sent, since a frame of a try before may end after this one began.)"""
    sender_bus = TrainhilBus("lze/bus1", node_name="S", lazy_reader=True)
    reader_bus = TrainhilBus("lze/bus1", node_name="R", lazy_reader=True)
    sender = engine.FrameLink(sender_bus.fileno(), 0.0, 1.0, keep=True, lazy=True)
    reader = engine.FrameLink(reader_bus.fileno(), 0.0, 1.0, keep=True, lazy=True)
    try:
        t_read = time.time() + 0.03
        reader.read_every(t_read, 0.0)
        time.sleep(max(0.0, t_read - 0.004 - time.time()))
        sender.send([(0x100, bytes(8))])  # on the wire from about 4 ms before the read time to 1.5 ms after
        assert reader.sync_to(t_read, 1.0)
        synced_at = time.time()
        reader.act_at(t_read)
        reader.send([(0x200, bytes(1))])
        reader.read_every(t_read + 0.015, 0.0)  # both frames have ended by then: the server has run the bus
        assert reader.sync_to(t_read + 0.015, 1.0)
        rows = srv.with_log(lambda log: log.frames.rows_from(0).copy())
    finally:
        sender_bus.shutdown()
        reader_bus.shutdown()
    return t_read, synced_at, rows[rows[:, 0] + srv.epoch0 > t_read - 0.004]


@pytest.mark.parametrize("turns", [True, False])
def test_a_turns_frame_sent_late_goes_on_the_bus_at_its_read_time_and_a_later_reader_has_it(server, turns):
    """A node whose read times are turns (``read_every(..., turns=True)``) takes a millisecond of work after its SYNC,
    past another reader's read time. Its frame still goes on the bus at its own read time and that reader gets it,
    since the bus waits for the turn's end (``send(..., end_turn=True)``). Without turns the frame goes when sent,
    after the reader's read time.

    The node's work must end within the turn's hold (TURN_HOLD_MAX_S after its read time). On a loaded machine the
    node's SYNC can reach it later than that, and the turn be let go as it should; the scene is then tried again
    (``_late_turn_scene``)."""
    for attempt in range(LOADED_ATTEMPTS):
        before = (server.stats.turns_held, server.stats.turn_overruns)
        got, t_turn, work_ended = _late_turn_scene(server, turns, attempt)
        held, overruns = server.stats.turns_held - before[0], server.stats.turn_overruns - before[1]
        if turns and work_ended > t_turn + TURN_HOLD_MAX_S:  # the node itself was late: its turn may have gone
            continue  # (or been held, had the serving thread been late too and found the turn's end first)
        if turns:
            assert [fid for fid, _, _ in got] == [0x100], f"work ended {1e3 * (work_ended - t_turn):.3f} ms after the turn"
            assert abs(got[0][2] - (t_turn + frame_bits(0x100, bytes(1)) / BITRATE)) < 2e-6, got[0][2] - t_turn
            # held once, unless the serving thread itself woke after the turn's end (a loaded machine): then it
            # never had to wait (as the engine's own test of it allows)
            assert held <= 1 and overruns == 0
        else:
            assert got == []  # sent after the read time: the reader's next read has it
            assert held == 0
        return
    pytest.skip(f"the node's work overran the turn's hold in {LOADED_ATTEMPTS} attempts: the machine is too loaded")


def _late_turn_scene(server, turns: bool, attempt: int) -> tuple[list, float, float]:
    """One try: (what the reader got at its read time, the node's turn, when the node's send returned)."""
    node_bus, node = lazy_link(f"N{attempt}")
    reader_bus, reader = lazy_link(f"R{attempt}")
    try:
        t_turn = time.time() + 0.03
        one_frame = frame_bits(0x100, bytes(1)) / BITRATE  # about 0.45 ms
        t_read = t_turn + one_frame + 0.0002  # after the frame's end at the turn, before the node sends it
        node.read_every(t_turn, 0.0, turns)
        reader.read_every(t_read, 0.0)
        assert node.sync_to(t_turn, 1.0)
        node.act_at(t_turn)
        assert node.in_turn is turns
        time.sleep(max(0.0, t_turn + 0.001 - time.time()))  # the node's work: a millisecond past its read time
        node.send([(0x100, bytes(1))], end_turn=True)
        work_ended = time.time()
        assert not node.in_turn
        assert reader.sync_to(t_read, 1.0)
        return reader.take(), t_turn, work_ended
    finally:
        node_bus.shutdown()
        reader_bus.shutdown()


def test_faster_than_real_time_a_wait_between_read_times_is_asked_for_and_synced(rt):
    """At pace 10 the node's read schedule is in simulated time (the server is told the wall period): a wait at an
    instant between two read times is not foreseen, so it is asked for once and its own SYNC comes (with the wall
    period in the schedule, it was taken for a read time and waited for the next one's SYNC)."""
    pace = 10.0
    with NativeBusServer("lzp", "bus1", BITRATE, log=BusLog("bus1", BITRATE), pace=pace):
        bus = TrainhilBus("lzp/bus1", node_name="P", lazy_reader=True)
        try:
            t0 = time.time() + 0.05  # the epoch second of simulated 0
            link = engine.FrameLink(bus.fileno(), t0, pace, keep=True, lazy=True)
            group = engine.LinkGroup([link])
            group.read_every(0, 0.0, 0.1)  # every 0.1 simulated s: 10 ms of wall time
            t = 0.35  # between the read times 0.3 and 0.4
            waiting = group.begin_wait(t)
            deadline = time.time() + 1.0
            while waiting and time.time() < deadline:
                waiting = group.wait_more(t, 0.1)
            assert waiting == [], "the SYNC of an instant between read times never came"
            assert abs(link.synced - (t0 + t / pace)) < 2e-6, "synced by the next read time's SYNC, not its own"
            group.finish(t)
        finally:
            bus.shutdown()


@pytest.mark.parametrize("for_good", [True, False])
def test_a_node_whose_turns_are_over_holds_its_bus_for_none_of_its_later_read_times(server, for_good):
    """A node that stays connected after its last turn (the rig's nodes linger at the end of a run) says its turns
    are over (``LinkGroup.end_turns_for_good``): its read times go on as plain reads, and none is held or let go.
    Without it, each later read time holds the bus TURN_HOLD_MAX_S and is let go, counted under the node's name."""
    bus = TrainhilBus("lz/bus1", node_name="N", lazy_reader=True)
    try:
        t0 = time.time() + 0.02  # the epoch second of simulated 0
        link = engine.FrameLink(bus.fileno(), t0, 1.0, keep=True, lazy=True)
        group = engine.LinkGroup([link])
        group.read_every(0, 0.0, 0.005, True)  # a turn every 5 ms
        waiting = group.begin_wait(0.0)
        deadline = time.time() + 1.0
        while waiting and time.time() < deadline:
            waiting = group.wait_more(0.0, 0.1)
        assert waiting == []
        group.finish(0.0)
        group.end_turn()  # its last turn
        if for_good:
            group.end_turns_for_good()
        time.sleep(0.03)  # lingers over six more read times
        stats = server.stats
    finally:
        bus.shutdown()
    if for_good:
        assert (stats.turn_overruns, stats.turns_let_go, stats.turns_behind) == (0, {}, 0)
    else:
        assert stats.turns_let_go.get("N", 0) >= 1, stats
        assert stats.turn_overruns == stats.turns_let_go["N"] + stats.turns_behind
