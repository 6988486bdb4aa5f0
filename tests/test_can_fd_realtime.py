"""CAN FD in real time: both bus servers carry FD frames of up to 64 bytes beside classical ones, the
python-can interface opens FD buses with fd=True and marks is_fd and bitrate_switch, a classical-only client gets
clear errors, and a real-time FD run keeps its FD frames in its CAN logs."""
from __future__ import annotations

import can
import pytest

from hil.can.frame import fd_frame_bits, fd_pad, frame_bits
from hil.runtime.realtime.pycan_bus import TrainhilBus
from tests.polling import wait_for


def _fd_server(server_cls, fd: bool = True):
    return server_cls("r1", "bus1", 1_000_000, fd=fd, data_bitrate=5_000_000 if fd else None)


def _receive(bus: can.BusABC, n: int, timeout: float = 3.0) -> list[can.Message]:
    got: list[can.Message] = []
    assert wait_for(lambda: (m := bus.recv(0.05)) is not None and got.append(m) is None and len(got) >= n, timeout)
    return got


def test_fd_and_classical_frames_share_an_fd_bus_and_keep_their_format(rt, server_cls):
    with _fd_server(server_cls) as srv:
        with TrainhilBus("r1/bus1", fd=True, node_name="tx") as tx, TrainhilBus("r1/bus1", node_name="rx") as rx:
            assert tx.data_bitrate == 5_000_000 and "CAN FD data 5000000" in tx.channel_info
            tx.send(can.Message(arbitration_id=0x10, data=bytes(8), is_fd=True, bitrate_switch=True, is_extended_id=False))
            tx.send(can.Message(arbitration_id=0x11, data=bytes(8), is_fd=True, bitrate_switch=False, is_extended_id=False))
            tx.send(can.Message(arbitration_id=0x12, data=bytes(8), is_extended_id=False))
            got = {m.arbitration_id: m for m in _receive(rx, 3)}
        assert (got[0x10].is_fd, got[0x10].bitrate_switch) == (True, True)
        assert (got[0x11].is_fd, got[0x11].bitrate_switch) == (True, False)
        assert not got[0x12].is_fd  # a classical frame stays classical on an FD bus
        assert wait_for(lambda: srv.stats.frames >= 3)


def test_a_classical_only_client_is_told_what_to_do(rt, server_cls):
    with _fd_server(server_cls, fd=False):
        with pytest.raises(can.CanInitializationError, match=r"fd=True, but the bus 'r1/bus1' is classical CAN"):
            TrainhilBus("r1/bus1", fd=True)
        with TrainhilBus("r1/bus1") as bus:
            with pytest.raises(can.CanOperationError, match=r"open the bus with fd=True"):
                bus.send(can.Message(arbitration_id=0x10, data=bytes(8), is_fd=True, is_extended_id=False))
    with _fd_server(server_cls):
        with TrainhilBus("r1/bus1", fd=True) as bus:
            with pytest.raises(ValueError, match=r"12 data bytes > 8 in a classical frame"):
                bus.send(can.Message(arbitration_id=0x10, data=bytes(12), is_extended_id=False))
            with pytest.raises(ValueError, match=r"65 data bytes > 64"):
                bus.send(can.Message(arbitration_id=0x10, data=bytes(65), is_fd=True, is_extended_id=False, check=False))


@pytest.mark.parametrize("length", [9, 12, 31, 48, 64])
def test_fd_payloads_up_to_64_bytes_cross_the_server_whole(rt, server_cls, length):
    """A long FD payload travels as a FRAME record and FRAME_DATA records; it arrives padded to its FD length, timed
    by its padded length, and the frames around it are untouched."""
    payload = bytes((7 * k + 1) % 256 for k in range(length))
    padded = len(fd_pad(payload))
    with _fd_server(server_cls) as srv:
        with TrainhilBus("r1/bus1", fd=True, node_name="tx") as tx, TrainhilBus("r1/bus1", fd=True, node_name="rx") as rx:
            for can_id, data in ((0x10, b"\x01"), (0x11, payload), (0x12, b"\x02\x03")):
                tx.send(can.Message(arbitration_id=can_id, data=data, is_fd=True, bitrate_switch=True, is_extended_id=False))
            got = {m.arbitration_id: m for m in _receive(rx, 3)}
        assert bytes(got[0x11].data) == fd_pad(payload) and got[0x11].dlc == padded and got[0x11].is_fd
        assert bytes(got[0x10].data) == b"\x01" and bytes(got[0x12].data) == b"\x02\x03"
    nominal, fast = fd_frame_bits(0x11, fd_pad(payload))
    assert round(1e9 * max(lat for _, fid, lat, _ in srv.log.frames.array if fid == 0x11)) >= nominal * 1000 + fast * 200


def test_the_servers_time_fd_frames_at_both_rates(rt, server_cls):
    """The end-to-end latency of a lone frame on an idle bus is its exact duration (FD: nominal + data phase)."""
    with _fd_server(server_cls) as srv:
        with TrainhilBus("r1/bus1", fd=True, node_name="tx") as tx, TrainhilBus("r1/bus1", node_name="rx") as rx:
            tx.send(can.Message(arbitration_id=0x10, data=bytes(range(8)), is_fd=True, bitrate_switch=True,
                                is_extended_id=False))
            _receive(rx, 1)
            tx.send(can.Message(arbitration_id=0x20, data=bytes(range(8)), is_extended_id=False))
            _receive(rx, 1)
        assert wait_for(lambda: srv.stats.frames >= 2)
    nominal, fast = fd_frame_bits(0x10, bytes(range(8)))
    durations = sorted(round(lat * 1e9) for _, _, lat, _ in srv.log.frames.array)
    assert durations == sorted([nominal * 1000 + fast * 200, frame_bits(0x20, bytes(range(8))) * 1000])


def test_a_real_time_fd_run_logs_fd_frames(rt, tmp_path):
    from hil.runtime.realtime.orchestrator import run_realtime
    from hil.scenario import load_scenario

    sc = load_scenario("seed000", {"can.fd": True, "can.data_bitrate": 2_000_000})
    res = run_realtime(sc, tmp_path / "rt", pace=1.0, duration_s=1.0, ecus_per_process=6, can_log=True)
    assert res.metrics["frames_lost"] == 0
    msgs = list(can.ASCReader(tmp_path / "rt" / "bus1.asc"))
    assert len(msgs) > 500 and all(m.is_fd and m.bitrate_switch for m in msgs)


def test_hil_bus_server_serves_an_fd_bus_and_names_a_data_bitrate_without_fd(rt):
    import subprocess
    import sys

    bad = subprocess.run([sys.executable, "-m", "hil", "bus-server", "--run", "r2", "--bus", "bus1",
                          "--data-bitrate", "2000000", "--duration", "1"], capture_output=True, text=True, timeout=60)
    assert bad.returncode == 2 and "--data-bitrate is for CAN FD buses: add --fd" in bad.stderr
    proc = subprocess.Popen([sys.executable, "-m", "hil", "bus-server", "--run", "r2", "--bus", "bus1", "--fd",
                             "--bitrate", "1000000", "--data-bitrate", "8000000", "--duration", "20"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        assert proc.stdout.readline().startswith("ready ")
        with TrainhilBus("r2/bus1", fd=True) as bus:
            assert (bus.bitrate, bus.data_bitrate) == (1_000_000, 8_000_000)
    finally:
        proc.terminate()
        proc.communicate(timeout=30)
