"""The real-time bus: run directories, wire protocol, the wall-clock bus server and the python-can plugin.

Timing assertions use the bus's own stamps (model times, exact) or orderings; wall-clock bounds are generous
so a loaded 2-core machine does not make them flaky. Slow bitrates (5 kbit/s: ~26 ms per 8-byte frame) make
"queued while the bus is busy" hold with a wide margin.
"""
from __future__ import annotations

import asyncio
import importlib.metadata
import json
import logging
import os
import signal
import socket
import stat
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from types import SimpleNamespace

import can
import pytest

from ecu_sim.codec import TrainDb
from tests.oracle.bus_model import CanBusModel, arbitration_key
from hil.can.frame import frame_bits
from hil.runtime.realtime import sockets, protocol
from hil.runtime.realtime.sockets import BusServerError
from tests.oracle.python_server import PythonBusServer as BusServer
from hil.runtime.realtime.pycan_bus import TrainhilBus

REPO = Path(__file__).resolve().parents[1]
SLOW = 5000  # bit/s: bit time 200 us
SLOW_BIT_NS = 200_000
DATA8 = bytes(range(1, 9))
ENTRY_POINT_INSTALLED = any(ep.name == "trainhil" for ep in importlib.metadata.entry_points(group="can.interface"))
NEEDS_ENTRY_POINT = pytest.mark.skipif(
    not ENTRY_POINT_INSTALLED,
    reason="the can.interface entry point 'trainhil' is not installed yet (add it to pyproject.toml and "
           "`pip install -e .`)")


@pytest.fixture
def server(rt, server_cls):
    with server_cls("r1", "bus1", SLOW) as srv:
        yield srv


def node(name: str, **kwargs) -> TrainhilBus:
    return TrainhilBus("r1/bus1", node_name=name, **kwargs)


def drain(bus: TrainhilBus, timeout: float = 0.3) -> list[can.Message]:
    out = []
    while (m := bus.recv(timeout)) is not None:
        out.append(m)
    return out


# ---------------------------------------------------------------- protocol

def test_frame_record_round_trips_and_is_24_bytes():
    for can_id, data, flags in [(0x7FF, b"", 0), (0x123, DATA8, 0), (0x1ABCDEF0 & 0x1FFFFFFF, b"\xff" * 3,
                                                                       protocol.FLAG_EXTENDED)]:
        rec = protocol.pack_frame(can_id, data, flags, 1712345678.123456)
        assert len(rec) == protocol.RECORD_SIZE == 24
        assert protocol.unpack_frame(rec) == (can_id, data, flags, 1712345678.123456, len(data))
    # layout fixed by the docstring: kind, flags, dlc, pad, id (LE u32), timestamp (LE f64), 8 data bytes
    rec = protocol.pack_frame(0x123, b"\xaa\xbb", 0, 0.0)
    assert rec[:8] == bytes([1, 0, 2, 0, 0x23, 0x01, 0, 0]) and rec[16:] == b"\xaa\xbb" + bytes(6)


def test_control_records_round_trip():
    hello = protocol.pack_hello("ECU_U01", receive_own=True)
    assert protocol.unpack_hello(hello) == ("ECU_U01", True, protocol.PROTOCOL_VERSION)
    assert protocol.unpack_welcome(protocol.pack_welcome(500_000, 1.5e9, 7)) == (500_000, 1.5e9, 7, 1, 0)
    fd_welcome = protocol.pack_welcome(1_000_000, 1.5e9, 7, fd_data_bitrate=8_000_000)
    assert protocol.unpack_welcome(fd_welcome).fd_data_bitrate == 8_000_000 and fd_welcome[20:] == (8_000_000).to_bytes(4, "little")
    filters = [protocol.Filter(0x100, 0x7FF, protocol.MATCH_STANDARD), protocol.Filter(0x18FF0000, 0x1FFF0000, 2)]
    raw = protocol.pack_filters(filters, generation=3)
    assert len(raw) == 3 * 24
    assert protocol.unpack_filters_head(raw) == (2, 3)
    assert [protocol.unpack_filter(raw, 24 * (i + 1)) for i in range(2)] == filters
    assert protocol.unpack_filters_ack(protocol.pack_filters_ack(3)) == 3


