"""Properties of the bus server's record parser: random bytes never crash it, and are rejected cleanly.

``decode_record`` turns any 24 bytes into a typed record or a ProtocolError (nothing else). A live server fed
random byte streams by a foreign client (with or without a HELLO first, in random pieces) stays up, keeps its
counters consistent, and two well-behaved nodes still exchange frames after every example.
"""
from __future__ import annotations

import os
import shutil
import socket
import tempfile
import time

import can
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from hil.runtime.realtime import protocol
from tests.oracle.python_server import PythonBusServer as BusServer
from hil.runtime.realtime.pycan_bus import TrainhilBus

RECORD = st.binary(min_size=protocol.RECORD_SIZE, max_size=protocol.RECORD_SIZE)
KINDS = st.sampled_from(range(1, 10))


@st.composite
def plausible_records(draw) -> bytes:
    """24 bytes with a known kind byte: reaches the per-kind checks, not only 'unknown kind'."""
    return bytes([draw(KINDS)]) + draw(st.binary(min_size=23, max_size=23))


@settings(max_examples=200, deadline=None, database=None)
@given(RECORD | plausible_records())
def test_decode_record_returns_a_typed_record_or_a_protocol_error(record):
    try:
        rec = protocol.decode_record(record)
    except protocol.ProtocolError as exc:
        assert str(exc)
        return
    assert isinstance(rec, (protocol.Frame, protocol.Hello, protocol.Welcome, protocol.FiltersHead, protocol.Filter,
                            protocol.FiltersAck, protocol.Auth, protocol.FrameData))
    if isinstance(rec, protocol.Frame):
        assert len(rec.data) <= protocol.MAX_DLC
        why = protocol.frame_error(rec.can_id, record[2], rec.flags)
        assert why is None or isinstance(why, str)


@settings(max_examples=100, deadline=None, database=None)
@given(st.binary(max_size=100))
def test_decode_record_refuses_other_lengths(blob):
    if len(blob) == protocol.RECORD_SIZE:
        return
    with pytest.raises(protocol.ProtocolError, match="24 bytes"):
        protocol.decode_record(blob)


@pytest.fixture(scope="module")
def server():
    d = tempfile.mkdtemp(prefix="th", dir="/tmp")
    old = os.environ.get("XDG_RUNTIME_DIR")
    os.environ["XDG_RUNTIME_DIR"] = d
    srv = BusServer("h1", "bus1", 1_000_000, hello_timeout_s=1.0).start()
    yield srv
    srv.close()
    if old is None:
        del os.environ["XDG_RUNTIME_DIR"]
    else:
        os.environ["XDG_RUNTIME_DIR"] = old
    shutil.rmtree(d, ignore_errors=True)


STREAMS = st.lists(st.binary(min_size=1, max_size=64) | plausible_records() | RECORD, min_size=1, max_size=8)


@settings(max_examples=100, deadline=None, database=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(hello=st.booleans(), pieces=STREAMS)
def test_random_streams_from_a_foreign_client_never_disturb_the_server(server, hello, pieces):
    before = server.stats
    with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as s:
        s.connect(str(server.path))
        if hello:
            s.sendall(protocol.pack_hello("fuzz"))
            assert protocol.unpack_welcome(s.recv(24)).client_id > 0
        try:
            for p in pieces:
                s.sendall(p)
        except (BrokenPipeError, ConnectionResetError):
            pass  # the server already hung up on a bad record
    with TrainhilBus("h1/bus1", node_name="a") as a, TrainhilBus("h1/bus1", node_name="b") as b:
        a.send(can.Message(arbitration_id=0x7E0, data=b"ok", is_extended_id=False))
        deadline = time.monotonic() + 3.0
        while (m := b.recv(max(deadline - time.monotonic(), 0))) is not None and m.arbitration_id != 0x7E0:
            pass  # frames the fuzz client got onto the bus may come first
        assert m is not None and m.arbitration_id == 0x7E0
    after = server.stats
    assert server.serving
    assert after.frames > before.frames
    bad = ("protocol_errors", "truncated_records", "frames_rejected", "auth_failures", "clients_refused")
    assert all(getattr(after, k) >= getattr(before, k) for k in bad)
