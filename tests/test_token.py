"""Local only: bus servers accept owner-only unix sockets, and loopback TCP only with the run's token.

A connection without the token, or with a wrong one, is refused and counted; a non-loopback address cannot be
bound; the token file and the socket are owner-only; other nodes are not disturbed by refused connections.
"""
from __future__ import annotations

import json
import os
import socket
import stat
import time
from pathlib import Path

import can
import pytest

from hil.runtime.realtime import protocol
from tests.oracle.python_server import PythonBusServer as BusServer
from hil.runtime.realtime.pycan_bus import TrainhilBus
from tests.polling import wait_for

DATA = bytes(range(8))


@pytest.fixture
def server(rt, server_cls):
    with server_cls("r1", "bus1", 500_000, tcp=True) as srv:
        yield srv


def raw_tcp(server: BusServer, *records: bytes) -> bytes:
    """Connect over TCP, send the records, return what the server answers before it hangs up (or 1 s passes)."""
    with socket.create_connection(server.tcp_address, timeout=2.0) as s:
        s.sendall(b"".join(records))
        got = b""
        s.settimeout(1.0)
        try:
            while chunk := s.recv(4096):
                got += chunk
        except (TimeoutError, ConnectionResetError):
            pass
        return got


def test_token_file_and_socket_are_owner_only(server, rt):
    run_dir = rt / "trainhil" / "r1"
    assert stat.S_IMODE(os.stat(run_dir).st_mode) == 0o700
    assert stat.S_IMODE(os.stat(server.path).st_mode) == 0o600
    tok = run_dir / "bus1.tcp"
    assert stat.S_IMODE(os.stat(tok).st_mode) == 0o600
    data = json.loads(tok.read_text())
    assert data["host"] == "127.0.0.1" and data["port"] == server.tcp_address[1]
    assert bytes.fromhex(data["token"]) == server.token and len(server.token) == 16


def test_without_the_token_or_with_a_wrong_one_the_connection_is_refused_and_counted(server):
    hello = protocol.pack_hello("intruder")
    refused = protocol.pack_refused(protocol.REFUSED_TOKEN)  # no WELCOME: why, then hung up
    assert raw_tcp(server, hello) == refused  # HELLO without AUTH
    wrong = bytes(b ^ 0xFF for b in server.token)
    assert raw_tcp(server, protocol.pack_auth(wrong), hello) == refused
    assert raw_tcp(server, protocol.pack_auth(bytes(16)), hello) == refused
    assert wait_for(lambda: server.stats.auth_failures == 3)
    stats = server.stats
    assert stats.clients == 0 and stats.protocol_errors == 0
    # with the token the same bytes get a WELCOME
    answer = raw_tcp(server, protocol.pack_auth(server.token), hello)
    assert protocol.unpack_welcome(answer[:24]).bitrate == 500_000
    assert server.stats.auth_failures == 3


def test_python_can_finds_the_token_in_the_run_directory_and_talks_to_unix_nodes(server):
    with TrainhilBus("tcp:r1/bus1", node_name="tcp-node") as tcp_node, TrainhilBus("r1/bus1", node_name="unix") as unix:
        tcp_node.send(can.Message(arbitration_id=0x123, data=DATA, is_extended_id=False))
        got = unix.recv(2.0)
        assert got is not None and got.arbitration_id == 0x123 and bytes(got.data) == DATA
        unix.send(can.Message(arbitration_id=0x42, data=b"\x01", is_extended_id=False))
        assert tcp_node.recv(2.0).arbitration_id == 0x42
    assert server.stats.auth_failures == 0


def test_python_can_with_a_wrong_or_missing_token_is_refused_clearly(server):
    port = server.tcp_address[1]
    with pytest.raises(can.CanInitializationError, match="refused the connection: a missing or wrong token"):
        can.Bus(interface="trainhil", channel=f"tcp://127.0.0.1:{port}", token="00" * 16)  # python-can: int 0
    with pytest.raises(can.CanInitializationError, match="refused the connection: a missing or wrong token"):
        can.Bus(interface="trainhil", channel=f"tcp://127.0.0.1:{port}", token=bytes(b ^ 1 for b in server.token))
    with pytest.raises(can.CanInitializationError, match="needs the run's token"):
        can.Bus(interface="trainhil", channel=f"tcp://127.0.0.1:{port}")
    with pytest.raises(can.CanInitializationError, match="must be 16 bytes"):
        can.Bus(interface="trainhil", channel=f"tcp://127.0.0.1:{port}", token="abcd")
    assert wait_for(lambda: server.stats.auth_failures == 2)
    with can.Bus(interface="trainhil", channel=f"tcp://127.0.0.1:{port}", token=server.token.hex()) as ok:
        assert ok.channel_info.startswith(f"trainhil tcp://127.0.0.1:{port}")


def test_refused_connections_do_not_disturb_the_other_nodes(server):
    with TrainhilBus("r1/bus1", node_name="rx") as rx, TrainhilBus("tcp:r1/bus1", node_name="tx") as tx:
        for k in range(20):
            raw_tcp(server, b"\x00" * 24) if k % 2 else raw_tcp(server, protocol.pack_hello(f"x{k}"))
            tx.send(can.Message(arbitration_id=0x100 + k, data=DATA, is_extended_id=False))
        ids = []
        while (m := rx.recv(1.0)) is not None:
            ids.append(m.arbitration_id)
        assert ids == [0x100 + k for k in range(20)]
    assert server.stats.auth_failures == 20