def test_protocol_rejects_bad_input_with_clear_errors():
    with pytest.raises(ValueError, match="0x800"):
        protocol.pack_frame(0x800, b"")
    with pytest.raises(ValueError, match="9 data bytes"):
        protocol.pack_frame(0x1, bytes(9))
    with pytest.raises(ValueError, match="node name"):
        protocol.pack_hello("x" * 21)
    with pytest.raises(protocol.ProtocolError, match="not a FRAME"):
        protocol.unpack_frame(protocol.pack_hello("a"))
    with pytest.raises(ValueError, match=r"can_filters\[1\]"):
        protocol.filter_from_python_can({"can_id": 1}, 1)
    assert "remote" in protocol.frame_error(0x10, 0, protocol.FLAG_REMOTE)
    assert protocol.frame_error(0x10, 8, 0) is None


def test_filter_semantics_match_python_can():
    """Cross-check against python-can's own software filter on a grid of ids, masks and formats."""
    cases = [None, [{"can_id": 0x100, "can_mask": 0x7FF}], [{"can_id": 0x100, "can_mask": 0x700}],
             [{"can_id": 0x100, "can_mask": 0x7FF, "extended": True}],
             [{"can_id": 0x100, "can_mask": 0, "extended": False}],
             [{"can_id": 0x200, "can_mask": 0x7F0}, {"can_id": 0x1234, "can_mask": 0x1FFFFFFF, "extended": True}]]
    for python_can_filters in cases:
        ours = tuple(protocol.filter_from_python_can(f) for f in python_can_filters or ())
        for can_id in (0x0, 0x100, 0x105, 0x1FF, 0x200, 0x20F, 0x210, 0x1234):
            for ext in (False, True):
                msg = can.Message(arbitration_id=can_id, is_extended_id=ext)
                expected = can.BusABC._matches_filters(SimpleNamespace(_filters=python_can_filters), msg)
                assert protocol.filters_accept(ours, can_id, ext) == expected, (python_can_filters, can_id, ext)


# ---------------------------------------------------------------- run directories

def test_runtime_root_and_run_dir_are_private(rt, monkeypatch):
    assert sockets.runtime_root() == rt / "trainhil"
    d = sockets.run_dir("seed000", create=True)
    assert d == rt / "trainhil" / "seed000"
    for p in (d, d.parent):
        st = os.lstat(p)
        assert stat.S_IMODE(st.st_mode) == 0o700 and st.st_uid == os.getuid()
    assert sockets.socket_path("seed000", "bus1") == d / "bus1.sock"
    monkeypatch.delenv("XDG_RUNTIME_DIR")
    assert sockets.runtime_root() == Path(tempfile.gettempdir()) / f"trainhil-{os.getuid()}"


def test_insecure_run_dirs_are_refused(rt):
    root = rt / "trainhil"
    root.mkdir()
    os.chmod(root, 0o777)
    with pytest.raises(sockets.InsecureRunDirError, match="group/others"):
        sockets.run_dir("seed000", create=True)
    os.chmod(root, 0o700)
    (root / "seed000").mkdir()
    os.chmod(root / "seed000", 0o755)
    with pytest.raises(sockets.InsecureRunDirError, match="0o755"):
        sockets.socket_path("seed000", "bus1")
    (root / "link").symlink_to(root / "seed000")
    with pytest.raises(sockets.InsecureRunDirError, match="symlink"):
        sockets.run_dir("link")


def test_names_and_channels_are_validated(rt):
    assert sockets.parse_channel("seed000/bus1") == ("seed000/bus1", rt / "trainhil" / "seed000" / "bus1.sock")
    assert sockets.parse_channel("/x/y/bus2.sock") == ("/x/y/bus2.sock", Path("/x/y/bus2.sock"))
    for bad in ("bus1", "a/b/c", "../bus1", "a/..", "a/b c", "/x/bus1", "a/", "/" + "x" * 120 + ".sock"):
        with pytest.raises(ValueError):
            sockets.parse_channel(bad)
    with pytest.raises(ValueError, match="run name"):
        sockets.run_dir("a..b")


# ---------------------------------------------------------------- model additions (tests/oracle/bus_model.py)

