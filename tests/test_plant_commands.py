"""The plant's TractionCmd checks, shared by both runtimes: length, E2E CRC and Mode are checked and the command
decoded by the engine on receipt (``Network.attach_commands`` in virtual time, ``trainhil_engine.CommandInbox`` in
real time, both from ``PlantCanNode.command_table``); the plant node applies a valid one (``apply``), and counts and
logs a refused one with its reason (``refuse``), which never reaches the plant."""
from __future__ import annotations

import pytest
import trainhil_engine as engine

from ecu_sim.view import BrakeMode
from hil.plant.can_node import VALID_MODES
from hil.runtime.virtual import VirtualRig
from hil.scenario import load_scenario


@pytest.fixture
def rig() -> VirtualRig:
    return VirtualRig(load_scenario("seed000"))


def _receive(rig: VirtualRig, train: int, frame_id: int, data: bytes, t: float) -> int | None:
    """A frame on a train's bus through the engine's check and the plant node, as the real-time plant takes it: the
    unit it drove, or None when refused or out of sequence."""
    inbox = engine.CommandInbox(rig.plant_io.command_table(train), VALID_MODES, [], rig.layout.n_units)
    assert inbox.put(frame_id, data, t)
    valid, refused, _ = inbox.take()
    for frame in refused:
        rig.plant_io.refuse(train, *frame)
    return next((u for u, *rest in valid if rig.plant_io.apply(u, *rest)), None)


def test_a_good_command_drives_its_unit(rig):
    codec, u = rig.db.traction_cmd(1), rig.layout.index(1, 1)  # train 2, unit 2
    assert _receive(rig, 1, codec.frame_id, codec.encode((int(BrakeMode.NORMAL), -20_000.0), 1), 0.5) == u
    assert rig.plant._act.force_cmd[u] == pytest.approx(-20_000.0, abs=1.0)
    assert _receive(rig, 1, codec.frame_id, codec.encode((int(BrakeMode.SERVICE), 0.0), 2), 0.51) == u


def _refused(rig: VirtualRig, data: bytes) -> list[str]:
    """Hand ``data`` as train 1's TractionCmd_U01; assert it is refused and unapplied; the plant's warnings."""
    codec = rig.db.traction_cmd(0)
    before = rig.plant._act.force_cmd.copy()
    assert _receive(rig, 0, codec.frame_id, data, 0.5) is None
    assert (rig.plant._act.force_cmd == before).all()
    return [e.text for e in rig.log.events if e.source == "bus1/plant"]


def test_a_command_of_the_wrong_length_is_refused_and_counted(rig):
    codec = rig.db.traction_cmd(0)
    data = codec.encode((0, -5e4), 1)
    assert _refused(rig, data[:-1]) == [f"TractionCmd_U01: {codec.dlc - 1} bytes, DLC is {codec.dlc}: frame ignored"]
    assert rig.plant_io.malformed_frames == 1 and rig.plant_io.e2e_errors == 0


def test_a_command_with_a_crc_error_is_refused_and_counted(rig):
    data = bytearray(rig.db.traction_cmd(0).encode((0, -5e4), 1))
    data[-1] ^= 0x10
    assert _refused(rig, bytes(data)) == ["TractionCmd_U01: CRC error, frame ignored"]
    assert rig.plant_io.e2e_errors == 1 and rig.plant_io.malformed_frames == 0


def test_a_crc_valid_command_with_an_unknown_mode_is_refused(rig):
    codec = rig.db.traction_cmd(0)
    data = bytearray(codec.encode((0, -5e4), 1))
    data[1] |= 0x30  # Mode (bits 12-13) = 3: the DBC's range is 0..2, so encode would saturate it
    data[0] = engine.e2e_crc(codec.data_id, data)
    assert codec.crc_ok(bytes(data))
    assert _refused(rig, bytes(data)) == ["TractionCmd_U01: unknown Mode 3, frame ignored"]


def test_a_frame_that_is_not_a_command_of_the_train_is_a_programming_error(rig):
    codec = rig.db.agent_state(0)
    with pytest.raises(KeyError, match="not a TractionCmd of train 1"):
        rig.plant_io.refuse(0, codec.frame_id, codec.encode((0.0, 0.0), 1), 0.5)