def test_only_loopback_can_be_bound(rt, server_cls):
    for host in ("0.0.0.0", "::", "192.168.1.10", "localhost", "example.com"):
        with pytest.raises(ValueError, match="loopback only"):
            server_cls("r1", "bus1", 500_000, tcp=True, tcp_host=host)
        assert not (rt / "trainhil" / "r1" / "bus1.sock").exists()  # nothing left behind
    for channel in ("tcp://0.0.0.0:5000", "tcp://10.1.2.3:5000"):
        with pytest.raises(can.CanInitializationError, match="loopback only"):
            TrainhilBus(channel, token="00" * 16)


def test_ipv6_loopback_works(rt, server_cls):
    if not socket.has_ipv6:
        pytest.skip("no IPv6")
    try:
        srv = server_cls("r1", "bus1", 500_000, tcp=True, tcp_host="::1").start()
    except OSError as exc:
        pytest.skip(f"::1 not available: {exc}")
    try:
        with TrainhilBus("tcp:r1/bus1") as a:
            assert a.bitrate == 500_000
    finally:
        srv.close()


def test_a_token_file_others_can_read_is_refused(server, rt):
    tok = rt / "trainhil" / "r1" / "bus1.tcp"
    os.chmod(tok, 0o644)
    with pytest.raises(can.CanInitializationError, match="mode 0o600"):
        TrainhilBus("tcp:r1/bus1")
    os.chmod(tok, 0o600)
    with TrainhilBus("tcp:r1/bus1"):
        pass


def test_a_socket_others_can_use_is_refused_by_clients(rt, server_cls):
    with server_cls("r1", "bus1", 500_000) as srv:
        os.chmod(srv.path, 0o666)
        with pytest.raises(can.CanInitializationError, match="group/others can use it"):
            TrainhilBus("r1/bus1")
        os.chmod(srv.path, 0o600)
        with TrainhilBus("r1/bus1"):
            pass


def test_the_token_file_goes_away_with_the_server(rt, server_cls):
    srv = server_cls("r1", "bus1", 500_000, tcp=True).start()
    tok = srv.token_file
    assert tok.exists()
    srv.close()
    assert not tok.exists() and not srv.path.exists()
    with pytest.raises(can.CanInitializationError, match="no TCP bus server"):
        TrainhilBus("tcp:r1/bus1")


def test_unix_sockets_need_no_token_and_an_unexpected_auth_is_a_protocol_error(rt, server_cls):
    with server_cls("r1", "bus1", 500_000) as srv:
        assert srv.token is None and srv.stats.tcp_port is None
        with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as s:
            s.connect(str(srv.path))
            s.sendall(protocol.pack_auth(bytes(16)))
            s.settimeout(2.0)
            assert s.recv(24) == b""
        assert wait_for(lambda: srv.stats.protocol_errors == 1)


def test_bus_server_command_with_tcp_publishes_the_endpoint_and_accepts_the_token(rt):
    import subprocess
    import sys

    proc = subprocess.Popen([sys.executable, "-m", "hil.runtime.realtime.bus_server", "--run", "r1", "--bus", "bus1", "--tcp",
                             "--duration", "20"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            env=os.environ.copy())
    try:
        words = proc.stdout.readline().split()
        assert words[0] == "ready" and words[2] == "tcp" and words[3].startswith("127.0.0.1:")
        assert Path(words[5]) == rt / "trainhil" / "r1" / "bus1.tcp"
        with TrainhilBus("tcp:r1/bus1") as a, TrainhilBus("r1/bus1") as b:
            a.send(can.Message(arbitration_id=0x21, data=DATA, is_extended_id=False))
            assert b.recv(2.0).arbitration_id == 0x21
    finally:
        proc.terminate()
        proc.communicate(timeout=10)


def test_connections_without_the_token_cannot_take_the_owners_slots(rt, server_cls):
    """The slot-exhaustion attack: another local user opens TCP connections and never shows the token. They
    have their own budget (MAX_UNAUTHENTICATED) and deadline (AUTH_TIMEOUT_S): the owner's unix-socket and
    authenticated nodes still join, up to max_clients, and whoever is refused is told why."""
    with server_cls("r1", "bus1", 500_000, tcp=True, max_clients=4) as srv:
        squatters = [socket.create_connection(srv.tcp_address, timeout=2.0) for _ in range(protocol.MAX_UNAUTHENTICATED)]
        assert wait_for(lambda: srv.stats.clients == 0)  # not nodes, and not counted against max_clients
        one_more = raw_tcp(srv)  # the budget of connections waiting to authenticate is used up
        assert protocol.refused_reason(one_more) == protocol.REFUSED_REASONS[protocol.REFUSED_WAITING]
        nodes = [TrainhilBus("r1/bus1", node_name=f"owner{k}") for k in range(4)]  # late or restarted owner nodes
        try:
            assert wait_for(lambda: srv.stats.clients == 4)
            with pytest.raises(can.CanInitializationError, match=r"refused the connection: the bus server is full"):
                TrainhilBus("r1/bus1", node_name="fifth")
            nodes[0].send(can.Message(arbitration_id=0x10, data=DATA, is_extended_id=False))
            assert nodes[1].recv(2.0).arbitration_id == 0x10
        finally:
            for n in nodes:
                n.shutdown()
        # the squatters are told and dropped after the deadline; a token holder then gets in over TCP
        for s in squatters:
            s.settimeout(5.0)
            assert protocol.refused_reason(s.recv(24)) == protocol.REFUSED_REASONS[protocol.REFUSED_TIMEOUT]
            s.close()
        assert wait_for(lambda: srv.stats.auth_failures >= protocol.MAX_UNAUTHENTICATED)
        with TrainhilBus("tcp:r1/bus1", node_name="tcp-owner") as ok:
            assert ok.channel_info.startswith("trainhil tcp:")