def test_model_extended_frames_arbitrate_by_wire_order_and_time_as_extended():
    m = CanBusModel("b", 500_000)
    n = m.attach("n")
    m.enqueue(n, 0x101 << 18, b"", 0, extended=True)  # base 0x101
    m.enqueue(n, 0x100 << 18, b"", 0, extended=True)  # base 0x100, extended: loses to standard 0x100
    m.enqueue(n, 0x100, b"", 0)
    order = []
    t = 0
    while (tx := m.arbitrate(t)) is not None:
        order.append((tx.frame_id, tx.extended, tx.t_end - tx.t_start))
        m.complete()
        t = tx.t_end
    assert order == [(0x100, False, frame_bits(0x100, b"") * 2000),
                     (0x100 << 18, True, frame_bits(0x100 << 18, b"", True) * 2000),
                     (0x101 << 18, True, frame_bits(0x101 << 18, b"", True) * 2000)]
    # wire order: base ID first, so an extended frame with base 0x0FF beats standard 0x100 whatever its extension
    ext_base_0ff = arbitration_key((0x0FF << 18) | 0x3FFFF, True)
    assert ext_base_0ff < arbitration_key(0x100, False) < arbitration_key(0x100 << 18, True)


def test_model_detach_drops_and_counts_queued_frames():
    for policy in ("priority", "fifo"):
        m = CanBusModel("b", 500_000, policy)
        a, b = m.attach("a"), m.attach("b")
        for k in range(3):
            m.enqueue(a, 0x100 + k, b"", 0)
        m.enqueue(b, 0x200, b"", 0)
        tx = m.arbitrate(0)  # a's 0x100 on the wire
        assert m.detach(a) == 2
        m.complete()
        assert m.arbitrate(tx.t_end).frame_id == 0x200
        m.finish(tx.t_end)
        assert m.log.frames_dropped == 2 and a not in m.nodes


# ---------------------------------------------------------------- the server with python-can nodes

def test_frame_reaches_the_other_node_not_the_sender_unless_it_asks(server):
    with node("a") as a, node("b") as b, node("c", receive_own_messages=True) as c:
        a.send(can.Message(arbitration_id=0x123, data=DATA8, is_extended_id=False))
        got = b.recv(2.0)
        assert (got.arbitration_id, bytes(got.data), got.is_rx, got.channel) == (0x123, DATA8, True, 0)  # bus1: index 0
        assert abs(got.timestamp - time.time()) < 5.0  # epoch seconds
        c.send(can.Message(arbitration_id=0x1ABCDE, data=b"\x01", is_extended_id=True))
        heard = [(m.arbitration_id, m.is_extended_id, m.is_rx) for m in (c.recv(2.0), c.recv(2.0))]
        assert heard == [(0x123, False, True), (0x1ABCDE, True, False)]  # a's frame, then its own echo
        assert [m.arbitration_id for m in drain(a)] == [0x1ABCDE]  # a: c's frame only, never its own
        assert [m.arbitration_id for m in drain(b)] == [0x1ABCDE]
    assert server.stats.frames == 2


def test_lower_id_wins_while_the_bus_is_busy_and_stamps_follow_exact_frame_durations(rt, server_cls):
    bit_ns = 1_000_000  # 1 kbit/s: the long frame is on the wire for ~130 ms
    with server_cls("r1", "bus1", 1000) as server, node("long") as long_, node("a") as a, node("b") as b, \
            node("rx") as rx:
        long_.send(can.Message(arbitration_id=0x400, data=DATA8, is_extended_id=False))
        deadline = time.monotonic() + 5
        while not server.transmitting and time.monotonic() < deadline:  # 0x400 alone won the idle bus
            time.sleep(0.001)
        a.send(can.Message(arbitration_id=0x300, data=DATA8, is_extended_id=False))
        b.send(can.Message(arbitration_id=0x100, data=b"\x55\xaa", is_extended_id=False))
        msgs = [rx.recv(2.0) for _ in range(3)]
    assert [m.arbitration_id for m in msgs] == [0x400, 0x100, 0x300]
    ts = [m.timestamp for m in msgs]
    assert ts[0] < ts[1] < ts[2]
    # back to back: each frame ends exactly its duration after the previous one (float epoch: within 1 us)
    assert ts[1] - ts[0] == pytest.approx(frame_bits(0x100, b"\x55\xaa") * bit_ns * 1e-9, abs=1e-6)
    assert ts[2] - ts[1] == pytest.approx(frame_bits(0x300, DATA8) * bit_ns * 1e-9, abs=1e-6)
    stats = server.stats
    assert stats.frames == 3 and stats.load > 0
    assert stats.latency_p99_s >= frame_bits(0x300, DATA8) * bit_ns * 1e-9  # 0x300 waited for two frames


