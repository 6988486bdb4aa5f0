"""A foreign client sends a bus server bad input: each case is counted and logged, the offender is dropped if it
broke the protocol, and the server and the well-behaved nodes carry on as if nothing happened.

Cases: truncated records, bad DLC, remote/error/echo flags, ids out of range, unknown record kinds, garbage
bytes, a frame before HELLO, oversized filter sets, non-UTF-8 names, abrupt disconnects with queued frames, a
connection that never says HELLO, too many connections. Receivers: an ECU counts frames of unknown IDs and of
the wrong length instead of decoding them.
"""
from __future__ import annotations

import logging
import re
import socket
import struct
import time
from pathlib import Path

import can
import pytest

from ecu_sim.codec import TrainDb
from hil.runtime.realtime import protocol
from tests.oracle.python_server import PythonBusServer as BusServer
from hil.runtime.realtime.pycan_bus import TrainhilBus
from tests.polling import wait_for

DATA = bytes(range(1, 9))


@pytest.fixture
def server(rt, server_cls):
    with server_cls("r1", "bus1", 500_000, hello_timeout_s=0.3, max_clients=8) as srv:
        yield srv


def raw(server: BusServer, payload: bytes, hello: str | None = "foreign", close: bool = True) -> socket.socket:
    """A unix connection that (optionally) says HELLO, then sends ``payload`` as it is."""
    s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    s.connect(str(server.path))
    if hello is not None:
        s.sendall(protocol.pack_hello(hello))
        assert protocol.unpack_welcome(s.recv(24)).bitrate == server.bitrate
    if payload:
        s.sendall(payload)
    if close:
        s.close()
    return s


def hung_up(s: socket.socket, timeout: float = 2.0) -> bool:
    """True when the server closed the connection (reads EOF or a reset)."""
    s.settimeout(timeout)
    try:
        while True:
            chunk = s.recv(4096)
            if not chunk:
                return True
    except (ConnectionResetError, BrokenPipeError):
        return True
    except TimeoutError:
        return False


def still_works(server: BusServer, k: int) -> None:
    """Two well-behaved nodes exchange a frame; the server thread is alive."""
    with TrainhilBus("r1/bus1", node_name=f"a{k}") as a, TrainhilBus("r1/bus1", node_name=f"b{k}") as b:
        a.send(can.Message(arbitration_id=0x10 + k, data=DATA, is_extended_id=False))
        got = b.recv(2.0)
        assert got is not None and got.arbitration_id == 0x10 + k and bytes(got.data) == DATA
    assert server.serving


def frame_record(can_id: int, dlc: int, flags: int = 0, data: bytes = DATA) -> bytes:
    return protocol.FRAME.pack(protocol.KIND_FRAME, flags, dlc, can_id, 0.0, data)


# (case id, bytes after HELLO (None: no HELLO), counter that must rise, whether the server hangs up)
SESSION_CASES = [
    ("dlc-9", frame_record(0x100, 9), "frames_rejected", False),
    ("dlc-255", frame_record(0x100, 255), "frames_rejected", False),
    ("remote-flag", frame_record(0x100, 8, protocol.FLAG_REMOTE), "frames_rejected", False),
    ("error-flag", frame_record(0x100, 8, protocol.FLAG_ERROR), "frames_rejected", False),
    ("echo-flag", frame_record(0x100, 8, protocol.FLAG_ECHO), "frames_rejected", False),
    ("id-beyond-11-bits", frame_record(0x800, 8), "frames_rejected", False),
    ("id-beyond-29-bits", frame_record(1 << 29, 8, protocol.FLAG_EXTENDED), "frames_rejected", False),
    ("unknown-kind", bytes([99]) + bytes(23), "protocol_errors", True),
    ("kind-zero", bytes(24), "protocol_errors", True),
    ("welcome-from-a-node", protocol.pack_welcome(1, 0.0, 1), "protocol_errors", True),
    ("second-hello", protocol.pack_hello("again"), "protocol_errors", True),
    ("garbage", b"\xde\xad\xbe\xef" * 60, "protocol_errors", True),
    ("too-many-filters", protocol.FILTERS.pack(protocol.KIND_FILTERS, protocol.MAX_FILTERS + 1, 1), "protocol_errors", True),
    ("filter-without-head", protocol.FILTER.pack(protocol.KIND_FILTER, 0, 1, 0x7FF), "protocol_errors", True),
    ("bad-filter-match", protocol.FILTERS.pack(protocol.KIND_FILTERS, 1, 1) + protocol.FILTER.pack(protocol.KIND_FILTER, 7, 1, 1),
     "protocol_errors", True),
    ("frame-before-hello", None, "protocol_errors", True),
]


