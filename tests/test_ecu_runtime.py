"""ECU runtime: E2E checks, freshness timeouts, degraded modes, crashes, and its output frames."""
from __future__ import annotations

import math

import pytest

from ecu_sim.codec import TrainDb
from ecu_sim.controllers.base import Controller, ControllerParams, PlantInfo
from ecu_sim.runtime import Ecu, NeighbourLink
from ecu_sim.view import AgentInfo, BrakeMode, Command, LocalView
from hil.scenario.model import EcuConfig

DB = TrainDb.load()
INFO = PlantInfo(davis_c0=0.0, davis_c1=0.0, davis_c2=0.0, coupler_stiffness=1.6e5, coupler_damping=600.0,
                 spacing_m=3000.0, emergency_gap_m=1500.0, radio_range_m=10_000.0, emergency_brake_mps2=1.2)


class Recorder(Controller):
    """Test law: remembers the last view and returns a fixed force (or raises on demand)."""

    name = "test-recorder"
    Params = ControllerParams

    def __init__(self, *a, force: float = 1000.0, fail: bool = False) -> None:
        super().__init__(*a)
        self.force, self.fail, self.views = force, fail, []

    def step(self, view: LocalView) -> Command:
        if self.fail:
            raise ZeroDivisionError("boom")
        self.views.append((view.x, view.v, [(n.valid, n.x, n.v) for n in view.neighbours], view.ref.valid, view.ref.x))
        return Command(self.force, BrakeMode.NORMAL, self.force / 8e4)


def make_ecu(unit: int = 1, has_reference: bool = False, **kw) -> tuple[Ecu, Recorder]:
    agent = AgentInfo(train=0, unit=unit, n_trains=1, n_units=4, mass_kg=8e4, length_m=80.0, offset_m=80.0 * unit,
                      has_reference=has_reference)
    law = Recorder(ControllerParams(), agent, INFO, **kw)
    ahead = NeighbourLink(DB.agent_state(unit - 1).frame_id, DB.agent_aux(unit - 1).frame_id, "intra", "ahead", 80.0 * (unit - 1))
    return Ecu("ecu", agent, law, DB, [ahead], EcuConfig(cycle_s=0.01, neighbour_timeout_s=0.05, reference_timeout_s=0.1)), law


def sensor(unit: int, x: float, v: float, counter: int) -> tuple[int, bytes]:
    c = DB.sensor(unit)
    return c.frame_id, c.encode((x, v), counter)


def state(unit: int, x: float, v: float, counter: int) -> tuple[int, bytes]:
    c = DB.agent_state(unit)
    return c.frame_id, c.encode((x, v), counter)


def test_cycle_decodes_inputs_and_encodes_three_outputs():
    ecu, law = make_ecu()
    ecu.on_frame(*sensor(1, 1000.0, 50.0, 1), t=0.000)
    ecu.on_frame(*state(0, 1080.02, 50.5, 1), t=0.001)
    out = ecu.cycle(0.002)
    x, v, nbrs, _, _ = law.views[-1]
    assert (x, v) == (pytest.approx(1000.0, abs=5e-4), pytest.approx(50.0, abs=2.5e-4))
    assert nbrs[0][0] is True and nbrs[0][1] == pytest.approx(1080.02, abs=5e-4)
    ids = [fid for fid, _ in out]
    assert ids == [DB.traction_cmd(1).frame_id, DB.agent_state(1).frame_id, DB.agent_aux(1).frame_id]
    mode, force = DB.traction_cmd(1).decode(out[0][1])
    assert (mode, force) == (0, 1000.0)
    assert DB.agent_state(1).decode(out[1][1]) == pytest.approx((1000.0, 50.0), abs=5e-4)


def test_the_engine_encodes_a_cycle_s_outputs_in_one_call_as_cycle_would():
    """``cycle_outputs`` are ``cycle``'s frames unencoded; the engine's one call encodes them to the same bytes."""
    import trainhil_engine as engine

    frames, outputs = [], []
    for ecu, take in ((make_ecu()[0], frames), (make_ecu()[0], outputs)):
        ecu.on_frame(*sensor(1, 1000.0, 50.0, 1), t=0.000)
        take.extend(ecu.cycle(0.002) if take is frames else ecu.cycle_outputs(0.002))
    net = engine.Network()
    bus = net.add_bus("b", 500_000)
    sender, (_, inbox) = net.attach_sender(bus, "ecu"), net.attach_inbox(bus, "rx", None)
    net.send_encoded(bus, sender, outputs)
    net.advance(10_000_000)
    assert [(fid, data) for _, fid, data, _ in net.drain_inboxes()] == frames
    with pytest.raises(ValueError, match="NaN|nan"):  # the codec refuses what encode refuses
        net.send_encoded(bus, sender, [(outputs[0][0], (0.0, math.nan), 1)])


def test_a_program_that_overrides_cycle_is_not_encoded_by_the_engine():
    from ecu_sim.runtime import encodes_in_engine

    class Quiet(Ecu):
        def cycle(self, t: float) -> list[tuple[int, bytes]]:
            return []

    ecu = make_ecu()[0]
    assert encodes_in_engine(ecu)
    quiet = Quiet("q", ecu.agent, ecu.controller, DB, [], EcuConfig(cycle_s=0.01))
    assert not encodes_in_engine(quiet)
    ecu.cycle = lambda t: []  # a factory may patch the instance
    assert not encodes_in_engine(ecu)