@pytest.mark.parametrize("pace", [1.0, 4.0])
def test_load_windows_aligned_to_a_run_s_zero_end_at_whole_windows_of_it_and_hold_its_frames(rt, server_cls, pace):
    """The rig aligns each server's load windows to the run's t = 0 (its epoch ``t0``) before "go", so that a
    window reads the same span of the run as virtual time's: every window after t0 ends at t0 + k x the window,
    and the bus time of the frames sent after t0 is all in them."""
    window = 0.02
    with server_cls("r1", "bus1", 500_000, load_window_s=window, pace=pace) as server, node("tx") as tx:
        server.align_load_windows(server.epoch0 - 1.0)  # a t0 before the bus's zero (a clock set back): no error
        t0 = time.time() + 0.033  # a third of the way into a window of the server's own time, most likely
        server.align_load_windows(t0)
        time.sleep(max(0.0, t0 - time.time()) + 0.01)
        for i in range(3):
            tx.send(can.Message(arbitration_id=0x100 + i, data=DATA8, is_extended_id=False))
        time.sleep(8 * window / pace)
        origin = (t0 - server.epoch0) * pace  # the run's zero in the bus's model time
        rows = [(t, load) for t, load in server.with_log(lambda log: log.load.array.tolist()) if t > origin]
    assert len(rows) >= 5
    k = [(t - origin) / window for t, _ in rows]
    assert all(abs(x - round(x)) < 1e-4 for x in k), k  # the ends: t0 + whole windows
    busy = sum(load for _, load in rows) * window
    assert busy == pytest.approx(sum(frame_bits(0x100 + i, DATA8) for i in range(3)) * 2e-6)  # 2 us a bit


def test_server_applies_acceptance_filters(server):
    with node("f", can_filters=[{"can_id": 0x100, "can_mask": 0x7FF}]) as f, node("tx") as tx, node("all") as al:
        deadline = time.monotonic() + 5
        while f._acked_gen != 1 and time.monotonic() < deadline:
            assert f.recv(0.05) is None  # takes the server's acknowledgement of the filters
        assert f._acked_gen == f._filter_gen == 1
        tx.send(can.Message(arbitration_id=0x200, data=b"\x02", is_extended_id=False))
        assert al.recv(2.0).arbitration_id == 0x200
        tx.send(can.Message(arbitration_id=0x100, data=b"\x01", is_extended_id=False))
        # the raw socket of f holds 0x100 only: 0x200 was never sent to it (not merely filtered here)
        msg, already_filtered = f._recv_internal(2.0)
        assert (msg.arbitration_id, already_filtered) == (0x100, True)
        assert f.recv(0.2) is None
        f.set_filters([{"can_id": 0x200, "can_mask": 0x7FF, "extended": False}])
        tx.send(can.Message(arbitration_id=0x100, data=b"", is_extended_id=False))
        tx.send(can.Message(arbitration_id=0x200, data=b"", is_extended_id=False))
        assert f.recv(2.0).arbitration_id == 0x200
        assert f.recv(0.3) is None


def test_notifier_with_asyncio_loop_uses_the_fd_and_gets_every_frame(server):
    async def run() -> list[int]:
        with node("asyncrx") as bus, node("tx") as tx:
            reader = can.AsyncBufferedReader()
            notifier = can.Notifier(bus, [reader], loop=asyncio.get_running_loop())
            try:
                assert bus.fileno() in notifier._readers  # the fileno path, not a reader thread
                for k in range(3):  # several records can arrive in one go: each must come out
                    tx.send(can.Message(arbitration_id=0x10 + k, data=b"", is_extended_id=False))
                return [(await asyncio.wait_for(reader.get_message(), 3.0)).arbitration_id for _ in range(3)]
            finally:
                notifier.stop()

    assert asyncio.run(run()) == [0x10, 0x11, 0x12]