@pytest.mark.parametrize(("payload", "counter", "hangs_up"), [c[1:] for c in SESSION_CASES],
                         ids=[c[0] for c in SESSION_CASES])
def test_bad_records_are_counted_and_only_the_offender_suffers(server, caplog, payload, counter, hangs_up):
    before = server.stats.as_dict()
    with caplog.at_level(logging.WARNING, logger="hil.runtime.realtime.bus_server"):
        if payload is None:
            s = raw(server, frame_record(0x100, 8), hello=None, close=False)
        else:
            s = raw(server, payload, close=False)
        assert hung_up(s, 2.0 if hangs_up else 0.3) == hangs_up
        assert wait_for(lambda: server.stats.as_dict()[counter] == before[counter] + 1)
        s.close()
    still_works(server, 0)
    after = server.stats.as_dict()
    others = {"frames_rejected", "protocol_errors", "truncated_records", "auth_failures", "clients_refused"} - {counter}
    assert all(after[k] == before[k] for k in others), {k: (before[k], after[k]) for k in others}
    assert after["frames"] == before["frames"] + 1  # only the well-behaved frame went on the bus
    assert any(r.levelno == logging.WARNING and "r1/bus1" in r.getMessage() for r in caplog.records)


def test_truncated_records_are_discarded_and_counted(server):
    for cut in (1, 8, 23):
        raw(server, frame_record(0x123, 8)[:cut])
    assert wait_for(lambda: server.stats.truncated_records == 3)
    raw(server, protocol.pack_hello("half")[:10], hello=None)  # inside the HELLO itself
    assert wait_for(lambda: server.stats.truncated_records == 4)
    still_works(server, 1)
    assert server.stats.frames == 1 and server.stats.protocol_errors == 0


def test_a_record_split_across_writes_is_reassembled(server):
    with TrainhilBus("r1/bus1", node_name="rx") as rx:
        s = raw(server, b"", close=False)
        rec = frame_record(0x321, 8)
        for part in (rec[:5], rec[5:17], rec[17:]):
            s.sendall(part)
            time.sleep(0.02)
        got = rx.recv(2.0)
        assert got.arbitration_id == 0x321 and bytes(got.data) == DATA
        s.close()
    assert server.stats.truncated_records == 0


def test_abrupt_disconnect_with_queued_frames_counts_them(rt, server_cls):
    with server_cls("r1", "bus1", 5000) as srv:  # slow bus: 26 ms per frame, so frames queue up
        with TrainhilBus("r1/bus1", node_name="rx") as rx:
            s = raw(srv, b"".join(frame_record(0x200 + k, 8) for k in range(10)), close=False)
            s.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))  # RST, not FIN
            time.sleep(0.05)
            s.close()
            first = rx.recv(2.0)
            assert first is not None and first.arbitration_id == 0x200
            assert wait_for(lambda: srv.stats.frames + srv.stats.frames_dropped == 10)  # sent or counted: none vanish
            stats = srv.stats
            assert stats.frames_dropped >= 5 and stats.clients == 1
            still_works(srv, 2)


def test_a_nodes_first_frame_refused_by_its_full_tx_queue_is_one_warning(rt, server_cls, caplog):
    """A node that sends faster than its bus overflows its TX queue: every frame refused is counted, and the first
    is a warning that names the node, the frame and the cause (in a rig run, a WARN event at its time), so a loss
    can be found; the rest are not logged, so a flood cannot flood the log."""
    caplog.set_level(logging.INFO)
    with server_cls("r1", "bus1", 5000, depth=4) as srv:  # slow bus: 26 ms per frame
        s = raw(srv, b"".join(frame_record(0x200 + k, 8) for k in range(10)), hello="flooder", close=False)
        assert wait_for(lambda: srv.stats.frames_dropped >= 5)  # four queued, one on the wire at most
        s.sendall(b"".join(frame_record(0x210 + k, 8) for k in range(5)))
        assert wait_for(lambda: srv.stats.frames_dropped >= 9)
        s.close()
    said = [r for r in caplog.records if " dropped frame " in r.getMessage()]
    assert [r.levelno for r in said] == [logging.WARNING], [r.getMessage() for r in said]
    assert re.fullmatch(r"bus \S+: node flooder dropped frame 0x20[45] \(its TX queue of 4 is full\); its later "
                        r"drops are only counted", said[0].getMessage()), said[0].getMessage()


