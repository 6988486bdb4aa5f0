"""The compiled frame engine against the Python implementations it replaced: the same bytes, bits and schedules."""
from __future__ import annotations

import math
import random

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import trainhil_engine as engine
from ecu_sim.codec import TrainDb
from ecu_sim.e2e import e2e_crc as python_e2e_crc
from hil.can.frame import frame_bits_reference
from tests.oracle.python_codec import oracle_codec
from tests.oracle.python_rig import rig_on

DB = TrainDb.load()
CODECS = list(DB.by_name.values())
ORACLES = {c.name: oracle_codec(c) for c in CODECS}


def same_events(py_log, en_log) -> bool:
    """The same events, in time order: the Python model's plant hears a command when it arrives, the engine's at the
    next plant step (hil/runtime/virtual.py), so a plant event may be appended after an ECU event of the same
    instant; the times, sources and texts are identical."""
    def key(log):
        return sorted((e.t, e.source, e.text) for e in log.events)

    return key(py_log) == key(en_log)


def test_every_dbc_message_encodes_to_the_same_bytes_as_the_python_codec():
    rng = random.Random(5)
    for codec in CODECS:
        oracle = ORACLES[codec.name]
        for _ in range(300):
            values = []
            for lo, hi in codec.limits:
                span = hi - lo
                values.append(rng.choice([rng.uniform(lo, hi), rng.uniform(lo - span, hi + span), lo, hi,
                                          round(rng.uniform(lo, hi) / codec.scales[len(values)]) * codec.scales[len(values)]]))
            counter = rng.randrange(16)
            frame = codec.encode(values, counter)
            assert frame == oracle.encode(values, counter), (codec.name, values)
            assert codec.decode(frame) == oracle.decode(frame)
        assert codec.saturations == oracle.saturations, codec.name
        codec.reset_saturations()


@settings(max_examples=300, deadline=None, database=None)
@given(st.sampled_from(CODECS), st.data())
def test_any_frame_decodes_like_the_python_codec(codec, data):
    frame = data.draw(st.binary(min_size=codec.dlc, max_size=codec.dlc))
    assert codec.decode(frame) == ORACLES[codec.name].decode(frame)
    assert codec.crc_ok(frame) == ORACLES[codec.name].crc_ok(frame)


def test_nan_is_an_error_naming_the_signal_in_both():
    codec = DB.sensor(0)
    with pytest.raises(ValueError, match=r"Sensor_U01\.Speed: cannot encode NaN"):
        codec.encode((1.0, math.nan), 0)
    with pytest.raises(ValueError, match=r"Sensor_U01\.Speed: cannot encode NaN"):
        ORACLES[codec.name].encode((1.0, math.nan), 0)


@settings(max_examples=500, deadline=None, database=None)
@given(st.booleans(), st.data())
def test_frame_length_equals_the_bit_by_bit_reference(extended, data):
    can_id = data.draw(st.integers(0, (1 << 29) - 1 if extended else (1 << 11) - 1))
    payload = data.draw(st.binary(max_size=8))
    assert engine.frame_bits(can_id, payload, extended) == frame_bits_reference(can_id, payload, extended)


@settings(max_examples=300, deadline=None, database=None)
@given(st.integers(0, 255), st.binary(min_size=1, max_size=64))
def test_e2e_crc_equals_the_python_table(data_id, payload):
    assert engine.e2e_crc(data_id, payload) == python_e2e_crc(data_id, payload)


# ---------------------------------------------------------------------------------------------- whole runs

from hil.record.metrics import compute_metrics  # noqa: E402
from hil.runtime.virtual import VirtualRig  # noqa: E402
from hil.scenario import load_scenario  # noqa: E402
from hil.scenario.loader import scenario_from_dict  # noqa: E402
from hil.scenario.model import Scenario  # noqa: E402

LOSSY_RADIO = {"radio.loss": {"model": "gilbert_elliott", "p_good_to_bad": 0.1, "p_bad_to_good": 0.3, "loss_bad": 0.8},
               "radio.jitter_s": 0.01, "radio.latency_s": 0.05, "radio.rate_cap_hz": 150.0}