def test_a_node_that_disconnects_loses_its_queue_and_does_not_disturb_others(server, caplog):
    caplog.set_level(logging.INFO, logger="hil.runtime.realtime.bus_server")
    with node("rx") as rx, node("other") as other:
        with node("quitter") as q:
            for k in range(5):  # the first goes on the wire (~26 ms), four wait in its TX queue
                q.send(can.Message(arbitration_id=0x300 + k, data=DATA8, is_extended_id=False))
        # the frame on the wire completes, the queued four are dropped and counted
        assert rx.recv(3.0).arbitration_id == 0x300
        assert rx.recv(0.3) is None  # the next would have ended ~26 ms later
        other.send(can.Message(arbitration_id=0x55, data=b"\x01", is_extended_id=False))
        assert rx.recv(2.0).arbitration_id == 0x55
        stats = server.stats
    assert (stats.frames, stats.frames_dropped, stats.clients) == (2, 4, 2)
    assert stats.dropped_by_node == {"quitter": 4}
    # the loss is a warning that names the node and the count; a node that leaves with nothing queued is not
    left = {r.getMessage().split(" node ")[1].split(" ")[0]: r for r in caplog.records if " left (" in r.getMessage()}
    assert left["quitter"].levelno == logging.WARNING
    assert left["quitter"].getMessage().endswith("; 4 queued frames dropped")
    server.close()
    rx_left = [r for r in caplog.records if " node rx " in r.getMessage() and " left (" in r.getMessage()]
    assert [r.levelno for r in rx_left] == [logging.INFO]


def test_the_rig_records_a_nodes_lost_queue_as_a_warning_event_from_its_bus(rt):
    """The real-time rig hands its servers' warnings to the run's events (summary, metrics, recording): here a node
    that leaves with four frames queued while the run's clock reads about t = 1.5 s, timed when it left though
    reported a simulated second later. Past the limit one more says the rest are not recorded, and then nothing:
    nodes that come and go cannot fill the orchestrator's memory."""
    from hil.record.runlog import Event
    from hil.runtime.realtime.native_server import NativeBusServer
    from hil.runtime.realtime.orchestrator import record_bus_warnings

    events: list[Event] = []
    pace, clock = 2.0, {"t0": time.time() - 0.75}
    srv = NativeBusServer("r1", "bus1", SLOW).start(pump_thread=False)  # reported only when asked
    try:
        record_bus_warnings(srv, events, "bus1", clock, pace, limit=1)
        with node("rx") as rx:
            left_at = []
            for name in ("quitter", "second", "third"):
                with node(name) as q:
                    for k in range(5):
                        q.send(can.Message(arbitration_id=0x300 + k, data=DATA8, is_extended_id=False))
                left_at.append((time.time() - clock["t0"]) * pace)
                assert rx.recv(3.0).arbitration_id == 0x300  # its frame on the wire ends; the rest were dropped
            time.sleep(0.5)
            reported_at = (time.time() - clock["t0"]) * pace
            srv.stats  # reports the server's messages so far
    finally:
        srv.close()
    assert [(e.level, e.source) for e in events] == [("WARN", "bus1")] * 2, events
    assert events[0].text.startswith("node quitter (#") and events[0].text.endswith("; 4 queued frames dropped")
    assert reported_at - left_at[0] > 1.0
    assert left_at[0] - 0.05 <= events[0].t <= left_at[0] + 0.2, (left_at, events[0].t)
    assert events[1].text.startswith("more than 1 warnings from this bus: the rest are not recorded")


def test_protocol_violation_disconnects_only_the_offender(server):
    with node("rx") as rx, node("tx") as tx:
        raw = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        raw.connect(str(server.path))
        raw.sendall(protocol.pack_frame(0x1, b""))  # a frame before HELLO
        raw.settimeout(2.0)
        assert raw.recv(24) == b""  # the server hung up
        raw.close()
        tx.send(can.Message(arbitration_id=0x7, data=b"", is_extended_id=False))
        assert rx.recv(2.0).arbitration_id == 0x7


def test_bad_frames_are_refused_by_the_plugin(server):
    with node("a") as a:
        with pytest.raises(can.CanOperationError, match="remote"):
            a.send(can.Message(arbitration_id=0x1, is_remote_frame=True, is_extended_id=False))
        with pytest.raises(ValueError, match="0x800"):
            a.send(can.Message(arbitration_id=0x800, is_extended_id=False, check=False))