def test_a_connection_that_never_says_hello_is_dropped(server):
    s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    s.connect(str(server.path))
    assert hung_up(s, 3.0)
    s.close()
    assert server.stats.protocol_errors == 1
    still_works(server, 3)


def test_connections_beyond_the_limit_are_refused_and_counted(server):
    held = [raw(server, b"", hello=f"n{k}", close=False) for k in range(8)]
    extra = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    extra.connect(str(server.path))
    assert hung_up(extra, 2.0)
    extra.close()
    assert server.stats.clients_refused == 1 and server.stats.clients == 8
    for s in held:
        s.close()
    assert wait_for(lambda: server.stats.clients == 0)
    still_works(server, 4)


def test_random_garbage_connections_never_stop_the_server(server):
    import random

    rng = random.Random(7)
    for k in range(40):
        blob = bytes(rng.randrange(256) for _ in range(rng.randrange(1, 200)))
        raw(server, blob, hello=None if k % 2 else "g")
    still_works(server, 5)
    stats = server.stats
    assert stats.protocol_errors + stats.truncated_records + stats.frames_rejected >= 20


# --------------------------------------------------------------------------- receivers


def test_an_ecu_counts_unknown_ids_and_wrong_lengths_without_decoding_them():
    from ecu_sim.controllers.base import get_controller
    from hil.runtime.firmware import build_ecu
    from hil.runtime.assembly import assemble
    from hil.scenario import load_scenario

    sc = load_scenario("seed000")
    parts, db = assemble(sc, 0), TrainDb.load()
    ecu = build_ecu(parts, db, 1)
    sensor = db.sensor(1)
    ecu.on_frame(0x7FF, DATA, 0.0)  # no such input
    ecu.on_frame(sensor.frame_id, DATA[:3], 0.0)  # the sensor's id, 3 bytes instead of 8
    ecu.on_frame(sensor.frame_id, DATA + DATA, 0.0)  # 16 bytes
    ecu.cycle(0.01)  # nothing usable arrived: no crash, the stale sensor brakes
    assert ecu.counters.unknown_frames == 1 and ecu.counters.malformed_frames == 2
    assert ecu.e2e_summary()["UNKNOWN_ID"] == 1 and ecu.e2e_summary()["WRONG_LENGTH"] == 2
    assert any("DLC is 8" in text for _, _, text in ecu.events)
    assert get_controller(sc.controller.law) is not None


# Every receiver checks the length before decoding: the plant (TractionCmd), the radio gateway (the tail's
# AgentState it reads positions from) and the ECUs.
WRONG_LENGTH_RECEIVERS = [
    pytest.param(0x080, 8, id="plant-TractionCmd_U01-8-bytes"),
    pytest.param(0x103, 3, id="radio-AgentState_U04-3-bytes"),
    pytest.param(0x101, 3, id="ecu-AgentState_U02-3-bytes"),  # an ECU input only: counted, no crash
]


@pytest.mark.parametrize(("frame_id", "length"), WRONG_LENGTH_RECEIVERS)
def test_a_known_id_with_the_wrong_length_does_not_stop_the_rig(frame_id, length):
    from hil.runtime.virtual import VirtualRig
    from hil.scenario import load_scenario

    rig = VirtualRig(load_scenario("seed000"))
    bus, node = rig.buses[0], rig._wayside_nodes[0]  # any node may send any ID: here the wayside's controller
    rig.kernel.at(int(0.5e9), lambda _: bus.send(node, frame_id, bytes(length)), None)
    log = rig.run(1.0)
    assert not log.interrupted and log.sim_time_s == pytest.approx(1.0)
    listeners = [e for e in rig.ecus[: rig.layout.units_per_train] if frame_id in e.rx_ids]  # on bus 1
    assert all(e.counters.malformed_frames == 1 for e in listeners)  # counted by every ECU that takes the ID
    if frame_id == 0x080:  # the plant's command input: counted and logged, the unit's command untouched
        assert rig.plant_io.malformed_frames == 1
        assert any("DLC is 5: frame ignored" in e.text for e in log.events)