def _schedule_and_log(network: str, scenario, seconds: float):
    """Every frame as (bus, ID, payload, enqueue ns, start ns, end ns), per bus in time order, and the run log."""
    rig = rig_on(network, scenario)
    frames: list[list[tuple]] = [[] for _ in rig.buses]
    for i, bus in enumerate(rig.buses):
        bus.frame_listeners.append(lambda tx, rows=frames[i], i=i: rows.append(
            (i, tx.frame_id, bytes(tx.data), tx.t_enqueue, tx.t_start, tx.t_end)))
    return frames, rig.run(seconds)


@pytest.mark.parametrize("name, overrides", [
    ("seed000", {}),  # 12 ECUs at 100 Hz, 500 kbit/s, priority queues, perfect radio
    ("seed000", {"can.queue_policy": "fifo", "can.bitrate": 125_000}),  # overloaded FIFO bus: inversion and drops
    ("seed000", LOSSY_RADIO),  # Gilbert-Elliott loss, jitter, latency and a rate cap on the radio
    ("seed001", {}),  # one train, 5 ms cycles, AgentAux exchange
], ids=["seed000", "fifo-125k", "lossy-radio", "seed001"])
def test_engine_and_python_model_give_the_same_frames_and_signals(name, overrides):
    sc = load_scenario(name, overrides)
    py_frames, py_log = _schedule_and_log("python", sc, 10.0 if name == "seed000" and not overrides else 4.0)
    en_frames, en_log = _schedule_and_log("engine", sc, 10.0 if name == "seed000" and not overrides else 4.0)
    assert sum(map(len, en_frames)) > 1000
    for bus, (a, b) in enumerate(zip(py_frames, en_frames)):
        assert len(a) == len(b), f"bus{bus + 1}: {len(a)} frames in the Python model, {len(b)} in the engine"
        first = next((k for k, (x, y) in enumerate(zip(a, b)) if x != y), None)
        assert first is None, f"bus{bus + 1} frame {first}: Python {a[first]} != engine {b[first]}"
    assert np.array_equal(py_log.signals.array, en_log.signals.array)  # bit for bit
    for x, y in zip(py_log.buses, en_log.buses):
        assert np.array_equal(x.frames.array, y.frames.array) and np.array_equal(x.load.array, y.load.array)
        assert (x.frames_sent, x.frames_dropped) == (y.frames_sent, y.frames_dropped)
    assert py_log.e2e == en_log.e2e and py_log.radio_stats == en_log.radio_stats
    assert py_log.frames_lost == en_log.frames_lost and py_log.codec_saturations == en_log.codec_saturations
    assert same_events(py_log, en_log)
    for bus in en_log.buses:  # each node that dropped frames said so once, at its first (the same in both)
        said = [e.text.split()[1] for e in en_log.events if e.source == bus.name and " dropped frame " in e.text]
        assert sorted(said) == sorted(bus.dropped_by_node), (bus.name, said, bus.dropped_by_node)


def test_an_ecu_that_crashes_with_frames_queued_says_how_many_it_lost_on_both_models():
    """An ECU whose TX queue is full (an overloaded 125 kbit/s FIFO bus) crashes: its queued frames are dropped and
    counted, and a WARN event from its bus at the crash says how many, as a real-time server says a node's leave."""
    data = load_scenario("seed000", {"can.queue_policy": "fifo", "can.bitrate": 125_000}).model_dump()
    data["faults"] = [{"kind": "ecu_crash", "train": 1, "unit": 3, "at_s": 1.0}]
    sc = scenario_from_dict(data, "crash-on-a-full-queue")
    (_, py_log), (_, en_log) = (_schedule_and_log(network, sc, 2.0) for network in ("python", "engine"))
    assert same_events(py_log, en_log)
    left = [e for e in en_log.events if " left (crashed)" in e.text]
    assert [(e.t, e.level, e.source) for e in left] == [(1.0, "WARN", "bus1")], left
    assert left[0].text == "node ECU_U03 left (crashed); 64 queued frames dropped"  # its whole TX queue


def _faults_with_every_bus_fault() -> Scenario:
    """The faults scenario (an ECU crash and restart, a babbler, a corruption burst that drives nodes bus-off) with
    error flags and frame drops added on bus 2, each selecting frames by ID and by chance."""
    data = load_scenario("faults").model_dump()
    data["faults"] += [
        {"kind": "bus_error_frames", "train": 2, "at_s": 9.0, "duration_s": 2.0, "probability": 0.3,
         "frame_ids": [0x101, 0x102, 0x103]},
        {"kind": "frame_drop", "train": 2, "at_s": 10.0, "duration_s": 3.0, "probability": 0.5, "frame_ids": [0x102]},
        {"kind": "bus_corruption", "train": 3, "bits": 1, "at_s": 14.0, "duration_s": 1.0, "probability": 0.2}]
    return scenario_from_dict(data, "faults-every-bus-fault")


