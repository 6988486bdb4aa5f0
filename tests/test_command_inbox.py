"""The real-time plant's command inbox (``trainhil_engine.CommandInbox``, engine/src/command_inbox.rs): TractionCmd
frames checked and decoded in the engine on receipt, AgentState frames closing the sensor-to-actuator latency, and
the plant node taking them at each event (hil/runtime/realtime/plant_node.py) in arrival order across its buses."""
from __future__ import annotations

import pytest
import trainhil_engine as engine

from ecu_sim.view import BrakeMode
from hil.plant.can_node import VALID_MODES
from hil.runtime.realtime.plant_node import PlantNode
from hil.runtime.train_db import load_train_db
from hil.scenario import load_scenario

NORMAL = int(BrakeMode.NORMAL)


@pytest.fixture(scope="module")
def node() -> PlantNode:
    sc = load_scenario("seed000")
    return PlantNode(sc, 0, load_train_db(sc), [], [])


def test_the_inbox_queues_valid_commands_keeps_refused_ones_raw_and_closes_latencies(node):
    db, train, unit = node.db, 1, 2
    u = node.layout.index(train, unit)
    cmd, state = db.traction_cmd(unit), db.agent_state(unit)
    inbox = engine.CommandInbox(node.io.command_table(train), VALID_MODES, [(state.frame_id, u)], node.layout.n_units)
    assert set(inbox.ids) == set(node.io.cmd_unit[train]) | {state.frame_id}  # the train's four commands
    inbox.published(1.0, [(u, 5)])
    assert inbox.put(cmd.frame_id, cmd.encode((NORMAL, -20_000.0), 3), 1.0025)
    bad = bytearray(cmd.encode((NORMAL, 1.0), 4))
    bad[-1] ^= 0x10
    assert inbox.put(cmd.frame_id, bytes(bad), 1.0026)
    assert inbox.put(state.frame_id, state.encode((1000.0, 80.0), 5), 1.003)
    assert not inbox.put(db.sensor(unit).frame_id, b"\0" * 8, 1.004)
    valid, refused, latencies = inbox.take()
    assert valid == [(u, pytest.approx(-20_000.0, abs=1.0), NORMAL, 1.0025, 3)]
    assert refused == [(cmd.frame_id, bytes(bad), 1.0026)]
    assert latencies == [(1.0025, pytest.approx(0.0025))]
    assert inbox.take() == ([], [], [])
    with pytest.raises(IndexError, match="unit 99"):
        inbox.published(0.0, [(99, 0)])


def test_the_plant_applies_the_commands_of_all_its_buses_in_arrival_order_and_logs_the_refused(node):
    """Train 2's command came first (3.1 ms) but its bus is read second: taken bus by bus, train 1's at 5.2 ms
    would have moved the plant past it, and train 2's would count as late."""
    step = node.sc.plant.step_s
    node.tick, node.target = 0, 10
    first, second = node.layout.index(1, 0), node.layout.index(0, 0)
    cmd = node.db.traction_cmd(0)
    node.inboxes[0].put(cmd.frame_id, cmd.encode((NORMAL, -30_000.0), 1), 5.2 * step)
    node.inboxes[1].put(cmd.frame_id, cmd.encode((NORMAL, -10_000.0), 1), 3.1 * step)
    node.inboxes[2].put(cmd.frame_id, cmd.encode((NORMAL, 0.0), 1)[:-1], 4.0 * step)
    node.take_commands()
    assert node.late_commands == 0 and node.tick == 6
    assert node.plant.force_cmd[first] == pytest.approx(-10_000.0, abs=1.0)
    assert node.plant.force_cmd[second] == pytest.approx(-30_000.0, abs=1.0)
    assert node.io.malformed_frames == 1
    assert [e.text for e in node.log.events if e.source == "bus3/plant"] == [
        f"{cmd.name}: {cmd.dlc - 1} bytes, DLC is {cmd.dlc}: frame ignored"]


def test_python_can_receivers_put_a_plants_frames_into_its_inbox(node):
    """On SocketCAN the frames come through python-can: ``route_commands`` puts them into the same inbox."""
    from hil.runtime.realtime.frame_io import PythonCanFrames

    frames = PythonCanFrames(None, [object()], extended=False)  # type: ignore[arg-type]
    inbox = engine.CommandInbox(node.io.command_table(0), VALID_MODES, [], node.layout.n_units)
    frames.route_commands(0, inbox)
    cmd = node.db.traction_cmd(1)
    frames._hand_over(0, cmd.frame_id, cmd.encode((NORMAL, -5_000.0), 2), 0.25)
    assert inbox.take()[0] == [(node.layout.index(0, 1), pytest.approx(-5_000.0, abs=1.0), NORMAL, 0.25, 2)]