def test_cycle_and_send_takes_the_engine_path_or_the_frames_and_stops_an_ecu_whose_outputs_are_refused():
    from ecu_sim.runtime import ECU_STOPPED, cycle_and_send, encode_outputs

    sent: list[tuple[str, object, list]] = []
    ecu = make_ecu()[0]
    ecu.on_frame(*sensor(1, 1000.0, 50.0, 1), t=0.0)
    cycle_and_send(ecu, 0.002, "node", lambda k, o: sent.append(("outputs", k, o)), lambda k, f: sent.append(("frames", k, f)))
    assert [(kind, key) for kind, key, _ in sent] == [("outputs", "node")] and len(encode_outputs(sent[0][2])) == 3
    ecu.cycle = lambda t: [(0x123, b"x")]  # a patched program: its frames as they are
    cycle_and_send(ecu, 0.012, "node", lambda k, o: sent.append(("outputs", k, o)), lambda k, f: sent.append(("frames", k, f)))
    assert sent[-1] == ("frames", "node", [(0x123, b"x")])

    def refuse(key, outputs):
        raise ValueError("signal Force is NaN")

    other = make_ecu()[0]
    other.on_frame(*sensor(1, 1000.0, 50.0, 1), t=0.0)
    cycle_and_send(other, 0.002, "node", refuse, lambda k, f: None)
    assert not other.alive and ECU_STOPPED in other.events[-1][2] and "signal Force is NaN" in other.events[-1][2]


def test_corrupted_frame_is_rejected_and_stale_sensor_brakes():
    ecu, law = make_ecu()
    fid, data = sensor(1, 1000.0, 50.0, 1)
    ecu.on_frame(fid, data, 0.0)
    ecu.cycle(0.001)
    bad = bytearray(sensor(1, 2000.0, 50.0, 2)[1])
    bad[3] ^= 0x10  # one flipped bit: the CRC must catch it
    ecu.on_frame(fid, bytes(bad), 0.01)
    ecu.cycle(0.011)
    assert law.views[-1][0] == pytest.approx(1000.0, abs=1e-3)  # the corrupted value was not used
    assert ecu.e2e_summary().get("CRC_ERROR") == 1
    out = ecu.cycle(0.1)  # last good sensor frame is 0.1 s old > 0.05 s timeout
    mode, force = DB.traction_cmd(1).decode(out[0][1])
    assert mode == BrakeMode.SERVICE and force == 0.0
    assert any("sensor data stale" in text for _, _, text in ecu.events)


def test_repeated_counter_is_not_used_as_fresh_data():
    ecu, law = make_ecu()
    ecu.on_frame(*sensor(1, 1000.0, 50.0, 5), t=0.0)
    ecu.cycle(0.001)
    ecu.on_frame(*sensor(1, 1000.5, 50.0, 5), t=0.01)  # same alive counter: a repeated (stuck) frame
    ecu.cycle(0.011)
    assert law.views[-1][0] == pytest.approx(1000.0, abs=1e-3)
    assert ecu.e2e_summary().get("REPEATED") == 1


def test_stale_neighbour_is_left_out():
    ecu, law = make_ecu()
    ecu.on_frame(*state(0, 1080.0, 50.0, 1), t=0.0)
    for k in range(10):
        ecu.on_frame(*sensor(1, 1000.0, 50.0, k + 1), t=0.01 * k)
        ecu.cycle(0.01 * k + 0.001)
    valid = [views[2][0][0] for views in law.views]
    assert valid[:5] == [True] * 5 and valid[-1] is False  # 0.05 s timeout


def test_stale_reference_commands_service_brake_for_pinned_units():
    ecu, law = make_ecu(unit=1, has_reference=True)
    ref = DB.reference
    ecu.on_frame(ref.frame_id, ref.encode((5000.0, 80.0), 1), 0.0)
    outs = []
    for k in range(20):
        ecu.on_frame(*sensor(1, 1000.0, 50.0, (k + 1) % 16), t=0.01 * k)
        outs.append(DB.traction_cmd(1).decode(ecu.cycle(0.01 * k + 0.001)[0][1])[0])
    assert outs[0] == BrakeMode.NORMAL and outs[-1] == BrakeMode.SERVICE
    assert law.views[0][3] is True and law.views[0][4] == pytest.approx(5000.0)


def test_controller_exception_stops_the_ecu_and_is_reported():
    ecu, _ = make_ecu(fail=True)
    ecu.on_frame(*sensor(1, 1000.0, 50.0, 1), t=0.0)
    assert ecu.cycle(0.001) == []
    assert ecu.alive is False and ecu.counters.controller_errors == 1
    assert ecu.events[-1][1] == "ERROR" and "ZeroDivisionError" in ecu.events[-1][2]
    assert ecu.cycle(0.011) == []  # a dead ECU stays silent
    ecu.restart()
    ecu.controller.fail = False
    ecu.on_frame(*sensor(1, 1000.0, 50.0, 2), t=0.02)
    assert len(ecu.cycle(0.021)) == 3


def test_non_finite_force_counts_as_a_controller_fault():
    ecu, law = make_ecu(force=math.nan)
    ecu.on_frame(*sensor(1, 1000.0, 50.0, 1), t=0.0)
    assert ecu.cycle(0.001) == [] and not ecu.alive
    assert "non-finite" in ecu.events[-1][2]