def test_bus_faults_and_error_confinement_run_on_the_engine_as_on_the_python_model():
    """Corruption judged bit by bit (stuff, form and CRC errors, and corruptions CAN misses), error flags, frame
    drops, a babbling node and the guardian, error frames and retransmission, error passive, bus-off and recovery:
    the same frames, signals, events and CAN error counts from the engine and the Python bus model (17 s)."""
    sc = _faults_with_every_bus_fault()
    runs = []
    for network in ("python", "engine"):
        frames, log = _schedule_and_log(network, sc, 17.0)
        runs.append((frames, log, compute_metrics(log, sc.plant.coupler_band_m)))
    (py_frames, py_log, py_m), (en_frames, en_log, en_m) = runs
    for bus, (a, b) in enumerate(zip(py_frames, en_frames)):
        first = next((k for k, (x, y) in enumerate(zip(a, b)) if x != y), None)
        assert first is None and len(a) == len(b), f"bus{bus + 1} frame {first}: {a[first:first + 1]} != {b[first:first + 1]}"
    assert np.array_equal(py_log.signals.array, en_log.signals.array)
    assert same_events(py_log, en_log)
    for x, y in zip(py_log.buses, en_log.buses):
        assert np.array_equal(x.frames.array, y.frames.array) and np.array_equal(x.load.array, y.load.array)
        assert (x.frames_sent, x.frames_dropped) == (y.frames_sent, y.frames_dropped)
    assert py_m["faults"] == en_m["faults"]
    can = en_m["faults"]["can_errors"]
    bus1, bus2, bus3 = (can["buses"][f"bus{i}"] for i in (1, 2, 3))
    assert {"stuff", "crc", "form"} <= set(bus1["by_error"]) and any(n["bus_off"] for n in bus1["nodes"].values())
    assert bus2["injected_error_flags"] > 10 and bus2["dropped_by_fault"] > 10
    assert bus3["babbled"] > 1000 and bus3["babbling_detections"] == 1
    assert any("recovered from bus-off" in e.text for e in en_log.events)


def _faults_without_bus_faults() -> Scenario:
    """The faults scenario with its ECU crash (and restart policy) kept, its bus faults and its late tunnel swapped
    for an ECU hang, a stuck sensor, a traction loss and three radio faults: nothing the engine lacks."""
    data = load_scenario("faults").model_dump()
    data["faults"] = [f for f in data["faults"] if f["kind"] == "ecu_crash"] + [
        {"kind": "ecu_hang", "train": 1, "unit": 2, "at_s": 3.0, "duration_s": 2.5},
        {"kind": "sensor_stuck", "train": 3, "unit": 1, "at_s": 4.0, "duration_s": 2.0},
        {"kind": "traction_loss", "train": 1, "unit": 4, "at_s": 6.0, "duration_s": 2.0},
        {"kind": "radio_burst_loss", "pair": 1, "at_s": 2.0, "duration_s": 3.0, "probability": 0.5},
        {"kind": "radio_burst_loss", "pair": 1, "at_s": 3.0, "duration_s": 3.0, "probability": 0.3},
        {"kind": "radio_latency", "pair": 2, "at_s": 4.0, "duration_s": 3.0, "latency_s": 0.05},
        {"kind": "radio_blackout", "pair": 1, "at_s": 7.0, "duration_s": 2.0}]
    return scenario_from_dict(data, "faults-without-bus-faults")