def test_shutdown_stops_the_thread_and_then_clients_get_a_clear_error(rt, server_cls):
    srv = server_cls("r1", "bus1", 500_000).start()
    assert srv.path.exists()
    with node("a") as a:
        srv.close()
        assert not srv.path.exists()
        with pytest.raises(can.CanOperationError, match="closed the connection"):
            a.recv(2.0)
    with pytest.raises(can.CanInitializationError, match=str(srv.path).replace(".", r"\.")):
        node("b")


def test_connecting_without_a_server_names_the_socket(rt):
    with pytest.raises(can.CanInitializationError, match=r"no bus server is running at .*/r1/bus1\.sock"):
        TrainhilBus("r1/bus1")
    sockets.run_dir("r1", create=True)
    (rt / "trainhil" / "r1" / "bus1.sock").touch()
    with pytest.raises(can.CanInitializationError, match="no bus server"):
        TrainhilBus("r1/bus1")


def test_one_server_per_socket_and_stale_sockets_are_replaced(rt, server_cls):
    with server_cls("r1", "bus1", 500_000):
        with pytest.raises(BusServerError, match="already running"):
            server_cls("r1", "bus1", 500_000)
    stale = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    stale.bind(str(sockets.socket_path("r1", "bus1")))
    stale.close()  # the file stays, nobody listens
    with server_cls("r1", "bus1", 500_000) as srv, node("a") as a:
        assert srv.stats.clients == 1 and a.bitrate == 500_000
        assert stat.S_IMODE(os.stat(srv.path).st_mode) == 0o600


def test_python_can_factory_and_detection_find_running_buses(server, monkeypatch):
    monkeypatch.setitem(can.interfaces.BACKENDS, "trainhil", ("hil.runtime.realtime.pycan_bus", "TrainhilBus"))
    monkeypatch.setattr(can.util, "VALID_INTERFACES", can.util.VALID_INTERFACES | {"trainhil"})
    assert can.detect_available_configs("trainhil") == [{"interface": "trainhil", "channel": "r1/bus1"}]
    with can.Bus(interface="trainhil", channel="r1/bus1") as a, node("b") as b:
        assert isinstance(a, TrainhilBus) and "r1/bus1" in a.channel_info
        b.send(can.Message(arbitration_id=0x42, data=b"\x42", is_extended_id=False))
        assert a.recv(2.0).arbitration_id == 0x42


@NEEDS_ENTRY_POINT
def test_installed_entry_point_opens_the_bus(server):
    with can.Bus(interface="trainhil", channel="r1/bus1") as a, node("b") as b:
        b.send(can.Message(arbitration_id=0x43, data=b"", is_extended_id=False))
        assert a.recv(2.0).arbitration_id == 0x43


@NEEDS_ENTRY_POINT
def test_can_logger_records_an_asc_log_that_cantools_decodes(server, tmp_path):
    out = tmp_path / "out.asc"
    logger = subprocess.Popen([sys.executable, "-m", "can.logger", "-i", "trainhil", "-c", "r1/bus1", "-f", str(out)],
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=os.environ.copy())
    try:
        assert logger.stdout.readline().startswith("Connected to TrainhilBus")
        db = TrainDb.load()
        cmd, ref = db.traction_cmd(0), db.reference
        sent = {cmd.frame_id: cmd.encode([1, -12340.0], 5), ref.frame_id: ref.encode([1234.567, 41.5], 2)}
        with node("ecu") as ecu:
            for fid, data in sent.items():
                ecu.send(can.Message(arbitration_id=fid, data=data, is_extended_id=False))
            while server.stats.frames < 2:  # both ended on the bus
                time.sleep(0.02)
        time.sleep(1.0)  # let the logger process read them
    finally:
        logger.send_signal(signal.SIGINT)
        logger.communicate(timeout=10)
    logged = {m.arbitration_id: bytes(m.data) for m in can.ASCReader(out)}
    assert logged == sent
    decoded = db.database.decode_message(cmd.frame_id, logged[cmd.frame_id])
    assert decoded["Force"] == -12340 and decoded["AliveCounter"] == 5
    decoded = db.database.decode_message(ref.frame_id, logged[ref.frame_id])
    assert decoded["Position"] == pytest.approx(1234.567) and decoded["Speed"] == pytest.approx(41.5, abs=0.01)