def test_ecu_sensor_actuator_and_radio_faults_run_on_the_engine_as_on_the_python_model():
    """A crash and a watchdog restart (the ECU's node leaves the bus and a new one joins), a hang, a stuck sensor, a
    traction loss, overlapping radio burst losses, a radio latency and a radio blackout: the same frames, signals,
    events, radio counters and fault verdicts from both bus models (12 s); only the Python model's CAN error
    counters (all zero here) are not in the engine's report."""
    sc = _faults_without_bus_faults()
    runs = []
    for network in ("python", "engine"):
        frames, log = _schedule_and_log(network, sc, 12.0)
        runs.append((frames, log, compute_metrics(log, sc.plant.coupler_band_m)))
    (py_frames, py_log, py_m), (en_frames, en_log, en_m) = runs
    assert sum(map(len, en_frames)) > 50_000 and py_frames == en_frames
    assert np.array_equal(py_log.signals.array, en_log.signals.array)
    assert same_events(py_log, en_log)
    assert any("restart" in e.text for e in en_log.events)  # the crashed ECU came back, on a new node
    assert py_m["faults"] == en_m["faults"] and en_m["faults"]["injected"] == 8
    assert py_log.radio_stats == en_log.radio_stats and en_log.radio_stats["1>2"]["fault"] > 100


def test_the_bus_model_is_a_leaf_and_node_processes_do_not_import_the_server():
    """hil/can imports nothing of the recording or the runtimes; the real-time nodes do not load the bus server."""
    import subprocess
    import sys

    code = ("import sys, hil.can.transmission, hil.can.error_events, hil.can.frame, hil.can.bus_log, hil.can.wcrt; "
            "bad = [m for m in sys.modules if m.startswith(('hil.record', 'hil.runtime'))]; assert not bad, bad; "
            "import hil.runtime.realtime.ecu_node, hil.runtime.realtime.plant_node, hil.runtime.realtime.radio_node; "
            "assert 'tests.oracle.python_server' not in sys.modules")
    subprocess.run([sys.executable, "-c", code], check=True)


def test_an_inbox_node_hands_over_its_frames_in_arrival_order():
    """The engine's generic inbox (a node whose frames Python drains) keeps the order and end times of the bus."""
    net = engine.Network()
    bus = net.add_bus("bus1", 500_000)
    sender = net.attach_sender(bus, "tx")
    node, inbox = net.attach_inbox(bus, "rx", [0x10, 0x20])
    net.every(0, 0)
    assert net.advance(10**9) is not None
    for fid in (0x20, 0x30, 0x10):
        net.send(bus, sender, fid, bytes(8))
    assert net.advance(10**9) is None
    frames = net.drain_inboxes()
    assert [(i, fid) for i, fid, _, _ in frames] == [(inbox, 0x10), (inbox, 0x20)]  # 0x30 is not in the filter
    t = [t_end for _, _, _, t_end in frames]
    assert t[0] == engine.frame_bits(0x10, bytes(8)) * 2000 and t[1] > t[0]
    assert net.drain_inboxes() == []



# ---------------------------------------------------------------------------------------------- the CAN receiver

from tests.oracle.bus_errors import corrupt, receive, wire_bits  # noqa: E402


def _engine_reception(wire: list[int]) -> tuple:
    error, at, can_id, extended, data = engine.receive_wire(wire)
    return (error, at) if error else (None, at, can_id, extended, data)


def _python_reception(wire: list[int]) -> tuple:
    r = receive(wire)
    return (r.error, r.at) if r.error else (None, r.at, r.can_id, r.extended, r.data)


@settings(max_examples=400, deadline=None, database=None)
@given(st.booleans(), st.data())
def test_the_engines_receiver_judges_every_corrupted_frame_like_the_python_one(extended, data):
    """The same error, at the same bit, for any frame with any bits flipped (SOF to the end of EOF)."""
    can_id = data.draw(st.integers(0, (1 << 29) - 1 if extended else (1 << 11) - 1))
    payload = data.draw(st.binary(max_size=8))
    wire = wire_bits(can_id, payload, extended)
    assert list(engine.wire_bits(can_id, payload, extended)) == wire
    flips = data.draw(st.lists(st.integers(1, len(wire) - 1), max_size=8, unique=True))
    seen = corrupt(wire, flips)
    assert _engine_reception(seen) == _python_reception(seen)


def test_a_corruption_that_makes_another_valid_frame_is_accepted_by_both_receivers():
    """CAN's residual error: flipping exactly the bits in which two frames of the same length differ gives a frame
    every check passes; both receivers accept it with the other frame's ID and data."""
    rng = random.Random(11)
    accepted = 0
    for _ in range(300):
        a, b = (wire_bits(rng.randrange(1 << 11), bytes(rng.randrange(256) for _ in range(2))) for _ in range(2))
        if len(a) != len(b) or a == b:
            continue
        seen = corrupt(a, [k for k in range(len(a)) if a[k] != b[k]])
        assert seen == b and _engine_reception(seen) == _python_reception(seen)
        accepted += _python_reception(seen)[0] is None
    assert accepted > 50


def test_the_engine_continues_a_numpy_stream_and_draws_corrupted_bits_alike():
    """Two-bit corruptions of 70 % of the frames on a bus: the engine, handed the streams' states, hits the same
    frames and flips the same bits as the Python model (a partial Fisher-Yates shuffle over its numpy stream), so
    the same errors are found and the retransmitted frames go at the same times."""
    from tests.oracle.bus_errors import BusErrors, Corruption
    from hil.faults.bus import rng_state
    from hil.runtime.kernel import Kernel
    from tests.oracle.python_bus import VirtualCanBus

    kernel = Kernel()
    bus = VirtualCanBus(kernel, "b", 500_000)
    errors = BusErrors(bus, None, np.random.default_rng(7))
    errors.corruptions.append(Corruption(np.random.default_rng(8), probability=0.7, bits=2))
    a = bus.attach("A")
    bus.attach("B", lambda *x: None)
    py_frames: list[tuple[int, int, int]] = []
    bus.frame_listeners.append(lambda tx: py_frames.append((tx.frame_id, tx.t_start, tx.t_end)))
    for k in range(40):
        kernel.at(k * 1_000_000, lambda _, k=k: bus.send(a, 0x100 + k, bytes([k]) * 8))
    kernel.run(50_000_000)

    net = engine.Network()
    nb = net.add_bus("b", 500_000)
    na = net.attach_sender(nb, "A")
    net.attach_inbox(nb, "B", None)
    net.enable_bus_errors(nb, rng_state(np.random.default_rng(7)))
    net.add_bus_fault(nb, 0, "corruption", rng_state(np.random.default_rng(8)), 0.7, None, None, 2)
    net.set_trace(nb, True)
    net.every(0, 1_000_000)
    for k in range(40):
        assert net.advance(50_000_000) is not None
        net.send(nb, na, 0x100 + k, bytes([k]) * 8)
    while net.advance(50_000_000) is not None:
        pass
    en_frames = [(fid, t_start, t_end) for fid, _, _, _, t_start, t_end, *_ in net.take_trace(nb)]
    assert len(py_frames) > 10 and en_frames == py_frames  # the others were lost when A went bus-off
    summary = net.bus_errors(nb)
    assert errors.stats["rejected"] > 10 and summary["by_error"] == errors.by_error
    assert {k: summary[k] for k in errors.stats} == errors.stats


def test_bad_bus_fault_arguments_are_refused_and_leave_the_bus_as_it_was():
    from hil.faults.bus import rng_state

    net = engine.Network()
    bus = net.add_bus("b", 500_000)
    net.enable_bus_errors(bus, rng_state(np.random.default_rng(1)))
    with pytest.raises(ValueError, match="at least 1 bit"):
        net.add_bus_fault(bus, 0, "corruption", rng_state(np.random.default_rng(2)), 1.0, None, None, 0)
    with pytest.raises(ValueError, match="probability 1.5"):
        net.add_bus_fault(bus, 0, "drops", rng_state(np.random.default_rng(2)), 1.5, None, None)
    with pytest.raises(ValueError, match="corruption, error_flags or drops"):
        net.add_bus_fault(bus, 0, "smoke", rng_state(np.random.default_rng(2)), 1.0, None, None)
    with pytest.raises(ValueError, match="can_id"):
        net.start_babbler(bus, 1, "Babbler#1", 0x800, bytes(8), False)  # not an 11-bit ID
    assert net.nodes(bus) == []  # the refused babbler did not join


def test_the_network_seams_are_protocols_that_the_engine_and_the_oracle_meet():
    """hil/runtime/kernel.py: EventKernel and hil/can/train_bus.py: TrainBus: the engine's and the oracle's meet them."""
    from hil.can.train_bus import TrainBus
    from hil.runtime.kernel import EventKernel
    from hil.runtime.kernel import Kernel
    from tests.oracle.python_rig import PythonNetworkRig

    sc = load_scenario("seed000")
    for rig in (VirtualRig(sc), PythonNetworkRig(sc)):
        assert isinstance(rig.kernel, EventKernel) and all(isinstance(b, TrainBus) for b in rig.buses)
    assert isinstance(Kernel(), EventKernel)