# ---------------------------------------------------------------- command line

def test_bus_server_command_serves_until_duration_and_writes_stats(rt, tmp_path):
    stats_file = tmp_path / "stats.json"
    proc = subprocess.Popen([sys.executable, "-m", "hil.runtime.realtime.bus_server", "--run", "cli", "--bus", "bus1",
                             "--bitrate", "250000", "--duration", "60", "--stats-json", str(stats_file)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=REPO, env=os.environ.copy())
    try:
        line = proc.stdout.readline()
        assert line.startswith("ready ") and line.split()[1].endswith("/cli/bus1.sock")
        with TrainhilBus("cli/bus1", node_name="a") as a, TrainhilBus("cli/bus1", node_name="b") as b:
            assert a.bitrate == 250_000
            a.send(can.Message(arbitration_id=0x10, data=b"\x01", is_extended_id=False))
            assert b.recv(2.0).arbitration_id == 0x10
        proc.send_signal(signal.SIGTERM)
        out, err = proc.communicate(timeout=10)
    finally:
        proc.kill()
    assert proc.returncode == 0, err
    stats = json.loads(stats_file.read_text())
    assert stats["frames"] == 1 and stats["bitrate"] == 250_000
    assert not Path(line.split()[1]).exists()  # the socket is removed on exit
    bad = subprocess.run([sys.executable, "-m", "hil.runtime.realtime.bus_server", "--run", "../x", "--bus", "bus1"],
                         capture_output=True, text=True, cwd=REPO, env=os.environ.copy())
    assert bad.returncode == 2 and "run name '../x' is invalid" in bad.stderr


def test_latency_histogram_quantiles_are_upper_bounds_within_a_bin():
    from tests.oracle.python_server import _Histogram

    h = _Histogram()
    for ns in [1_500] * 50 + [2_047_000] * 49 + [300_000_000]:  # 1.5 us, 2.047 ms, one 300 ms outlier
        h.add(ns)
    assert h.quantile_s(0.5) == pytest.approx(2e-6)  # 1 us bins below 1.024 ms: [1, 2) us
    assert h.quantile_s(0.99) == pytest.approx(2.048e-3)  # bin [2046, 2048) us, 0.1 % wide
    assert h.quantile_s(1.0) == pytest.approx(0.3)  # capped at the exact maximum
    assert _Histogram().quantile_s(0.5) is None


def test_bus_server_parser_registers_on_the_hil_parser():
    import argparse

    from hil.runtime.realtime.command_line import add_bus_server_parser, cmd_bus_server

    p = argparse.ArgumentParser(prog="hil")
    add_bus_server_parser(p.add_subparsers(dest="command", required=True))
    args = p.parse_args(["bus-server", "--run", "seed000", "--bus", "bus1", "--policy", "fifo"])
    assert (args.func, args.run, args.bus, args.bitrate, args.policy, args.depth) == \
        (cmd_bus_server, "seed000", "bus1", 500_000, "fifo", 64)


@pytest.mark.parametrize("args, named", [(["--bitrate", "0"], "--bitrate"), (["--bitrate", "-5"], "--bitrate"),
                                         (["--depth", "0"], "--depth"), (["--duration", "-1"], "--duration"),
                                         (["--pace", "0"], "--pace"), (["--pace", "nan"], "--pace")])
def test_bus_server_command_refuses_values_that_cannot_work(rt, capsys, args, named):
    from hil.runtime.realtime.command_line import bus_server_main

    with pytest.raises(SystemExit) as exc:
        bus_server_main(["--run", "v1", "--bus", "bus1", *args])
    assert exc.value.code == 2 and f"argument {named}" in capsys.readouterr().err
    assert not (rt / "trainhil" / "v1").exists()  # refused before anything was made


def test_both_servers_meet_the_bus_server_protocol(rt, server_cls):
    """The seam is a typing.Protocol (hil/runtime/realtime/bus_server.py): the engine's server and the oracle."""
    from hil.runtime.realtime.bus_server import BusServer as BusServerProtocol

    server = server_cls("proto", "bus1", 500_000)
    try:
        assert isinstance(server, BusServerProtocol)
    finally:
        server.close()
